//! The GPU rasterizer on wgpu (WGSL kernels in `shaders/`), implementing
//! [`Renderer`](super::Renderer) and [`DifferentiableRenderer`] with the CPU renderer's
//! semantics.
//!
//! Stages, one kernel each (gsplat's / Brush's structure): `project` (EWA projection, 0.3 px
//! low-pass, opacity-aware extent, the CPU's culling of poisoned inputs, SH colour in the
//! world or local frame, tile counts) → exclusive prefix sum of the counts → `emit` the
//! (tile, depth) pairs → stable 4-bit LSD radix sort (depth bits, then tile bits) → tile
//! `ranges` → `rasterize_fwd` (one 16x16 workgroup per tile, front to back, per-Gaussian
//! Σ(T·α)², Σ T·α and pixel counts). Backward: `rasterize_bwd` (back to front from each
//! pixel's last contributor) → `project_bwd` (projection and SH VJPs). Convergence:
//! `fail_pairs` and `centre` on the saved forward state.
//!
//! Per-pixel arithmetic mirrors [`super::cpu::blend`] operation for operation (same exp
//! polynomial, same evaluation order), so skip decisions agree with the CPU; sums that the
//! GPU accumulates with atomics (statistics, gradients) are in a different order, so GPU
//! results are **not bitwise deterministic**: they match the CPU within the tolerances of
//! `gpu::tests` (images 1e-4 absolute, statistics 1e-4 relative, gradients 1e-3 relative).
//!
//! Buffers live in [`frame::Frame`]s reused across renders of the same sizes; a render
//! does one readback (images, statistics, and the pair count, which grows the intersection
//! buffer and re-renders in the frame that overflows it; later frames start at the grown
//! size).

mod context;
mod device;
mod frame;
mod params;
#[cfg(test)]
mod tests;

pub use context::GpuContext;
pub use device::{AnyRenderer, AnySaved};

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use frame::{
    Frame, FrameKey, FramePool, PooledFrame, bind, dispatch, grid, read_words, sort_passes,
};
use params::ColorMode;

use super::cpu::check_inputs;
use super::{
    ColorSource, ConvergenceTest, Cutoff, DifferentiableRenderer, Error, ImageGrads, RenderAux,
    RenderCamera, RenderOutput, RenderSettings, ShFrame, SplatGrads, SplatInputs, check_saved, sh,
};

/// The GPU rasterizer. Cheap to clone (shares the device and the buffer pool).
#[derive(Clone)]
pub struct GpuRenderer {
    ctx: Arc<GpuContext>,
    pool: Arc<FramePool>,
    /// The largest intersection capacity a frame has needed: later frames start there, so
    /// that a scene whose frames all overflow the first guess grows it once, not per frame.
    pair_cap: Arc<AtomicUsize>,
    junk: bool,
}

impl std::fmt::Debug for GpuRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuRenderer({}, {:?})", self.ctx.info.name, self.ctx.info.backend)
    }
}

/// Forward state kept on the device for [`DifferentiableRenderer::backward`] and
/// [`DifferentiableRenderer::convergence_saved`]: the frame's buffers (projected splats,
/// channels, sorted intersections, tile ranges, final transmittance, last contributors).
pub struct GpuSaved {
    frame: std::sync::Mutex<PooledFrame>,
    /// Which ping-pong half holds the sorted pairs.
    sorted: usize,
    n: usize,
    width: u32,
    height: u32,
    /// M, the number of (tile, Gaussian) intersections.
    pub num_pairs: usize,
}

impl std::fmt::Debug for GpuSaved {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuSaved(n = {}, {}x{})", self.n, self.width, self.height)
    }
}

fn gpu_err(e: impl std::fmt::Display) -> Error {
    Error::Gpu(e.to_string())
}

impl GpuRenderer {
    /// Open a GPU (see [`GpuContext::new`]); `Ok(None)` when there is no usable adapter.
    pub fn new(allow_software: bool) -> Result<Option<GpuRenderer>, Error> {
        Ok(GpuContext::new(allow_software)?.map(|ctx| GpuRenderer {
            ctx: Arc::new(ctx),
            pool: Arc::default(),
            pair_cap: Arc::default(),
            junk: false,
        }))
    }

