//! Stage 1, `project`: EWA projection of each 3D Gaussian to a 2D screen-space Gaussian
//! (mean, inverse covariance "conic", depth, opacity-aware extent), and its VJP.
//!
//! One call of [`project_one`] is one GPU thread's work (reference for `gpu::project`).
//! Reads `[N]` positions, rotations, scales and opacities; writes `[N]` [`Splat2d`] indexed by
//! canonical (global) Gaussian index. Poisoned inputs (non-finite values, zero quaternion,
//! degenerate covariance) and Gaussians outside the near/far range or the screen are culled:
//! their `Splat2d` is `valid == false` with all other fields 0.
//!
//! Covariance: `Σ = R S Sᵀ Rᵀ` (R from the normalised quaternion, S = diag(scale)),
//! `Σ₂ = J W Σ Wᵀ Jᵀ + 0.3 I` with W the world-to-camera rotation and J the Jacobian of the
//! pinhole projection at the camera-space mean (x/z and y/z clamped to 1.3× the half field of
//! view as gsplat does).

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::math::quat;
use crate::render::constants::{ALPHA_THRESHOLD, COV_BLUR, FOV_MARGIN};
use crate::render::{RenderCamera, SplatInputs};

/// A projected Gaussian (screen space, pixels). All zero and `valid == false` when culled.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Splat2d {
    /// Projected mean `(u, v)`, pixels (pixel centres at +0.5).
    pub mean2d: [f32; 2],
    /// Inverse 2D covariance `(a, b, c)` = `[[a, b], [b, c]]`, 1/pixels².
    pub conic: [f32; 3],
    /// Camera-space z of the mean.
    pub depth: f32,
    /// Opacity o.
    pub opacity: f32,
    /// `ln(255·o)`: the largest σ where `o·exp(-σ) >= 1/255`.
    pub power: f32,
    /// Half-widths `(x, y)` of the bounding box of the `σ <= power` ellipse, pixels.
    pub extent: [f32; 2],
    /// Radius of the `σ <= power` ellipse along its major axis, pixels.
    pub radius: f32,
    /// Whether the Gaussian survived culling.
    pub valid: bool,
}

/// Camera constants of the projection, derived once from a [`RenderCamera`].
#[derive(Debug, Clone, Copy)]
pub struct CameraConsts {
    /// World-to-camera rotation W.
    pub rot: Mat3,
    /// World-to-camera translation.
    pub trans: Vec3,
    /// Camera centre in world coordinates.
    pub center: Vec3,
    /// Focal lengths and principal point.
    pub fx: f32,
    /// Focal length y.
    pub fy: f32,
    /// Principal point x.
    pub cx: f32,
    /// Principal point y.
    pub cy: f32,
    /// Clamp limits of x/z: `(-lim_x_neg, lim_x_pos)`.
    pub lim_x: [f32; 2],
    /// Clamp limits of y/z.
    pub lim_y: [f32; 2],
    /// Image size.
    pub width: f32,
    /// Image height.
    pub height: f32,
    /// Near and far planes.
    pub near: f32,
    /// Far plane.
    pub far: f32,
}

impl CameraConsts {
    /// Precompute the projection constants of `cam`.
    pub fn new(cam: &RenderCamera) -> Self {
        let rot = Mat3::from_mat4(cam.w2c);
        let trans = cam.w2c.w_axis.truncate();
        let (w, h) = (cam.width as f32, cam.height as f32);
        let tan_x = 0.5 * w / cam.fx;
        let tan_y = 0.5 * h / cam.fy;
        CameraConsts {
            rot,
            trans,
            center: -(rot.transpose() * trans),
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            lim_x: [
                cam.cx / cam.fx + FOV_MARGIN * tan_x,
                (w - cam.cx) / cam.fx + FOV_MARGIN * tan_x,
            ],
            lim_y: [
                cam.cy / cam.fy + FOV_MARGIN * tan_y,
                (h - cam.cy) / cam.fy + FOV_MARGIN * tan_y,
            ],
            width: w,
            height: h,
            near: cam.near,
            far: cam.far,
        }
    }
}

