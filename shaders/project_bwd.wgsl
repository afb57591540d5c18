// file: project_bwd.wgsl
// VJPs of the channel construction (SH colour, depth, features) and of `project`, one thread
// per Gaussian (mirror of cpu.rs::project_backward and project.rs::project_vjp). Output
// `[N, 14 + K·3 + F]`: mean 3, quat 4, scale 3, opacity 1, colour/dc 3, SH rest K·3,
// features F; zero for culled Gaussians.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> geom: array<f32>;          // [N, 11]
@group(0) @binding(2) var<storage, read> colors: array<f32>;        // [N, color_stride]
@group(0) @binding(3) var<storage, read> splats: array<f32>;        // [N, 12]
@group(0) @binding(4) var<storage, read> g2d: array<f32>;           // [N, 6 + C]
@group(0) @binding(5) var<storage, read_write> grads_out: array<f32>;     // [N, 14 + K3 + F]

// project.rs::quat_to_rotmat_vjp; v[j][i] is dL/dR[i][j].
fn quat_to_rotmat_vjp(q: vec4<f32>, v: mat3x3<f32>) -> vec4<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return vec4<f32>(
        2.0 * (x * (v[1][2] - v[2][1]) + y * (v[2][0] - v[0][2]) + z * (v[0][1] - v[1][0])),
        2.0 * (-2.0 * x * (v[1][1] + v[2][2]) + y * (v[0][1] + v[1][0]) + z * (v[0][2] + v[2][0])
            + w * (v[1][2] - v[2][1])),
        2.0 * (x * (v[0][1] + v[1][0]) - 2.0 * y * (v[0][0] + v[2][2]) + z * (v[1][2] + v[2][1])
            + w * (v[2][0] - v[0][2])),
        2.0 * (x * (v[0][2] + v[2][0]) + y * (v[1][2] + v[2][1]) - 2.0 * z * (v[0][0] + v[1][1])
            + w * (v[0][1] - v[1][0])),
    );
}

