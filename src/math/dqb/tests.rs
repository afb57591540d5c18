//! DQB tests: closed-form cases, finite differences of every VJP, and MoSca's own outputs
//! (`../shared/data/fixtures/mosca/mosca_dualquat_golden.npz`; see the README there). The
//! golden file does not validate the VJPs (finite differences do) nor blends with more than
//! its fixed number of neighbours.

use std::collections::HashMap;

use super::*;
use crate::math::quat64::tests::TestRng;

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

/// Rotation of `angle` about the unit `axis`.
fn axis_angle(axis: V3, angle: f64) -> Q {
    let (s, c) = (0.5 * angle).sin_cos();
    [c, axis[0] * s, axis[1] * s, axis[2] * s]
}

/// One key's motion from `(q_src, p_src)` to `(q_dst, p_dst)` as a relative dual quaternion.
fn rel_of(q_src: Q, p_src: V3, q_dst: Q, p_dst: V3) -> Dq {
    relative(&from_pose(q_dst, p_dst).0, &from_pose(q_src, p_src).0).0
}

#[test]
fn identity_motion_keeps_the_source_pose() {
    let mut rng = TestRng(1);
    let rel: Vec<Dq> = (0..4)
        .map(|_| {
            let (q, p) = (rng.q(), rng.v());
            rel_of(q, p, q, p)
        })
        .collect();
    let (sp, sq) = (rng.v(), rng.q());
    let out = warp(&rel, &[0.1, 0.2, 0.3, 0.4], sp, sq);
    assert!(close(&out.p, &sp, 1e-12));
    assert!(close(&out.q, &q4::standardize(q4::normalize(sq).0), 1e-12));
}

#[test]
fn pure_translation_moves_the_point_by_the_same_vector() {
    let mut rng = TestRng(2);
    let v = [0.3, -1.2, 2.5];
    let rel: Vec<Dq> = (0..3)
        .map(|_| {
            let (q, p) = (rng.q(), rng.v());
            rel_of(q, p, q, [p[0] + v[0], p[1] + v[1], p[2] + v[2]])
        })
        .collect();
    let sp = rng.v();
    let out = warp(&rel, &[0.5, 0.25, 0.25], sp, [1.0, 0.0, 0.0, 0.0]);
    assert!(close(&out.p, &[sp[0] + v[0], sp[1] + v[1], sp[2] + v[2]], 1e-12));
    assert!(close(&out.q, &[1.0, 0.0, 0.0, 0.0], 1e-12));
}

#[test]
fn blending_two_rotations_about_one_axis_gives_the_mean_angle() {
    let z = [0.0, 0.0, 1.0];
    let id = [1.0, 0.0, 0.0, 0.0];
    let (a, b) = (0.4, 1.4);
    let rel = [
        rel_of(id, [0.0; 3], axis_angle(z, a), [0.0; 3]),
        rel_of(id, [0.0; 3], axis_angle(z, b), [0.0; 3]),
    ];
    let out = warp(&rel, &[0.5, 0.5], [1.0, 0.0, 0.0], id);
    let m = 0.5 * (a + b);
    assert!(close(&out.p, &[m.cos(), m.sin(), 0.0], 1e-12), "{:?}", out.p);
    assert!(close(&out.q, &axis_angle(z, m), 1e-12));
    // Unequal weights stay on the arc between the two angles (DQB is not linear in angle).
    let out = warp(&rel, &[0.8, 0.2], [1.0, 0.0, 0.0], id);
    let ang = out.p[1].atan2(out.p[0]);
    assert!(ang > a && ang < m && (out.p[0].hypot(out.p[1]) - 1.0).abs() < 1e-12);
}