    /// The adapter's name and backend.
    pub fn adapter(&self) -> String {
        format!("{} ({:?})", self.ctx.info.name, self.ctx.info.backend)
    }

    /// Test mode: fill every buffer with junk before each use.
    #[cfg(test)]
    pub(crate) fn with_junk(mut self) -> Self {
        self.junk = true;
        self
    }

    fn key(cam: &RenderCamera, inputs: &SplatInputs, pair_cap: usize) -> FrameKey {
        let color_stride = match inputs.colors {
            ColorSource::Rgb(_) => 3,
            ColorSource::Sh { degree, .. } => 3 * sh::num_basis(degree),
        };
        FrameKey {
            n: inputs.means.len(),
            nc: 4 + inputs.num_features,
            color_stride,
            nf: inputs.num_features,
            w: cam.width as usize,
            h: cam.height as usize,
            pair_cap,
        }
    }

    fn run_forward(
        &self,
        frame: &mut Frame,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        cutoff: Cutoff,
    ) -> Result<(usize, Vec<u32>), Error> {
        let ctx = &*self.ctx;
        let k = &ctx.kernels;
        let key = frame.key;
        let n = key.n;
        let (mode, degree) = match inputs.colors {
            ColorSource::Rgb(_) => (ColorMode::Rgb, 0),
            ColorSource::Sh { degree, frame: ShFrame::World, .. } => (ColorMode::ShWorld, degree),
            ColorSource::Sh { degree, frame: ShFrame::Local, .. } => (ColorMode::ShLocal, degree),
        };
        let smooth = cutoff == Cutoff::Smooth;
        let params = params::pack(cam, settings, &key, mode, degree, smooth);
        let q = &ctx.queue;
        q.write_buffer(&frame.params, 0, bytemuck::cast_slice(&params));
        let mut geom = Vec::with_capacity(n * 11);
        for i in 0..n {
            geom.extend_from_slice(&inputs.means[i]);
            geom.extend_from_slice(&inputs.quats[i]);
            geom.extend_from_slice(&inputs.scales[i]);
            geom.push(inputs.opacities[i]);
        }
        q.write_buffer(&frame.geom, 0, bytemuck::cast_slice(&geom));
        let colors: Vec<f32> = match inputs.colors {
            ColorSource::Rgb(rgb) => rgb.concat(),
            ColorSource::Sh { dc, rest, .. } => {
                let k3 = key.color_stride - 3;
                let mut c = Vec::with_capacity(n * key.color_stride);
                for i in 0..n {
                    c.extend_from_slice(&dc[i]);
                    c.extend_from_slice(&rest[i * k3..(i + 1) * k3]);
                }
                c
            }
        };
        if !colors.is_empty() {
            q.write_buffer(&frame.colors, 0, bytemuck::cast_slice(&colors));
        }
        if !inputs.features.is_empty() {
            q.write_buffer(&frame.feats, 0, bytemuck::cast_slice(inputs.features));
        }

        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&frame.stats, 0, None);
        let gauss_groups = grid((n + 1).div_ceil(256));
        let g = bind(
            ctx,
            &k.project.layout,
            &[
                &frame.params,
                &frame.geom,
                &frame.colors,
                &frame.feats,
                &frame.splats,
                &frame.chans,
                &frame.counts,
                &frame.stats,
            ],
        );
        dispatch(&mut enc, k.project.pipeline("main"), &g, gauss_groups);
        self.scan(&mut enc, &frame.counts, &frame.count_scan);
        let emit =
            |enc: &mut wgpu::CommandEncoder, half: &[wgpu::Buffer; 3], entry: &str, groups| {
                let g = bind(
                    ctx,
                    &k.isect.layout,
                    &[
                        &frame.params,
                        &frame.splats,
                        &frame.counts,
                        &half[0],
                        &half[1],
                        &half[2],
                        &frame.tile_offsets,
                    ],
                );
                dispatch(enc, k.isect.pipeline(entry), &g, groups);
            };
        emit(&mut enc, &frame.pairs[0], "emit", gauss_groups);
        let mut cur = 0;
        let blocks = key.sort_blocks();
        for (p, _) in sort_passes(key.num_tiles()).iter().enumerate() {
            let (src, dst) = (&frame.pairs[cur], &frame.pairs[1 - cur]);
            let g = bind(
                ctx,
                &k.sort.layout,
                &[
                    &frame.sort_params[p],
                    &frame.counts,
                    &src[0],
                    &src[1],
                    &src[2],
                    &frame.hist,
                    &dst[0],
                    &dst[1],
                    &dst[2],
                ],
            );
            dispatch(&mut enc, k.sort.pipeline("count"), &g, grid(blocks));
            self.scan(&mut enc, &frame.hist, &frame.hist_scan);
            dispatch(&mut enc, k.sort.pipeline("scatter"), &g, grid(blocks));
            cur = 1 - cur;
        }
        emit(&mut enc, &frame.pairs[cur], "ranges", grid((key.pair_cap + 1).div_ceil(256)));
        let g = bind(
            ctx,
            &k.fwd.layout,
            &[
                &frame.params,
                &frame.splats,
                &frame.chans,
                &frame.tile_offsets,
                &frame.pairs[cur][2],
                &frame.img,
                &frame.final_t,
                &frame.last,
                &frame.stats,
            ],
        );
        let tiles = (key.w.div_ceil(16) as u32, key.h.div_ceil(16) as u32);
        dispatch(&mut enc, k.fwd.pipeline("main"), &g, tiles);
        let (px, nc) = (key.pixels() as u64, key.nc as u64);
        let mut off = 0;
        for (buf, len) in
            [(&frame.img, px * nc), (&frame.final_t, px), (&frame.stats, 4 * n as u64)]
        {
            if len > 0 {
                enc.copy_buffer_to_buffer(buf, 0, &frame.staging, off, 4 * len);
            }
            off += 4 * len;
        }
        enc.copy_buffer_to_buffer(&frame.counts, 0, &frame.staging, off, 4 * (n as u64 + 1));
        q.submit([enc.finish()]);
        let words = read_words(ctx, &frame.staging, key.fwd_readback_len()).map_err(gpu_err)?;
        Ok((cur, words))
    }

    /// Record an in-place exclusive prefix sum of `data` with the buffers of `plan`.
    fn scan(&self, enc: &mut wgpu::CommandEncoder, data: &wgpu::Buffer, plan: &frame::ScanPlan) {
        let k = &self.ctx.kernels.scan;
        let levels = &plan.levels;
        let groups: Vec<wgpu::BindGroup> = (0..levels.len())
            .map(|l| {
                let d = if l == 0 { data } else { &levels[l - 1].sums };
                bind(&self.ctx, &k.layout, &[&levels[l].params, d, &levels[l].sums])
            })
            .collect();
        for (l, g) in groups.iter().enumerate() {
            dispatch(enc, k.pipeline("scan_blocks"), g, grid(levels[l].len.div_ceil(256)));
        }
        for l in (0..levels.len().saturating_sub(1)).rev() {
            dispatch(enc, k.pipeline("add_sums"), &groups[l], grid(levels[l].len.div_ceil(256)));
        }
    }
}