@compute @workgroup_size(256)
fn main(f: Flat) {
    let i = item_of(f);
    if (i >= P.n) {
        return;
    }
    let nc = P.nc;
    let k3 = P.color_stride - 3u;
    let ostride = 16u + k3 + P.nf;
    let o = i * ostride;
    for (var k = 0u; k < ostride; k++) {
        grads_out[o + k] = 0.0;
    }
    let so = i * SPLAT_STRIDE;
    if (splats[so + 11u] == 0.0) {
        return;
    }
    let g3 = load_gaussian(i);
    let st = proj_state(g3.mean, g3.quat, g3.scale);
    if (!st.ok) {
        return;
    }
    let gb = i * (6u + nc);
    let v_mean2d = vec2<f32>(g2d[gb], g2d[gb + 1u]);
    let v_conic_in = vec3<f32>(g2d[gb + 2u], g2d[gb + 3u], g2d[gb + 4u]);
    let v_opacity = g2d[gb + 5u];
    let v_rgb = vec3<f32>(g2d[gb + 6u], g2d[gb + 7u], g2d[gb + 8u]);
    let v_depth = g2d[gb + 9u];

    // Colour: SH VJP (sh.rs::eval_vjp) and the view direction's dependence on the mean.
    var v_mean = vec3<f32>(0.0);
    var v_rot = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var v_dc = v_rgb;
    let cb = i * P.color_stride;
    if (P.color_mode != 0u) {
        let vd = view_dir(g3.mean, st.r);
        let dir = vd.xyz;
        let len = vd.w;
        var y = sh_basis_d(P.sh_degree, dir);
        let nb = (P.sh_degree + 1u) * (P.sh_degree + 1u);
        var raw = vec3<f32>(colors[cb], colors[cb + 1u], colors[cb + 2u]);
        for (var k = 1u; k < nb; k++) {
            raw += y[k].x * sh_coeff(cb, k);
        }
        let v = select(v_rgb, vec3<f32>(0.0), raw < vec3<f32>(0.0));
        v_dc = v;
        var v_dir = vec3<f32>(0.0);
        for (var k = 1u; k < nb; k++) {
            let rest = sh_coeff(cb, k);
            let vr = y[k].x * v;
            grads_out[o + 14u + (k - 1u) * 3u] = vr.x;
            grads_out[o + 15u + (k - 1u) * 3u] = vr.y;
            grads_out[o + 16u + (k - 1u) * 3u] = vr.z;
            let v_y = rest.x * v.x + rest.y * v.y + rest.z * v.z;
            v_dir += v_y * y[k].yzw;
        }
        if (len > 0.0 && is_finite(len)) {
            var v_dw = v_dir;
            var d_world = dir;
            if (P.color_mode == 2u) {
                let dw = st.r * dir;
                v_rot = mat3x3<f32>(dw * v_dir.x, dw * v_dir.y, dw * v_dir.z);
                v_dw = st.r * v_dir;
                d_world = dw;
            }
            v_mean += (v_dw - d_world * dot(d_world, v_dw)) / len;
        }
    }

    // project.rs::project_vjp
    let ca = splats[so + 2u];
    let cbb = splats[so + 3u];
    let cc = splats[so + 4u];
    let conic = mat3x3<f32>(vec3<f32>(ca, cbb, 0.0), vec3<f32>(cbb, cc, 0.0), vec3<f32>(0.0));
    let gm = mat3x3<f32>(
        vec3<f32>(v_conic_in.x, 0.5 * v_conic_in.y, 0.0),
        vec3<f32>(0.5 * v_conic_in.y, v_conic_in.z, 0.0),
        vec3<f32>(0.0),
    );
    let v_cov2d = -1.0 * (conic * gm * conic);
    let v_cov_cam = transpose(st.j) * v_cov2d * st.j;
    let v_j = 2.0 * v_cov2d * st.j * st.cov_cam;
    let rot = cam_rot();
    let v_cov_world = transpose(rot) * v_cov_cam * rot;
    let z = st.p_cam.z;
    let x = st.p_cam.x;
    let yy = st.p_cam.y;
    var v_p = vec3<f32>(0.0);
    v_p.x += P.fx / z * v_mean2d.x;
    v_p.y += P.fy / z * v_mean2d.y;
    v_p.z += -P.fx * x / (z * z) * v_mean2d.x - P.fy * yy / (z * z) * v_mean2d.y;
    v_p.z += v_depth;
    let vj00 = v_j[0].x;
    let vj11 = v_j[1].y;
    let vj02 = v_j[2].x;
    let vj12 = v_j[2].y;
    let z2 = z * z;
    let z3 = z2 * z;
    v_p.z += -P.fx / z2 * vj00 - P.fy / z2 * vj11 + 2.0 * P.fx * st.tx / z3 * vj02
        + 2.0 * P.fy * st.ty / z3 * vj12;
    let v_tx = -P.fx / z2 * vj02;
    let v_ty = -P.fy / z2 * vj12;
    if (st.clamped_x) {
        v_p.z += v_tx * st.tx / z;
    } else {
        v_p.x += v_tx;
    }
    if (st.clamped_y) {
        v_p.z += v_ty * st.ty / z;
    } else {
        v_p.y += v_ty;
    }
    v_mean += transpose(rot) * v_p;
    let v_m = 2.0 * v_cov_world * st.m;
    let v_scale = vec3<f32>(dot(st.r[0], v_m[0]), dot(st.r[1], v_m[1]), dot(st.r[2], v_m[2]));
    let v_r = mat3x3<f32>(
        v_rot[0] + v_m[0] * g3.scale.x,
        v_rot[1] + v_m[1] * g3.scale.y,
        v_rot[2] + v_m[2] * g3.scale.z,
    );
    let v_qn = quat_to_rotmat_vjp(st.q, v_r);
    let norm = quat_norm(g3.quat);
    let dq = dot(v_qn, st.q);
    let v_quat = (v_qn - dq * st.q) / norm;

    grads_out[o] = v_mean.x;
    grads_out[o + 1u] = v_mean.y;
    grads_out[o + 2u] = v_mean.z;
    grads_out[o + 3u] = v_quat.x;
    grads_out[o + 4u] = v_quat.y;
    grads_out[o + 5u] = v_quat.z;
    grads_out[o + 6u] = v_quat.w;
    grads_out[o + 7u] = v_scale.x;
    grads_out[o + 8u] = v_scale.y;
    grads_out[o + 9u] = v_scale.z;
    grads_out[o + 10u] = v_opacity;
    grads_out[o + 11u] = v_dc.x;
    grads_out[o + 12u] = v_dc.y;
    grads_out[o + 13u] = v_dc.z;
    for (var f = 0u; f < P.nf; f++) {
        grads_out[o + 14u + k3 + f] = g2d[gb + 10u + f];
    }
    // The screen-space mean gradient (density control accumulates it).
    grads_out[o + 14u + k3 + P.nf] = v_mean2d.x;
    grads_out[o + 15u + k3 + P.nf] = v_mean2d.y;
}