#[test]
fn antipodal_quaternions_blend_as_the_same_rotation() {
    let mut rng = TestRng(4);
    let (qs, ps, pd) = (rng.q(), rng.v(), rng.v());
    let qd = axis_angle([0.0, 0.6, 0.8], 0.9);
    let neg = qd.map(|v| -v);
    let same = [rel_of(qs, ps, qd, pd), rel_of(qs, ps, qd, pd)];
    let anti = [rel_of(qs, ps, qd, pd), rel_of(qs.map(|v| -v), ps, neg, pd)];
    let (sp, sq) = (rng.v(), rng.q());
    let a = warp(&same, &[0.5, 0.5], sp, sq);
    let b = warp(&anti, &[0.5, 0.5], sp, sq);
    assert!(close(&a.p, &b.p, 1e-12) && close(&a.q, &b.q, 1e-12));
}

#[test]
fn near_zero_real_part_becomes_the_identity_with_zero_gradient() {
    // Two 180° rotations about ±x have real parts (0, ±1, 0, 0), which cancel in the blend.
    let id = [1.0, 0.0, 0.0, 0.0];
    let rel = [
        rel_of(id, [0.0; 3], [0.0, 1.0, 0.0, 0.0], [0.0; 3]),
        rel_of(id, [0.0; 3], [0.0, -1.0, 0.0, 0.0], [0.0; 3]),
    ];
    assert!(q4::norm(real(&blend(&rel, &[0.5, 0.5]))) < UNIT_EPS);
    let out = warp(&rel, &[0.5, 0.5], [1.0, 2.0, 3.0], id);
    assert!(close(&out.p, &[1.0, 2.0, 3.0], 0.0) && close(&out.q, &id, 0.0));
    let g = warp_vjp(&rel, &[0.5, 0.5], [1.0, 2.0, 3.0], id, [1.0; 3], [1.0; 4]);
    assert_eq!(g.blend, [0.0; 8]);
}

/// Scalar test loss of a warp: ⟨p, a⟩ + ⟨q, b⟩.
fn probe(out: &Warped, a: V3, b: Q) -> f64 {
    out.p.iter().zip(a).map(|(x, y)| x * y).sum::<f64>() + q4::dot4(out.q, b)
}