/// Images and statistics from the forward readback (the CPU's `assemble`).
fn assemble(key: &FrameKey, settings: &RenderSettings, words: &[u32]) -> RenderOutput {
    let (w, h, nc, nf, n) = (key.w, key.h, key.nc, key.nf, key.n);
    let f = |i: usize| f32::from_bits(words[i]);
    let t_at = w * h * nc;
    let s_at = t_at + w * h;
    let o_at = s_at + 4 * n;
    let ch = |p: usize, c: usize| f(p * nc + c);
    let mut out = RenderOutput::compose(
        (w, h, nf),
        RenderAux::culled(n),
        ch,
        |p| f(t_at + p),
        settings.background,
    );
    let a = &mut out.aux;
    for g in 0..n {
        a.visible[g] = words[o_at + g + 1] > words[o_at + g];
        a.radius_px[g] = f(s_at + 4 * g + 3);
        a.sum_w2[g] = f(s_at + 4 * g);
        a.sum_w[g] = f(s_at + 4 * g + 1);
        a.n_pixels[g] = f(s_at + 4 * g + 2) as u32;
    }
    out
}

super::render_is_forward!(GpuRenderer);

impl DifferentiableRenderer for GpuRenderer {
    type Saved = GpuSaved;

    /// Upload the inputs and run the forward stages; one readback (`[H, W, C]` image,
    /// `[H, W]` T, `[N, 4]` statistics, M). A frame whose pairs overflow the intersection
    /// buffer is rendered again with a larger one.
    fn render_with_saved(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        cutoff: Cutoff,
    ) -> Result<(RenderOutput, GpuSaved), Error> {
        check_inputs(cam, inputs, settings)?;
        let _span = tracing::debug_span!("render.gpu.forward", n = inputs.means.len()).entered();
        let n = inputs.means.len();
        let mut cap = (4 * n).max(1 << 14).max(self.pair_cap.load(Ordering::Relaxed));
        loop {
            let key = Self::key(cam, inputs, cap);
            let mut frame = self.pool.take(&self.ctx, key);
            if self.junk {
                frame.fill_junk(&self.ctx);
            }
            let (sorted, words) = self.run_forward(&mut frame, cam, inputs, settings, cutoff)?;
            let m = *words.last().expect("pair count") as usize;
            if m > frame.key.pair_cap {
                cap = m + m / 4;
                self.pair_cap.fetch_max(cap, Ordering::Relaxed);
                drop(frame);
                continue;
            }
            let out = assemble(&frame.key, settings, &words);
            let saved = GpuSaved {
                frame: std::sync::Mutex::new(PooledFrame {
                    frame: Some(frame),
                    pool: self.pool.clone(),
                }),
                sorted,
                n,
                width: cam.width,
                height: cam.height,
                num_pairs: m,
            };
            return Ok((out, saved));
        }
    }

