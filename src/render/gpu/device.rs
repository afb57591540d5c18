//! [`AnyRenderer`], the one renderer type stages hold: the CPU or the GPU renderer behind the
//! same traits (`stages::device` picks one from `--device`).

use super::super::cpu::SavedForBackward;
use super::super::{
    ConvergenceTest, CpuRenderer, Cutoff, DifferentiableRenderer, Error, ImageGrads, RenderCamera,
    RenderOutput, RenderSettings, SplatGrads, SplatInputs,
};
use super::{GpuRenderer, GpuSaved};

/// The CPU or the GPU renderer.
#[derive(Debug, Clone)]
pub enum AnyRenderer {
    /// [`CpuRenderer`].
    Cpu(CpuRenderer),
    /// [`GpuRenderer`].
    Gpu(GpuRenderer),
}

/// Saved forward state of either renderer.
#[derive(Debug)]
pub enum AnySaved {
    /// CPU state.
    Cpu(SavedForBackward),
    /// GPU state (boxed: it holds the frame's buffer handles).
    Gpu(Box<GpuSaved>),
}

impl AnySaved {
    /// M, the number of (tile, Gaussian) intersections of the saved render.
    pub fn num_pairs(&self) -> usize {
        match self {
            AnySaved::Cpu(s) => s.isect.keys.len(),
            AnySaved::Gpu(s) => s.num_pairs,
        }
    }
}

impl AnyRenderer {
    /// `cpu`, or `gpu:<adapter>`: what produced a result (part of pipeline cache keys).
    pub fn tag(&self) -> String {
        match self {
            AnyRenderer::Cpu(_) => "cpu".into(),
            AnyRenderer::Gpu(g) => format!("gpu:{}", g.adapter()),
        }
    }
}

fn mismatch() -> Error {
    Error::Settings("saved forward state belongs to the other renderer".into())
}

super::super::render_is_forward!(AnyRenderer);

impl DifferentiableRenderer for AnyRenderer {
    type Saved = AnySaved;

    fn render_with_saved(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        cutoff: Cutoff,
    ) -> Result<(RenderOutput, AnySaved), Error> {
        Ok(match self {
            AnyRenderer::Cpu(r) => {
                let (o, s) = r.render_with_saved(cam, inputs, settings, cutoff)?;
                (o, AnySaved::Cpu(s))
            }
            AnyRenderer::Gpu(r) => {
                let (o, s) = r.render_with_saved(cam, inputs, settings, cutoff)?;
                (o, AnySaved::Gpu(Box::new(s)))
            }
        })
    }

    fn backward(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        saved: &AnySaved,
        grads: &ImageGrads,
    ) -> Result<SplatGrads, Error> {
        match (self, saved) {
            (AnyRenderer::Cpu(r), AnySaved::Cpu(s)) => r.backward(cam, inputs, settings, s, grads),
            (AnyRenderer::Gpu(r), AnySaved::Gpu(s)) => r.backward(cam, inputs, settings, s, grads),
            _ => Err(mismatch()),
        }
    }

    fn convergence_saved(
        &self,
        cam: &RenderCamera,
        settings: &RenderSettings,
        saved: &AnySaved,
        pixel_pass: &[bool],
        test: ConvergenceTest,
    ) -> Result<Vec<bool>, Error> {
        match (self, saved) {
            (AnyRenderer::Cpu(r), AnySaved::Cpu(s)) => {
                r.convergence_saved(cam, settings, s, pixel_pass, test)
            }
            (AnyRenderer::Gpu(r), AnySaved::Gpu(s)) => {
                r.convergence_saved(cam, settings, s, pixel_pass, test)
            }
            _ => Err(mismatch()),
        }
    }
}