#[test]
fn warp_vjp_matches_finite_differences_through_the_key_poses() {
    let mut rng = TestRng(7);
    let k = 4;
    let h = 1e-6;
    let mut fails = Vec::new();
    let mut worst = 0.0f64;
    for case in 0..6 {
        // Inputs: per key (q_src, p_src, q_dst, p_dst), weights, source pose.
        let mut x: Vec<f64> = Vec::new();
        for _ in 0..k {
            x.extend(rng.q().map(|v| v + 1.5));
            x.extend(rng.v());
            x.extend(rng.q().map(|v| v + 1.5));
            x.extend(rng.v());
        }
        for _ in 0..k {
            x.push(0.2 + 0.1 * rng.next());
        }
        x.extend(rng.v());
        x.extend(rng.q().map(|v| v + 1.5));
        let (a, b) = (rng.v(), rng.q());
        let f = |x: &[f64]| -> f64 {
            let (rel, w, sp, sq) = unpack(x, k);
            probe(&warp(&rel, &w, sp, sq), a, b)
        };
        // Analytic: warp_vjp, then relative_vjp and from_pose_vjp per key.
        let (rel, w, sp, sq) = unpack(&x, k);
        let g = warp_vjp(&rel, &w, sp, sq, a, b);
        let mut grad = vec![0.0; x.len()];
        for j in 0..k {
            let o = j * 14;
            let (qs, ps, qd, pd) = key_at(&x, o);
            let (ds, ns) = from_pose(qs, ps);
            let (dd, nd) = from_pose(qd, pd);
            let (_, sign) = relative(&dd, &ds);
            let g_rel = g.blend.map(|v| w[j] * v);
            let (g_dd, g_ds) = relative_vjp(&dd, &ds, sign, &g_rel);
            let (gqs, gps) = from_pose_vjp(&ds, ns, ps, &g_ds);
            let (gqd, gpd) = from_pose_vjp(&dd, nd, pd, &g_dd);
            grad[o..o + 4].copy_from_slice(&gqs);
            grad[o + 4..o + 7].copy_from_slice(&gps);
            grad[o + 7..o + 11].copy_from_slice(&gqd);
            grad[o + 11..o + 14].copy_from_slice(&gpd);
            grad[14 * k + j] = (0..8).map(|c| rel[j][c] * g.blend[c]).sum();
        }
        let o = 15 * k;
        grad[o..o + 3].copy_from_slice(&g.src_p);
        grad[o + 3..o + 7].copy_from_slice(&g.src_q);
        for i in 0..x.len() {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += h;
            xm[i] -= h;
            let fd = (f(&xp) - f(&xm)) / (2.0 * h);
            let err = (fd - grad[i]).abs();
            worst = worst.max(err);
            if err > 1e-6 * (1.0 + fd.abs()) {
                fails.push(format!("case {case} input {i}: analytic {} fd {fd}", grad[i]));
            }
        }
    }
    eprintln!("warp VJP: max |analytic − FD| = {worst:.2e}");
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

fn key_at(x: &[f64], o: usize) -> (Q, V3, Q, V3) {
    let q = |s: usize| [x[s], x[s + 1], x[s + 2], x[s + 3]];
    let v = |s: usize| [x[s], x[s + 1], x[s + 2]];
    (q(o), v(o + 4), q(o + 7), v(o + 11))
}

fn unpack(x: &[f64], k: usize) -> (Vec<Dq>, Vec<f64>, V3, Q) {
    let rel = (0..k)
        .map(|j| {
            let (qs, ps, qd, pd) = key_at(x, j * 14);
            rel_of(qs, ps, qd, pd)
        })
        .collect();
    let w = x[14 * k..15 * k].to_vec();
    let o = 15 * k;
    (rel, w, [x[o], x[o + 1], x[o + 2]], [x[o + 3], x[o + 4], x[o + 5], x[o + 6]])
}

// ---- MoSca golden values -------------------------------------------------------------

/// The arrays of a `.npz` whose members are stored uncompressed (numpy's `savez`), as f64.
fn read_npz(path: &std::path::Path) -> HashMap<String, (Vec<usize>, Vec<f64>)> {
    let bytes = std::fs::read(path).expect("read npz");
    let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]) as usize;
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap()) as usize;
    let mut out = HashMap::new();
    let mut o = 0;
    while o + 30 <= bytes.len() && u32_at(o) == 0x0403_4b50 {
        assert_eq!(u16_at(o + 8), 0, "{}: only stored (uncompressed) members", path.display());
        let (nlen, xlen) = (u16_at(o + 26), u16_at(o + 28));
        let mut size = u32_at(o + 18);
        if size == 0xFFFF_FFFF {
            // Zip64 (numpy writes it): extra field 0x0001 holds the 8-byte sizes.
            let x = o + 30 + nlen;
            assert_eq!(u16_at(x), 1, "{}: zip64 extra field expected", path.display());
            size = u64::from_le_bytes(bytes[x + 12..x + 20].try_into().unwrap()) as usize;
        }
        let name = String::from_utf8_lossy(&bytes[o + 30..o + 30 + nlen]).to_string();
        let start = o + 30 + nlen + xlen;
        let key = name.trim_end_matches(".npy").to_string();
        out.insert(key, parse_npy(&bytes[start..start + size]));
        o = start + size;
    }
    out
}

