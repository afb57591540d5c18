//! Renderer selection: the global `--device cpu|gpu|auto` flag and [`AnyRenderer`], the one
//! renderer type stages hold (CPU or GPU behind the same traits).
//!
//! The default is `cpu` (bit-deterministic, and no graphics driver is loaded). `auto` takes a
//! hardware GPU adapter when one exists and the CPU otherwise; software adapters (Mesa's
//! lavapipe, WARP) are used only with an explicit `--device gpu`, so `auto` stays on the
//! deterministic CPU path in CI.

use super::super::cpu::SavedForBackward;
use super::super::{
    Convergence, ConvergenceTest, CpuRenderer, DifferentiableRenderer, Error, ImageGrads,
    RasterPass, RenderCamera, RenderOutput, RenderSettings, Renderer, SplatGrads, SplatInputs,
};
use super::{GpuRenderer, GpuSaved};

/// Where to rasterize.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Device {
    /// The CPU reference renderer (bit-deterministic; the default).
    #[default]
    Cpu,
    /// A GPU through wgpu; software adapters (lavapipe) count. An error when there is none.
    Gpu,
    /// A hardware GPU adapter if there is one, else the CPU.
    Auto,
}

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
    /// GPU state.
    Gpu(GpuSaved),
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
    /// Open the renderer `device` asks for.
    pub fn open(device: Device) -> Result<AnyRenderer, Error> {
        Ok(match device {
            Device::Cpu => AnyRenderer::Cpu(CpuRenderer),
            Device::Gpu => AnyRenderer::Gpu(
                GpuRenderer::new(true)?
                    .ok_or_else(|| Error::Gpu("--device gpu: no GPU adapter found".into()))?,
            ),
            Device::Auto => match GpuRenderer::new(false)? {
                Some(g) => AnyRenderer::Gpu(g),
                None => AnyRenderer::Cpu(CpuRenderer),
            },
        })
    }

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

impl Renderer for AnyRenderer {
    fn render(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
    ) -> Result<RenderOutput, Error> {
        match self {
            AnyRenderer::Cpu(r) => r.render(camera, inputs, settings),
            AnyRenderer::Gpu(r) => r.render(camera, inputs, settings),
        }
    }

    fn convergence(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        pixel_pass: &[bool],
    ) -> Result<Convergence, Error> {
        match self {
            AnyRenderer::Cpu(r) => r.convergence(camera, inputs, settings, pixel_pass),
            AnyRenderer::Gpu(r) => r.convergence(camera, inputs, settings, pixel_pass),
        }
    }
}

impl DifferentiableRenderer for AnyRenderer {
    type Saved = AnySaved;

    fn render_with_saved(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        pass: RasterPass,
    ) -> Result<(RenderOutput, AnySaved), Error> {
        Ok(match self {
            AnyRenderer::Cpu(r) => {
                let (o, s) = r.render_with_saved(camera, inputs, settings, pass)?;
                (o, AnySaved::Cpu(s))
            }
            AnyRenderer::Gpu(r) => {
                let (o, s) = r.render_with_saved(camera, inputs, settings, pass)?;
                (o, AnySaved::Gpu(s))
            }
        })
    }

    fn backward(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        saved: &AnySaved,
        grads: &ImageGrads,
    ) -> Result<SplatGrads, Error> {
        match (self, saved) {
            (AnyRenderer::Cpu(r), AnySaved::Cpu(s)) => {
                r.backward(camera, inputs, settings, s, grads)
            }
            (AnyRenderer::Gpu(r), AnySaved::Gpu(s)) => {
                r.backward(camera, inputs, settings, s, grads)
            }
            _ => Err(mismatch()),
        }
    }

    fn convergence_saved(
        &self,
        camera: &RenderCamera,
        settings: &RenderSettings,
        saved: &AnySaved,
        pixel_pass: &[bool],
        test: ConvergenceTest,
    ) -> Result<Vec<bool>, Error> {
        match (self, saved) {
            (AnyRenderer::Cpu(r), AnySaved::Cpu(s)) => {
                r.convergence_saved(camera, settings, s, pixel_pass, test)
            }
            (AnyRenderer::Gpu(r), AnySaved::Gpu(s)) => {
                r.convergence_saved(camera, settings, s, pixel_pass, test)
            }
            _ => Err(mismatch()),
        }
    }
}
