//! Animation sampling (glTF 2.0 §3.11): LINEAR, STEP and CUBICSPLINE samplers for
//! translation, rotation (slerp; cubic Hermite then normalised) and scale and morph weights,
//! the per-node pose at a time, world matrices down the node hierarchy, and the benchmark's
//! frame → animation-time mapping (sampled at `fps`, cycled zig-zag when too short).

use glam::{Mat4, Quat, Vec3};

/// Interpolation of an animation sampler.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interp {
    /// Linear (spherical linear for rotations).
    Linear,
    /// Hold the previous keyframe.
    Step,
    /// Cubic Hermite spline with in/out tangents per keyframe.
    CubicSpline,
}

/// The node property a channel animates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Property {
    /// Translation (3 values).
    Translation,
    /// Rotation quaternion x, y, z, w (4 values).
    Rotation,
    /// Scale (3 values).
    Scale,
    /// Morph target weights (one value per target).
    Weights,
}

/// One animation channel with its sampler data.
#[derive(Debug, Clone)]
pub struct Channel {
    /// Target node.
    pub node: usize,
    /// Animated property.
    pub property: Property,
    /// Interpolation.
    pub interp: Interp,
    /// Keyframe times, seconds, strictly increasing, `[K]`.
    pub times: Vec<f32>,
    /// Keyframe values `[K, width]`, or `[K, 3, width]` (in-tangent, value, out-tangent) for
    /// cubic splines.
    pub values: Vec<f32>,
    /// Components per value.
    pub width: usize,
}

/// A named animation.
#[derive(Debug, Clone)]
pub struct Animation {
    /// Name (`animation<i>` when the file gives none).
    pub name: String,
    /// Channels.
    pub channels: Vec<Channel>,
    /// Earliest keyframe time, seconds.
    pub start: f32,
    /// Latest keyframe time, seconds.
    pub end: f32,
}

impl Channel {
    /// Value of keyframe `k` (for cubic splines element `e`: 0 in-tangent, 1 value, 2 out-tangent).
    fn key(&self, k: usize, e: usize) -> &[f32] {
        let (w, per) = (self.width, if self.interp == Interp::CubicSpline { 3 } else { 1 });
        let e = if per == 3 { e } else { 0 };
        let o = (k * per + e) * w;
        &self.values[o..o + w]
    }

    /// The sampled value at time `t` (clamped to the keyframe range), `[width]`; rotations are
    /// unit quaternions x, y, z, w.
    pub fn sample(&self, t: f32) -> Vec<f32> {
        let n = self.times.len();
        let k = self.times.partition_point(|&x| x <= t);
        if k == 0 || k == n {
            let i = if k == 0 { 0 } else { n - 1 };
            return self.key(i, 1).to_vec();
        }
        let (k0, k1) = (k - 1, k);
        let dt = self.times[k1] - self.times[k0];
        let u = (t - self.times[k0]) / dt;
        let (a, b) = (self.key(k0, 1), self.key(k1, 1));
        match (self.interp, self.property) {
            (Interp::Step, _) => a.to_vec(),
            (Interp::Linear, Property::Rotation) => {
                let qa = Quat::from_slice(a).normalize();
                let qb = Quat::from_slice(b).normalize();
                qa.slerp(qb, u).normalize().to_array().to_vec()
            }
            (Interp::Linear, _) => a.iter().zip(b).map(|(a, b)| a + (b - a) * u).collect(),
            (Interp::CubicSpline, prop) => {
                let (m0, m1) = (self.key(k0, 2), self.key(k1, 0));
                let (u2, u3) = (u * u, u * u * u);
                let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
                let h10 = u3 - 2.0 * u2 + u;
                let h01 = -2.0 * u3 + 3.0 * u2;
                let h11 = u3 - u2;
                let v: Vec<f32> = (0..self.width)
                    .map(|i| h00 * a[i] + h10 * dt * m0[i] + h01 * b[i] + h11 * dt * m1[i])
                    .collect();
                if prop == Property::Rotation {
                    let q = Quat::from_slice(&v);
                    let q = if q.length_squared() > 0.0 { q.normalize() } else { Quat::IDENTITY };
                    q.to_array().to_vec()
                } else {
                    v
                }
            }
        }
    }
}

