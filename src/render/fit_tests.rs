//! Fitting test: Adam through the CPU renderer's gradients reproduces a textured synthetic
//! image, which checks that forward and backward agree at scale (thousands of Gaussians,
//! hard cutoff, many layers), not only on finite-difference toy scenes.

use super::synthetic::camera;
use super::*;
use crate::util::rng::Rng;

/// Target `[H, W, 3]`: a 16-px checker mixed with horizontal and vertical colour ramps.
fn target(w: usize, h: usize) -> Vec<f32> {
    let mut img = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let check = if (x / 16 + y / 16) % 2 == 0 { 0.8 } else { 0.2 };
            let fx = x as f32 / w as f32;
            let fy = y as f32 / h as f32;
            img.extend_from_slice(&[
                0.2 + 0.6 * fx,
                check,
                0.5 + 0.4 * (std::f32::consts::TAU * fy).sin() * check,
            ]);
        }
    }
    img
}

/// Adam state of one flat parameter vector.
struct Adam {
    lr: f32,
    m: Vec<f32>,
    v: Vec<f32>,
}

impl Adam {
    fn new(lr: f32, n: usize) -> Self {
        Adam { lr, m: vec![0.0; n], v: vec![0.0; n] }
    }

    fn step(&mut self, t: i32, params: &mut [f32], grads: &[f32]) {
        let (b1, b2) = (0.9f32, 0.999f32);
        let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        for i in 0..params.len() {
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * grads[i];
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * grads[i] * grads[i];
            params[i] -= self.lr * (self.m[i] / c1) / ((self.v[i] / c2).sqrt() + 1e-15);
        }
    }
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a.iter().zip(b).map(|(x, y)| ((x.clamp(0.0, 1.0) - y) as f64).powi(2)).sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.log10()
}

#[test]
fn adam_on_2000_gaussians_fits_a_textured_image_above_30_db() {
    let (w, h) = (64usize, 64usize);
    let cam = camera(w as u32, h as u32);
    let gt = target(w, h);
    let n = 2000;
    let mut rng = Rng::from_state(1);
    // Parameters in unconstrained form: means [N,3], log-scales [N,3], quats [N,4],
    // opacity logits [N], colours [N,3]; Gaussians on the plane z = 1.
    let mut means: Vec<f32> = Vec::with_capacity(n * 3);
    for _ in 0..n {
        let (u, v) = (rng.range_f32(0.0, w as f32), rng.range_f32(0.0, h as f32));
        means.extend_from_slice(&[(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]);
    }
    let px = 1.0 / cam.fx;
    let mut log_scales: Vec<f32> =
        (0..n).flat_map(|_| [(1.2 * px).ln(), (1.2 * px).ln(), (0.2 * px).ln()]).collect();
    let mut quats: Vec<f32> = (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    let mut logits = vec![0.0f32; n];
    let mut colors = vec![0.5f32; n * 3];
    let mut opt = [
        Adam::new(0.2 * px, n * 3),
        Adam::new(0.01, n * 3),
        Adam::new(0.01, n * 4),
        Adam::new(0.05, n),
        Adam::new(0.01, n * 3),
    ];
    let settings = RenderSettings { background: [0.0; 3], alpha_max: 0.99 };
    let start = std::time::Instant::now();
    let mut best = 0.0;
    let mut steps = 0;
    for t in 1..=600 {
        let as3 =
            |v: &[f32]| v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<[f32; 3]>>();
        let m3 = as3(&means);
        let s3: Vec<[f32; 3]> = as3(&log_scales).iter().map(|s| s.map(f32::exp)).collect();
        let q4: Vec<[f32; 4]> = quats.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
        let op: Vec<f32> = logits.iter().map(|l| 1.0 / (1.0 + (-l).exp())).collect();
        let c3 = as3(&colors);
        let inputs = SplatInputs {
            means: &m3,
            quats: &q4,
            scales: &s3,
            opacities: &op,
            colors: ColorSource::Rgb(&c3),
            features: &[],
            num_features: 0,
        };
        let (out, saved) =
            CpuRenderer.render_with_saved(&cam, &inputs, &settings, Cutoff::Hard).unwrap();
        best = psnr(&out.color, &gt);
        steps = t;
        if best > 31.0 {
            break;
        }
        let scale = 2.0 / gt.len() as f32;
        let v = ImageGrads {
            color: out.color.iter().zip(&gt).map(|(c, g)| scale * (c - g)).collect(),
            ..ImageGrads::default()
        };
        let g = CpuRenderer.backward(&cam, &inputs, &settings, &saved, &v).unwrap();
        let g_means: Vec<f32> = g.means.concat();
        let g_ls: Vec<f32> = g
            .scales
            .iter()
            .zip(&s3)
            .flat_map(|(gs, s)| [gs[0] * s[0], gs[1] * s[1], gs[2] * s[2]])
            .collect();
        let g_q: Vec<f32> = g.quats.concat();
        let g_l: Vec<f32> = g.opacities.iter().zip(&op).map(|(go, o)| go * o * (1.0 - o)).collect();
        let g_c: Vec<f32> = g.colors.concat();
        opt[0].step(t, &mut means, &g_means);
        opt[1].step(t, &mut log_scales, &g_ls);
        opt[2].step(t, &mut quats, &g_q);
        opt[3].step(t, &mut logits, &g_l);
        opt[4].step(t, &mut colors, &g_c);
    }
    eprintln!(
        "fit: PSNR {best:.2} dB after {steps} steps in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    assert!(best > 30.0, "PSNR {best:.2} dB after {steps} steps");
}
