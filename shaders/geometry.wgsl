// file: geometry.wgsl
// What `project` and `project_bwd` share: the Gaussian's inputs, the projection geometry
// (project.rs::proj_state) and the SH view direction and coefficients.

struct ProjState {
    ok: bool,
    q: vec4<f32>,
    r: mat3x3<f32>,
    m: mat3x3<f32>,
    p_cam: vec3<f32>,
    tx: f32,
    ty: f32,
    clamped_x: bool,
    clamped_y: bool,
    j: mat3x3<f32>,
    cov_cam: mat3x3<f32>,
    cov2d: vec3<f32>,
}

// Gaussian i's inputs, read from the kernel's `geom` ([N, 11]: mean, quat, scale, opacity).
struct Gaussian {
    mean: vec3<f32>,
    quat: vec4<f32>,
    scale: vec3<f32>,
    opacity: f32,
}

fn load_gaussian(i: u32) -> Gaussian {
    let b = i * 11u;
    return Gaussian(
        vec3<f32>(geom[b], geom[b + 1u], geom[b + 2u]),
        vec4<f32>(geom[b + 3u], geom[b + 4u], geom[b + 5u], geom[b + 6u]),
        vec3<f32>(geom[b + 7u], geom[b + 8u], geom[b + 9u]),
        geom[b + 10u],
    );
}

// SH coefficient k >= 1 of the Gaussian whose colours start at `cb` in `colors`.
fn sh_coeff(cb: u32, k: u32) -> vec3<f32> {
    let r = cb + 3u * k;
    return vec3<f32>(colors[r], colors[r + 1u], colors[r + 2u]);
}

// The SH view direction of a Gaussian at `mean` with rotation `r` (cpu.rs::view_dir): unit,
// in the world frame, or the Gaussian's local frame for colour mode 2; zero at the camera
// centre. `.w` is |mean − centre|.
fn view_dir(mean: vec3<f32>, r: mat3x3<f32>) -> vec4<f32> {
    var dir = vec3<f32>(0.0);
    let dv = mean - P.center.xyz;
    let len = length(dv);
    if (len > 0.0 && is_finite(len)) {
        dir = dv / len;
        if (P.color_mode == 2u) {
            dir = transpose(r) * dir;
        }
    }
    return vec4<f32>(dir, len);
}

fn finite_or_zero(v: f32) -> f32 {
    return select(0.0, v, is_finite(v));
}

fn cam_rot() -> mat3x3<f32> {
    return mat3x3<f32>(P.rot0.xyz, P.rot1.xyz, P.rot2.xyz);
}

// Rotation matrix of a unit quaternion (w, x, y, z) (project.rs::quat_to_rotmat).
fn quat_to_rotmat(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

// Norm of q, or 0 when q is zero or not finite (project.rs::normalize_quat).
fn quat_norm(q: vec4<f32>) -> f32 {
    let n = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    if (!(is_finite(n) && n > 1e-12)) {
        return 0.0;
    }
    return n;
}

fn proj_state(mean: vec3<f32>, quat: vec4<f32>, scale: vec3<f32>) -> ProjState {
    var s: ProjState;
    s.ok = false;
    let fin = is_finite(mean.x) && is_finite(mean.y) && is_finite(mean.z)
        && is_finite(scale.x) && is_finite(scale.y) && is_finite(scale.z);
    if (!fin || scale.x < 0.0 || scale.y < 0.0 || scale.z < 0.0) {
        return s;
    }
    let qn = quat_norm(quat);
    if (qn == 0.0) {
        return s;
    }
    s.q = quat / qn;
    let rot = cam_rot();
    s.p_cam = rot * mean + P.trans.xyz;
    let z = s.p_cam.z;
    if (!(z >= P.near && z <= P.far)) {
        return s;
    }
    s.r = quat_to_rotmat(s.q);
    s.m = s.r * mat3x3<f32>(vec3<f32>(scale.x, 0.0, 0.0), vec3<f32>(0.0, scale.y, 0.0), vec3<f32>(0.0, 0.0, scale.z));
    let cov_world = s.m * transpose(s.m);
    s.cov_cam = rot * cov_world * transpose(rot);
    let ux = s.p_cam.x / z;
    let uy = s.p_cam.y / z;
    let cxz = clamp(ux, -P.lim_x0, P.lim_x1);
    let cyz = clamp(uy, -P.lim_y0, P.lim_y1);
    s.tx = z * cxz;
    s.ty = z * cyz;
    s.clamped_x = cxz != ux;
    s.clamped_y = cyz != uy;
    s.j = mat3x3<f32>(
        vec3<f32>(P.fx / z, 0.0, 0.0),
        vec3<f32>(0.0, P.fy / z, 0.0),
        vec3<f32>(-P.fx * s.tx / (z * z), -P.fy * s.ty / (z * z), 0.0),
    );
    let cov = s.j * s.cov_cam * transpose(s.j);
    s.cov2d = vec3<f32>(cov[0].x + COV_BLUR, cov[1].x, cov[1].y + COV_BLUR);
    if (!(is_finite(s.cov2d.x) && is_finite(s.cov2d.y) && is_finite(s.cov2d.z))) {
        return s;
    }
    s.ok = true;
    return s;
}

// Spherical harmonics (sh.rs::basis) with forward-mode derivatives: each entry is
// (value, d/dx, d/dy, d/dz). Entry 0 is 0 (the degree-0 term is carried by dc).
fn dmul(a: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(a.x * b.x, a.yzw * b.x + a.x * b.yzw);
}

fn dconst(v: f32) -> vec4<f32> {
    return vec4<f32>(v, 0.0, 0.0, 0.0);
}

fn sh_basis_d(degree: u32, dir: vec3<f32>) -> array<vec4<f32>, 16> {
    let C1 = 0.4886025;
    let x = vec4<f32>(dir.x, 1.0, 0.0, 0.0);
    let y = vec4<f32>(dir.y, 0.0, 1.0, 0.0);
    let z = vec4<f32>(dir.z, 0.0, 0.0, 1.0);
    var b: array<vec4<f32>, 16>;
    if (degree >= 1u) {
        b[1] = -C1 * y;
        b[2] = C1 * z;
        b[3] = -C1 * x;
    }
    if (degree >= 2u) {
        let xx = dmul(x, x);
        let yy = dmul(y, y);
        let zz = dmul(z, z);
        b[4] = 1.0925484 * dmul(x, y);
        b[5] = -1.0925484 * dmul(y, z);
        b[6] = 0.31539157 * (2.0 * zz - xx - yy);
        b[7] = -1.0925484 * dmul(x, z);
        b[8] = 0.5462742 * (xx - yy);
        if (degree >= 3u) {
            b[9] = dmul(-0.5900436 * y, 3.0 * xx - yy);
            b[10] = dmul(2.8906114 * dmul(x, y), z);
            b[11] = dmul(-0.4570458 * y, 4.0 * zz - xx - yy);
            b[12] = dmul(0.37317633 * z, 2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = dmul(-0.4570458 * x, 4.0 * zz - xx - yy);
            b[14] = dmul(1.4453057 * z, xx - yy);
            b[15] = dmul(-0.5900436 * x, xx - 3.0 * yy);
        }
    }
    return b;
}

fn sh_basis(degree: u32, dir: vec3<f32>) -> array<f32, 16> {
    var d = sh_basis_d(degree, dir);
    var b: array<f32, 16>;
    for (var k = 0u; k < 16u; k++) {
        b[k] = d[k].x;
    }
    return b;
}