fn parse_npy(b: &[u8]) -> (Vec<usize>, Vec<f64>) {
    assert_eq!(&b[..6], b"\x93NUMPY");
    let hlen = u16::from_le_bytes([b[8], b[9]]) as usize;
    let header = std::str::from_utf8(&b[10..10 + hlen]).unwrap();
    let descr = header.split("'descr':").nth(1).unwrap().trim_start();
    let descr = &descr[1..descr[1..].find('\'').unwrap() + 1];
    let shape_txt = header.split("'shape':").nth(1).unwrap();
    let shape_txt = &shape_txt[shape_txt.find('(').unwrap() + 1..shape_txt.find(')').unwrap()];
    let shape: Vec<usize> = shape_txt
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().unwrap())
        .collect();
    let n: usize = shape.iter().product();
    let body = &b[10 + hlen..];
    let data = match descr {
        "<f8" => body
            .chunks_exact(8)
            .take(n)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect(),
        "<f4" => body
            .chunks_exact(4)
            .take(n)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
            .collect(),
        "<i8" => body
            .chunks_exact(8)
            .take(n)
            .map(|c| i64::from_le_bytes(c.try_into().unwrap()) as f64)
            .collect(),
        "<i4" => body
            .chunks_exact(4)
            .take(n)
            .map(|c| i32::from_le_bytes(c.try_into().unwrap()) as f64)
            .collect(),
        d => panic!("unsupported dtype {d}"),
    };
    (shape, data)
}

fn mat(v: &[f64]) -> M3 {
    [[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]]
}