/// Rest transform and links of one glTF node.
#[derive(Debug, Clone)]
pub struct Node {
    /// Rest translation.
    pub translation: Vec3,
    /// Rest rotation.
    pub rotation: Quat,
    /// Rest scale.
    pub scale: Vec3,
    /// Child node indices.
    pub children: Vec<usize>,
    /// Morph weights of the node's mesh at rest (node weights, else mesh weights), `[targets]`.
    pub weights: Vec<f32>,
}

/// The pose of every node at one time.
#[derive(Debug, Clone)]
pub struct Pose {
    /// Node-to-world matrices (glTF world space), `[nodes]`.
    pub world: Vec<Mat4>,
    /// Morph weights of each node's mesh, `[nodes][targets]`.
    pub weights: Vec<Vec<f32>>,
}

/// Pose the node hierarchy (`nodes` and the `parent` of each) at time `t` of `anim` (rest
/// pose without an animation).
pub fn pose(nodes: &[Node], parent: &[Option<usize>], anim: Option<&Animation>, t: f32) -> Pose {
    let mut trs: Vec<(Vec3, Quat, Vec3)> =
        nodes.iter().map(|n| (n.translation, n.rotation, n.scale)).collect();
    let mut weights: Vec<Vec<f32>> = nodes.iter().map(|n| n.weights.clone()).collect();
    for ch in anim.map(|a| a.channels.as_slice()).unwrap_or(&[]) {
        let v = ch.sample(t);
        let n = ch.node;
        match ch.property {
            Property::Translation => trs[n].0 = Vec3::from_slice(&v),
            Property::Rotation => trs[n].1 = Quat::from_slice(&v),
            Property::Scale => trs[n].2 = Vec3::from_slice(&v),
            Property::Weights => weights[n] = v,
        }
    }
    let local: Vec<Mat4> =
        trs.iter().map(|&(t, r, s)| Mat4::from_scale_rotation_translation(s, r, t)).collect();
    let mut world = vec![None; local.len()];
    for i in 0..local.len() {
        resolve_world(i, parent, &local, &mut world);
    }
    Pose { world: world.into_iter().map(|m| m.unwrap_or(Mat4::IDENTITY)).collect(), weights }
}

/// World matrix of node `i`, walking up to the first resolved ancestor (iteratively).
fn resolve_world(i: usize, parent: &[Option<usize>], local: &[Mat4], world: &mut [Option<Mat4>]) {
    let mut chain = Vec::new();
    let mut n = Some(i);
    while let Some(k) = n {
        if world[k].is_some() || chain.contains(&k) {
            break;
        }
        chain.push(k);
        n = parent[k];
    }
    let mut acc = n.and_then(|k| world[k]).unwrap_or(Mat4::IDENTITY);
    for &k in chain.iter().rev() {
        acc *= local[k];
        world[k] = Some(acc);
    }
}