/// Intermediates of one projection, recomputed by the VJP.
struct ProjState {
    q: [f32; 4],
    r: Mat3,
    m: Mat3,
    p_cam: Vec3,
    /// Clamped x and y used in J, and whether each was clamped.
    tx: f32,
    ty: f32,
    clamped: [bool; 2],
    j: Mat3,
    cov_cam: Mat3,
    cov2d: [f32; 3],
}

fn proj_state(
    c: &CameraConsts,
    mean: [f32; 3],
    quat: [f32; 4],
    scale: [f32; 3],
) -> Option<ProjState> {
    if !mean.iter().chain(scale.iter()).all(|v| v.is_finite()) || scale.iter().any(|s| *s < 0.0) {
        return None;
    }
    let (q, _) = quat::normalize(quat)?;
    let p_cam = c.rot * Vec3::from(mean) + c.trans;
    let z = p_cam.z;
    if !(z >= c.near && z <= c.far) {
        return None;
    }
    let r = quat::to_rotmat(q);
    let m = r * Mat3::from_diagonal(Vec3::from(scale));
    let cov_world = m * m.transpose();
    let cov_cam = c.rot * cov_world * c.rot.transpose();
    let (ux, uy) = (p_cam.x / z, p_cam.y / z);
    let cxz = ux.clamp(-c.lim_x[0], c.lim_x[1]);
    let cyz = uy.clamp(-c.lim_y[0], c.lim_y[1]);
    let (tx, ty) = (z * cxz, z * cyz);
    // J as a 3x3 with a zero third row.
    let j = Mat3::from_cols(
        Vec3::new(c.fx / z, 0.0, 0.0),
        Vec3::new(0.0, c.fy / z, 0.0),
        Vec3::new(-c.fx * tx / (z * z), -c.fy * ty / (z * z), 0.0),
    );
    let cov = j * cov_cam * j.transpose();
    let cov2d = [cov.col(0).x + COV_BLUR, cov.col(1).x, cov.col(1).y + COV_BLUR];
    if !cov2d.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(ProjState { q, r, m, p_cam, tx, ty, clamped: [cxz != ux, cyz != uy], j, cov_cam, cov2d })
}

/// Project one Gaussian (one thread's work; reference for `gpu::project`).
pub fn project_one(
    c: &CameraConsts,
    mean: [f32; 3],
    quat: [f32; 4],
    scale: [f32; 3],
    opacity: f32,
) -> Splat2d {
    if !(opacity.is_finite() && opacity >= ALPHA_THRESHOLD) {
        return Splat2d::default();
    }
    let Some(s) = proj_state(c, mean, quat, scale) else { return Splat2d::default() };
    let [a, b, d] = s.cov2d;
    let det = a * d - b * b;
    if !(det > 0.0 && det.is_finite()) {
        return Splat2d::default();
    }
    let conic = [d / det, -b / det, a / det];
    let z = s.p_cam.z;
    let mean2d = [c.fx * s.p_cam.x / z + c.cx, c.fy * s.p_cam.y / z + c.cy];
    let power = (255.0 * opacity).ln();
    let extent = [(2.0 * power * a).sqrt(), (2.0 * power * d).sqrt()];
    let mid = 0.5 * (a + d);
    let lambda_max = mid + (mid * mid - det).max(0.0).sqrt();
    let radius = (2.0 * power * lambda_max).sqrt();
    let on_screen = mean2d[0] + extent[0] > 0.0
        && mean2d[0] - extent[0] < c.width
        && mean2d[1] + extent[1] > 0.0
        && mean2d[1] - extent[1] < c.height;
    if !(on_screen
        && conic.iter().chain(mean2d.iter()).all(|v| v.is_finite())
        && radius.is_finite())
    {
        return Splat2d::default();
    }
    Splat2d { mean2d, conic, depth: z, opacity, power, extent, radius, valid: true }
}

