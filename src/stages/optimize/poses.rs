//! Trainable per-frame poses of every Gaussian (the release's free `[T, N, 3]` and `[T, N, 4]`
//! tensors) and gradients of the same layout, shared by the loss functions and the training loop.
//! Static Gaussians are tied to one pose by the training loop; the losses see only positions and
//! rotations.

/// Trainable per-frame poses of all N Gaussians over T frames, frame-major (index `t * n + i`).
#[derive(Debug, Clone, PartialEq)]
pub struct Poses {
    /// T, the number of frames.
    pub frames: usize,
    /// N, the number of Gaussians.
    pub n: usize,
    /// `[T, N, 3]` world-space centres.
    pub position: Vec<[f32; 3]>,
    /// `[T, N, 4]` rotations as quaternions (w, x, y, z), unnormalised.
    pub rotation: Vec<[f32; 4]>,
}

impl Poses {
    /// Poses with every position zero and every rotation the identity.
    pub fn identity(frames: usize, n: usize) -> Self {
        Self {
            frames,
            n,
            position: vec![[0.0; 3]; frames * n],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; frames * n],
        }
    }

    /// Poses of `n` Gaussians with no frame yet and room for `frames` frames: push each
    /// frame's `n` positions and rotations in frame order.
    pub fn with_capacity(frames: usize, n: usize) -> Self {
        Self {
            frames,
            n,
            position: Vec::with_capacity(frames * n),
            rotation: Vec::with_capacity(frames * n),
        }
    }

    /// Flat index of Gaussian `i` at frame `t`.
    #[inline]
    pub fn idx(&self, t: usize, i: usize) -> usize {
        debug_assert!(t < self.frames && i < self.n);
        t * self.n + i
    }

    /// Position of Gaussian `i` at frame `t`.
    #[inline]
    pub fn p(&self, t: usize, i: usize) -> [f32; 3] {
        self.position[self.idx(t, i)]
    }

    /// Rotation (w, x, y, z, unnormalised) of Gaussian `i` at frame `t`.
    #[inline]
    pub fn q(&self, t: usize, i: usize) -> [f32; 4] {
        self.rotation[self.idx(t, i)]
    }

    /// Checks that both tensors hold `frames * n` entries.
    pub fn check(&self) -> Result<(), String> {
        let want = self.frames * self.n;
        if self.position.len() != want || self.rotation.len() != want {
            return Err(format!(
                "poses: position has {} and rotation {} entries, expected T*N = {}*{} = {want}",
                self.position.len(),
                self.rotation.len(),
                self.frames,
                self.n
            ));
        }
        Ok(())
    }
}

/// Gradients with the same layout as [`Poses`] (`[T, N, 3]` and `[T, N, 4]`, frame-major).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGrads {
    /// `[T, N, 3]` d loss / d position.
    pub position: Vec<[f32; 3]>,
    /// `[T, N, 4]` d loss / d rotation (w.r.t. the unnormalised quaternion).
    pub rotation: Vec<[f32; 4]>,
}

impl PoseGrads {
    /// All-zero gradients for `frames` frames of `n` Gaussians.
    pub fn zeros(frames: usize, n: usize) -> Self {
        Self { position: vec![[0.0; 3]; frames * n], rotation: vec![[0.0; 4]; frames * n] }
    }

    /// Sets every gradient to zero, keeping the allocation.
    pub fn clear(&mut self) {
        self.position.fill([0.0; 3]);
        self.rotation.fill([0.0; 4]);
    }

    /// Add the rows of `rows` (`[frames.len(), n]`) to the frames `frames` (row j to frame
    /// `frames[j]`, in row order).
    pub fn add_rows(&mut self, rows: &PoseGrads, frames: &[usize]) {
        let n = rows.position.len() / frames.len().max(1);
        for (j, &t) in frames.iter().enumerate() {
            let (to, from) = (t * n..(t + 1) * n, j * n..(j + 1) * n);
            for (a, b) in self.position[to.clone()].iter_mut().zip(&rows.position[from.clone()]) {
                (0..3).for_each(|c| a[c] += b[c]);
            }
            for (a, b) in self.rotation[to].iter_mut().zip(&rows.rotation[from]) {
                (0..4).for_each(|c| a[c] += b[c]);
            }
        }
    }

    /// Zero gradients for `frames` frames of `n` Gaussians, reusing the allocation (cleared
    /// in parallel).
    pub fn reset(&mut self, frames: usize, n: usize) {
        use rayon::prelude::*;
        self.position.resize(frames * n, [0.0; 3]);
        self.rotation.resize(frames * n, [0.0; 4]);
        self.position.par_chunks_mut(1 << 16).for_each(|c| c.fill([0.0; 3]));
        self.rotation.par_chunks_mut(1 << 16).for_each(|c| c.fill([0.0; 4]));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_major_index() {
        let mut p = Poses::identity(3, 5);
        assert!(p.check().is_ok());
        let k = p.idx(2, 4);
        assert_eq!(k, 14);
        p.position[k] = [1.0, 2.0, 3.0];
        assert_eq!(p.p(2, 4), [1.0, 2.0, 3.0]);
        assert_eq!(p.q(1, 1), [1.0, 0.0, 0.0, 0.0]);
        p.rotation.pop();
        assert!(p.check().is_err());
        let mut g = PoseGrads::zeros(3, 5);
        g.position[k][0] = 1.0;
        g.clear();
        assert_eq!(g, PoseGrads::zeros(3, 5));
        g.position[k][0] = 1.0;
        g.reset(2, 7);
        assert_eq!(g, PoseGrads::zeros(2, 7));
    }

    #[test]
    fn rows_are_added_to_their_frames() {
        let mut g = PoseGrads::zeros(4, 2);
        g.position[2 * 2 + 1] = [1.0, 0.0, 0.0];
        let mut rows = PoseGrads::zeros(3, 2);
        for (j, r) in rows.position.iter_mut().enumerate() {
            *r = [j as f32, 1.0, 0.0];
        }
        rows.rotation[5] = [0.0, 0.0, 0.0, 2.0];
        // frame 2 twice (a batch longer than the frames): both rows land on it
        g.add_rows(&rows, &[2, 0, 2]);
        assert_eq!(g.position[2 * 2 + 1], [1.0 + 1.0 + 5.0, 2.0, 0.0]);
        assert_eq!(g.position[0], [2.0, 1.0, 0.0]);
        assert_eq!(g.position[2], [0.0; 3], "frame 1 untouched");
        assert_eq!(g.rotation[2 * 2 + 1], [0.0, 0.0, 0.0, 2.0]);
    }
}