    fn backward(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        saved: &GpuSaved,
        v: &ImageGrads,
    ) -> Result<SplatGrads, Error> {
        check_inputs(cam, inputs, settings)?;
        let _span = tracing::debug_span!("render.gpu.backward", n = inputs.means.len()).entered();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = inputs.means.len();
        let same_size = saved.width == cam.width && saved.height == cam.height;
        check_saved(cam, None, saved.n == n && same_size)?;
        let mut guard = saved.frame.lock().map_err(gpu_err)?;
        let frame = guard.frame.as_mut().expect("saved frame");
        let key = frame.key;
        let (nf, nc) = (key.nf, key.nc);
        check_saved(cam, None, inputs.num_features == nf)?;
        v.check_shapes(w, h, nf)?;
        // [H, W, C + 1]: dL/d blended channels, then dL/d alpha (as the CPU backward).
        let mut v_pix = vec![0.0f32; w * h * (nc + 1)];
        for p in 0..w * h {
            let o = p * (nc + 1);
            v_pix[o + nc] = v.pixel(p, settings.background, &mut v_pix[o..o + nc]);
        }
        let ctx = &*self.ctx;
        let fresh = frame.bwd.is_none();
        frame.bwd(ctx);
        let frame = &*frame;
        let b = frame.bwd.as_ref().expect("backward buffers");
        if self.junk && fresh {
            frame::fill_junk(ctx, &[&b.v_pix, &b.scratch, &b.g2d, &b.out]);
        }
        ctx.queue.write_buffer(&b.v_pix, 0, bytemuck::cast_slice(&v_pix));
        let k = &ctx.kernels;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&b.g2d, 0, None);
        let g = bind(
            ctx,
            &k.bwd.layout,
            &[
                &frame.params,
                &frame.splats,
                &frame.chans,
                &frame.tile_offsets,
                &frame.pairs[saved.sorted][2],
                &frame.final_t,
                &frame.last,
                &b.v_pix,
                &b.scratch,
                &b.g2d,
            ],
        );
        dispatch(
            &mut enc,
            k.bwd.pipeline("main"),
            &g,
            (w.div_ceil(16) as u32, h.div_ceil(16) as u32),
        );
        let g = bind(
            ctx,
            &k.project_bwd.layout,
            &[&frame.params, &frame.geom, &frame.colors, &frame.splats, &b.g2d, &b.out],
        );
        dispatch(&mut enc, k.project_bwd.pipeline("main"), &g, grid(n.div_ceil(256)));
        let stride = key.grad_stride();
        if n > 0 {
            enc.copy_buffer_to_buffer(&b.out, 0, &b.staging, 0, 4 * (n * stride) as u64);
        }
        ctx.queue.submit([enc.finish()]);
        let words = read_words(ctx, &b.staging, n * stride).map_err(gpu_err)?;
        let f = |i: usize| f32::from_bits(words[i]);
        let k3 = key.color_stride - 3;
        let mut out = SplatGrads {
            means: Vec::with_capacity(n),
            quats: Vec::with_capacity(n),
            scales: Vec::with_capacity(n),
            opacities: Vec::with_capacity(n),
            colors: Vec::with_capacity(n),
            sh_rest: Vec::with_capacity(n * k3),
            features: Vec::with_capacity(n * nf),
            means2d: Vec::with_capacity(n),
        };
        for i in 0..n {
            let o = i * stride;
            out.means.push([f(o), f(o + 1), f(o + 2)]);
            out.quats.push([f(o + 3), f(o + 4), f(o + 5), f(o + 6)]);
            out.scales.push([f(o + 7), f(o + 8), f(o + 9)]);
            out.opacities.push(f(o + 10));
            out.colors.push([f(o + 11), f(o + 12), f(o + 13)]);
            out.sh_rest.extend((0..k3).map(|j| f(o + 14 + j)));
            out.features.extend((0..nf).map(|j| f(o + 14 + k3 + j)));
            out.means2d.push([f(o + 14 + k3 + nf), f(o + 15 + k3 + nf)]);
        }
        Ok(out)
    }

    fn convergence_saved(
        &self,
        cam: &RenderCamera,
        _settings: &RenderSettings,
        saved: &GpuSaved,
        pixel_pass: &[bool],
        test: ConvergenceTest,
    ) -> Result<Vec<bool>, Error> {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let same_size = saved.width == cam.width && saved.height == cam.height;
        check_saved(cam, Some(pixel_pass), same_size)?;
        let mut guard = saved.frame.lock().map_err(gpu_err)?;
        let frame = guard.frame.as_mut().expect("saved frame");
        let ctx = &*self.ctx;
        let fresh = frame.conv.is_none();
        frame.conv(ctx);
        let frame = &*frame;
        let c = frame.conv.as_ref().expect("convergence buffers");
        if self.junk && fresh {
            frame::fill_junk(ctx, &[&c.pass, &c.fail]);
        }
        let pass: Vec<u32> = pixel_pass.iter().map(|&p| p as u32).collect();
        ctx.queue.write_buffer(&c.pass, 0, bytemuck::cast_slice(&pass));
        let min_weight = match test {
            ConvergenceTest::WeightedPixels(m) => m,
            _ => 0.0,
        };
        let at = (4 * params::MIN_WEIGHT_WORD) as u64;
        ctx.queue.write_buffer(&frame.params, at, bytemuck::bytes_of(&min_weight.to_bits()));
        let k = &ctx.kernels.convergence;
        let g = bind(
            ctx,
            &k.layout,
            &[
                &frame.params,
                &frame.splats,
                &frame.tile_offsets,
                &frame.pairs[saved.sorted][2],
                &frame.last,
                &c.pass,
                &c.fail,
            ],
        );
        let n = saved.n;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        match test {
            ConvergenceTest::AllCoveredPixels | ConvergenceTest::WeightedPixels(_) => {
                enc.clear_buffer(&c.fail, 0, None);
                dispatch(
                    &mut enc,
                    k.pipeline("fail_pairs"),
                    &g,
                    (w.div_ceil(16) as u32, h.div_ceil(16) as u32),
                );
            }
            ConvergenceTest::CentrePixel => {
                dispatch(&mut enc, k.pipeline("centre"), &g, grid(n.div_ceil(256)));
            }
        }
        if n > 0 {
            enc.copy_buffer_to_buffer(&c.fail, 0, &c.staging, 0, 4 * n as u64);
        }
        ctx.queue.submit([enc.finish()]);
        let words = read_words(ctx, &c.staging, n).map_err(gpu_err)?;
        Ok(words.iter().map(|&f| f == 0).collect())
    }
}