/// Stage `project`: every Gaussian of `inputs`, `[N]` out (rayon over Gaussians).
pub fn project(c: &CameraConsts, inputs: &SplatInputs) -> Vec<Splat2d> {
    let n = inputs.means.len();
    assert!(
        inputs.quats.len() == n && inputs.scales.len() == n && inputs.opacities.len() == n,
        "project: means, quats, scales and opacities must all be [N]"
    );
    let _span = tracing::debug_span!("render.project", n).entered();
    (0..inputs.means.len())
        .into_par_iter()
        .map(|i| {
            project_one(c, inputs.means[i], inputs.quats[i], inputs.scales[i], inputs.opacities[i])
        })
        .collect()
}

/// Gradient of the loss w.r.t. one projected Gaussian.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Splat2dGrad {
    /// dL/d mean2d.
    pub mean2d: [f32; 2],
    /// dL/d conic `(a, b, c)`.
    pub conic: [f32; 3],
    /// dL/d depth (camera z), from the depth channel.
    pub depth: f32,
    /// dL/d opacity.
    pub opacity: f32,
}

/// Gradients of one Gaussian's 3D parameters.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Splat3dGrad {
    /// dL/d position.
    pub mean: [f32; 3],
    /// dL/d quaternion (w.r.t. the unnormalised input).
    pub quat: [f32; 4],
    /// dL/d scale.
    pub scale: [f32; 3],
    /// dL/d opacity.
    pub opacity: f32,
}