#[test]
fn equals_mosca_dualquat_golden() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/fixtures/mosca/mosca_dualquat_golden.npz");
    if !path.exists() {
        eprintln!("SKIP equals_mosca_dualquat_golden: {} not found", path.display());
        return;
    }
    let z = read_npz(&path);
    let get = |k: &str| z.get(k).unwrap_or_else(|| panic!("golden has no key {k}"));
    let mut worst: Vec<(&str, f64)> = Vec::new();
    let mut track = |name: &'static str, a: &[f64], b: &[f64]| {
        assert_eq!(a.len(), b.len(), "{name}: length");
        let e = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        worst.push((name, e));
    };

    // Rt2dq of (R, t): R as a quaternion (pytorch3d), then [p, ½ (0,t) ⊗ p].
    let (r, t) = (&get("R").1, &get("t").1);
    let n = t.len() / 3;
    let mut dqs = Vec::new();
    let mut norms = Vec::new();
    for i in 0..n {
        let q = q4::from_rotmat(&mat(&r[9 * i..9 * i + 9]));
        let d = from_rt(q, [t[3 * i], t[3 * i + 1], t[3 * i + 2]]);
        dqs.extend(d);
        let (a, b) = dual_norm(&d);
        norms.extend([a, b]);
    }
    track("Rt2dq", &dqs, &get("Rt2dq").1);
    track("dq2dualnorm_of_Rt2dq", &norms, &get("dq2dualnorm_of_Rt2dq").1);

    // Blend: dq_blend[m] = Σ_k blend_w[m,k] Rt2dq[blend_idx[m,k]].
    let (bi, bw) = (get("blend_idx"), get("blend_w"));
    let (m, k) = (bi.0[0], bi.0[1]);
    let gold_rt2dq: Vec<Dq> =
        get("Rt2dq").1.chunks_exact(8).map(|c| c.try_into().unwrap()).collect();
    let mut blends = Vec::new();
    let mut bnorm = Vec::new();
    let mut units = Vec::new();
    let (mut rs, mut ts) = (Vec::new(), Vec::new());
    for row in 0..m {
        let rel: Vec<Dq> = (0..k).map(|j| gold_rt2dq[bi.1[row * k + j] as usize]).collect();
        let mut b = blend(&rel, &bw.1[row * k..row * k + k]);
        if row == 1 {
            // The generator scales row 1 by 1e-5 to make the real part shorter than
            // UNIT_EPS (the README: "dq_blend[1] has a real part below 1e-4").
            b = b.map(|v| v * 1e-5);
        }
        blends.extend(b);
        let (a, d) = dual_norm(&b);
        bnorm.extend([a, d]);
    }
    track("dq_blend", &blends, &get("dq_blend").1);
    track("dq2dualnorm_of_blend", &bnorm, &get("dq2dualnorm_of_blend").1);
    for b in get("dq_blend").1.chunks_exact(8) {
        let u = unit(&b.try_into().unwrap());
        units.extend(u);
        let (r, t) = to_rt(&u);
        rs.extend(r.iter().flatten());
        ts.extend(t);
    }
    track("dq2unitdq", &units, &get("dq2unitdq").1);
    track("dq2Rt_R", &rs, &get("dq2Rt_R").1);
    track("dq2Rt_t", &ts, &get("dq2Rt_t").1);

    // Quaternion helpers.
    let (qa, qb) = (&get("qmul_a").1, &get("qmul_b").1);
    let prod: Vec<f64> = qa
        .chunks_exact(4)
        .zip(qb.chunks_exact(4))
        .flat_map(|(a, b)| q4::mul(a.try_into().unwrap(), b.try_into().unwrap()))
        .collect();
    track("quaternion_multiply", &prod, &get("quaternion_multiply").1);
    let q2r: Vec<f64> = qa
        .chunks_exact(4)
        .flat_map(|a| q4::to_rotmat(q4::normalize(a.try_into().unwrap()).0).into_iter().flatten())
        .collect();
    track("q2R_of_qa", &q2r, &get("q2R_of_qa").1);
    let m2q: Vec<f64> = r.chunks_exact(9).flat_map(|c| q4::from_rotmat(&mat(c))).collect();
    track("matrix_to_quaternion_of_R", &m2q, &get("matrix_to_quaternion_of_R").1);

    // __DQB_warp__: relative key motions, blend, dyn_o mix with the identity, unit, apply.
    let (skw, sxyz) = (get("warp_sk_w"), &get("warp_src_xyz").1);
    let (np, kk) = (skw.0[0], skw.0[1]);
    let (snx, snq) = (&get("warp_sk_src_node_xyz").1, &get("warp_sk_src_node_quat").1);
    let (dnx, dnq) = (&get("warp_sk_dst_node_xyz").1, &get("warp_sk_dst_node_quat").1);
    let (dyn_o, src_r) = (&get("warp_dyn_o").1, &get("warp_src_R").1);
    let (mut mu, mut fr) = (Vec::new(), Vec::new());
    let v3 = |a: &[f64], i: usize| [a[3 * i], a[3 * i + 1], a[3 * i + 2]];
    let v4 = |a: &[f64], i: usize| [a[4 * i], a[4 * i + 1], a[4 * i + 2], a[4 * i + 3]];
    for i in 0..np {
        let rel: Vec<Dq> = (0..kk)
            .map(|j| {
                let e = i * kk + j;
                let src = from_pose(v4(snq, e), v3(snx, e)).0;
                let dst = from_pose(v4(dnq, e), v3(dnx, e)).0;
                relative(&dst, &src).0
            })
            .collect();
        let o = dyn_o[i];
        let mut b = blend(&rel, &skw.1[i * kk..i * kk + kk]).map(|v| v * o);
        b[0] += 1.0 - o;
        let (rr, tt) = to_rt(&unit(&b));
        let p = q4::mat_vec(&rr, v3(sxyz, i));
        mu.extend([p[0] + tt[0], p[1] + tt[1], p[2] + tt[2]]);
        let sr = mat(&src_r[9 * i..9 * i + 9]);
        for a in 0..3 {
            for c in 0..3 {
                fr.push((0..3).map(|l| rr[a][l] * sr[l][c]).sum::<f64>());
            }
        }
    }
    track("dqb_mu", &mu, &get("dqb_mu").1);
    track("dqb_fr", &fr, &get("dqb_fr").1);

    eprintln!("MoSca DQB golden, max abs error per output: {worst:?}");
    let bad: Vec<_> = worst.iter().filter(|(_, e)| e.is_nan() || *e > 1e-5).collect();
    assert!(bad.is_empty(), "over 1e-5: {bad:?}");
}