/// Animation time, seconds, of benchmark frame `frame`: the animation is sampled at `fps`
/// from `start`; when it has fewer samples than needed it is played forward, then backward,
/// and so on (zig-zag), so motion stays continuous.
pub fn frame_time(frame: u32, fps: f64, start: f32, end: f32) -> f32 {
    let samples = ((end - start).max(0.0) as f64 * fps + 1e-4).floor() as u64 + 1;
    if samples <= 1 {
        return start;
    }
    let period = 2 * (samples - 1);
    let k = frame as u64 % period;
    let idx = if k < samples { k } else { period - k };
    (start as f64 + idx as f64 / fps).min(end as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(
        property: Property,
        interp: Interp,
        times: Vec<f32>,
        values: Vec<f32>,
        width: usize,
    ) -> Channel {
        Channel { node: 0, property, interp, times, values, width }
    }

    #[test]
    fn linear_and_step_translation() {
        let c = channel(
            Property::Translation,
            Interp::Linear,
            vec![0.0, 1.0],
            vec![0.0, 0.0, 0.0, 2.0, 4.0, 6.0],
            3,
        );
        assert_eq!(c.sample(0.25), vec![0.5, 1.0, 1.5]);
        assert_eq!(c.sample(-1.0), vec![0.0, 0.0, 0.0]);
        assert_eq!(c.sample(5.0), vec![2.0, 4.0, 6.0]);
        let s = Channel { interp: Interp::Step, ..c };
        assert_eq!(s.sample(0.99), vec![0.0, 0.0, 0.0]);
        assert_eq!(s.sample(1.0), vec![2.0, 4.0, 6.0]);
    }

    #[test]
    fn linear_rotation_is_slerp() {
        let a = Quat::IDENTITY;
        let b = Quat::from_rotation_y(std::f32::consts::FRAC_PI_2);
        let v: Vec<f32> = a.to_array().into_iter().chain(b.to_array()).collect();
        let c = channel(Property::Rotation, Interp::Linear, vec![0.0, 2.0], v, 4);
        let q = Quat::from_slice(&c.sample(1.0));
        let want = Quat::from_rotation_y(std::f32::consts::FRAC_PI_4);
        assert!(q.angle_between(want) < 1e-5, "{q:?}");
        assert!((q.length() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn cubic_spline_hermite_and_normalised_rotation() {
        // One component, p0 = 0, p1 = 1, out-tangent 0 at k0, in-tangent 0 at k1: smoothstep.
        let v = vec![9.0, 0.0, 0.0, 0.0, 1.0, 9.0];
        let c = channel(Property::Scale, Interp::CubicSpline, vec![0.0, 2.0], v, 1);
        let got = c.sample(0.5)[0];
        let u = 0.25f32;
        assert!((got - (3.0 * u * u - 2.0 * u * u * u)).abs() < 1e-6);
        // Tangents scale with the keyframe interval: p0 = p1 = 0, m0 = 1 gives dt*h10.
        let v = vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
        let c = channel(Property::Scale, Interp::CubicSpline, vec![0.0, 2.0], v, 1);
        let u = 0.5f32;
        assert!((c.sample(1.0)[0] - 2.0 * (u * u * u - 2.0 * u * u + u)).abs() < 1e-6);
        // Rotations come back unit length.
        let q0 = [0.0, 0.0, 0.0, 1.0];
        let q1 = Quat::from_rotation_x(1.0).to_array();
        let z = [0.0; 4];
        let v: Vec<f32> = [z, q0, z, z, q1, z].concat();
        let c = channel(Property::Rotation, Interp::CubicSpline, vec![0.0, 1.0], v, 4);
        let q = Quat::from_slice(&c.sample(0.5));
        assert!((q.length() - 1.0).abs() < 1e-6);
        assert!((q.angle_between(Quat::from_rotation_x(0.5))).abs() < 1e-3);
    }

    #[test]
    fn zig_zag_frame_mapping() {
        // 0.1 s at 30 fps: samples 0, 1, 2, 3 → frames 0..7 map to 0 1 2 3 2 1 0 1.
        let idx: Vec<u32> =
            (0..8).map(|f| (frame_time(f, 30.0, 0.0, 0.1) * 30.0).round() as u32).collect();
        assert_eq!(idx, vec![0, 1, 2, 3, 2, 1, 0, 1]);
        assert_eq!(frame_time(5, 30.0, 2.0, 2.0), 2.0);
        // Long enough: plain playback from the start time.
        assert!((frame_time(10, 10.0, 1.0, 5.0) - 2.0).abs() < 1e-6);
    }
}