/// VJP of [`project_one`] (reference for `gpu::project_bwd`); `v_rot` is an extra
/// dL/dR of the Gaussian's rotation (from local-frame SH), added before the quaternion VJP.
/// Zero for culled Gaussians.
pub fn project_vjp(
    c: &CameraConsts,
    mean: [f32; 3],
    quat: [f32; 4],
    scale: [f32; 3],
    splat: &Splat2d,
    v: &Splat2dGrad,
    v_rot: Mat3,
) -> Splat3dGrad {
    if !splat.valid {
        return Splat3dGrad::default();
    }
    let Some(s) = proj_state(c, mean, quat, scale) else { return Splat3dGrad::default() };
    let [ca, cb, cc] = splat.conic;
    let conic = Mat3::from_cols(Vec3::new(ca, cb, 0.0), Vec3::new(cb, cc, 0.0), Vec3::ZERO);
    // The off-diagonal conic entry b appears twice in the matrix.
    let g = Mat3::from_cols(
        Vec3::new(v.conic[0], 0.5 * v.conic[1], 0.0),
        Vec3::new(0.5 * v.conic[1], v.conic[2], 0.0),
        Vec3::ZERO,
    );
    let v_cov2d = -(conic * g * conic);
    let v_cov_cam = s.j.transpose() * v_cov2d * s.j;
    let v_j = 2.0 * v_cov2d * s.j * s.cov_cam;
    let v_cov_world = c.rot.transpose() * v_cov_cam * c.rot;

    let z = s.p_cam.z;
    let (x, y) = (s.p_cam.x, s.p_cam.y);
    let mut v_p = Vec3::ZERO;
    // mean2d = (fx x/z + cx, fy y/z + cy)
    v_p.x += c.fx / z * v.mean2d[0];
    v_p.y += c.fy / z * v.mean2d[1];
    v_p.z += -c.fx * x / (z * z) * v.mean2d[0] - c.fy * y / (z * z) * v.mean2d[1];
    v_p.z += v.depth;
    // J entries: J00 = fx/z, J11 = fy/z, J02 = -fx tx/z², J12 = -fy ty/z².
    let (vj00, vj11, vj02, vj12) = (v_j.col(0).x, v_j.col(1).y, v_j.col(2).x, v_j.col(2).y);
    let z2 = z * z;
    let z3 = z2 * z;
    v_p.z += -c.fx / z2 * vj00 - c.fy / z2 * vj11
        + 2.0 * c.fx * s.tx / z3 * vj02
        + 2.0 * c.fy * s.ty / z3 * vj12;
    let v_tx = -c.fx / z2 * vj02;
    let v_ty = -c.fy / z2 * vj12;
    // tx = x when not clamped, z·L otherwise.
    if s.clamped[0] {
        v_p.z += v_tx * s.tx / z;
    } else {
        v_p.x += v_tx;
    }
    if s.clamped[1] {
        v_p.z += v_ty * s.ty / z;
    } else {
        v_p.y += v_ty;
    }
    let v_mean = c.rot.transpose() * v_p;

    // Σ = M Mᵀ, M = R S.
    let v_m = 2.0 * v_cov_world * s.m;
    let mut v_r = v_rot;
    let mut v_scale = [0.0f32; 3];
    for j in 0..3 {
        let col = v_m.col(j);
        v_scale[j] = s.r.col(j).dot(col);
        *v_r.col_mut(j) += col * scale[j];
    }
    let v_qn = quat::to_rotmat_vjp(s.q, v_r);
    let (_, norm) = quat::normalize(quat).unwrap_or(([1.0, 0.0, 0.0, 0.0], 1.0));
    let v_quat = quat::normalize_vjp(s.q, norm, v_qn);
    Splat3dGrad { mean: v_mean.into(), quat: v_quat, scale: v_scale, opacity: v.opacity }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    fn camera() -> RenderCamera {
        RenderCamera {
            fx: 100.0,
            fy: 120.0,
            cx: 32.0,
            cy: 24.0,
            w2c: Mat4::IDENTITY,
            width: 64,
            height: 48,
            near: 0.01,
            far: 100.0,
        }
    }

    #[test]
    fn isotropic_gaussian_projects_to_expected_mean_and_covariance() {
        let c = CameraConsts::new(&camera());
        let s = project_one(&c, [0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.5);
        assert!(s.valid);
        assert_eq!(s.mean2d, [32.0, 24.0]);
        assert_eq!(s.depth, 2.0);
        // cov2d = diag((fx·0.1/2)², (fy·0.1/2)²) + 0.3.
        let (a, d) = (25.0f32 + 0.3, 36.0f32 + 0.3);
        assert!((s.conic[0] - 1.0 / a).abs() < 1e-6 && s.conic[1].abs() < 1e-9);
        assert!((s.conic[2] - 1.0 / d).abs() < 1e-6);
        let power = (255.0f32 * 0.5).ln();
        assert!((s.extent[0] - (2.0 * power * a).sqrt()).abs() < 1e-4);
        assert!((s.radius - (2.0 * power * d).sqrt()).abs() < 1e-4);
    }

    #[test]
    fn poisoned_and_out_of_view_gaussians_are_culled() {
        let c = CameraConsts::new(&camera());
        let ok = ([0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [0.1; 3], 0.5);
        type Case = ([f32; 3], [f32; 4], [f32; 3], f32);
        let cases: Vec<Case> = vec![
            ([0.0, 0.0, -2.0], ok.1, ok.2, ok.3),
            ([f32::NAN, 0.0, 2.0], ok.1, ok.2, ok.3),
            (ok.0, [0.0; 4], ok.2, ok.3),
            (ok.0, [f32::INFINITY, 0.0, 0.0, 0.0], ok.2, ok.3),
            (ok.0, ok.1, [1e30; 3], ok.3),
            (ok.0, ok.1, [-0.1; 3], ok.3),
            (ok.0, ok.1, ok.2, f32::NAN),
            (ok.0, ok.1, ok.2, 0.001),
            ([100.0, 0.0, 2.0], ok.1, ok.2, ok.3),
            ([0.0, 0.0, 1000.0], ok.1, ok.2, ok.3),
        ];
        for (i, (m, q, s, o)) in cases.into_iter().enumerate() {
            assert_eq!(project_one(&c, m, q, s, o), Splat2d::default(), "case {i}");
        }
        assert!(project_one(&c, ok.0, ok.1, [0.0; 3], ok.3).valid, "zero scale is a point splat");
    }
}
