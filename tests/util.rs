//! Test harness: a temporary directory and a runner for the real `usplat4d` binary.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `usplat4d` binary under test, as a command to add arguments to.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_usplat4d"))
}

/// Run `usplat4d args...` in the current directory; returns (exit code, stderr).
pub fn code_and_stderr<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> (i32, String) {
    let out = bin().args(args).output().expect("spawn usplat4d");
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stderr).into_owned())
}

/// The words of a command line written as one string (`"edges --model m --out ed"`).
#[allow(dead_code)]
pub fn words(line: &str) -> Vec<&str> {
    line.split_whitespace().collect()
}

/// The arguments of `render --model MODEL --scene SCENE --split eval --out OUT`.
pub fn render_eval_args<'a>(model: &'a Path, scene: &'a Path, out: &'a Path) -> [&'a str; 9] {
    let s = |p: &'a Path| p.to_str().expect("UTF-8 path");
    ["render", "--model", s(model), "--scene", s(scene), "--split", "eval", "--out", s(out)]
}

/// A temporary working directory that runs `usplat4d` commands.
pub struct Dir {
    tmp: tempfile::TempDir,
}

impl Dir {
    /// A fresh empty directory.
    pub fn new() -> Dir {
        Dir { tmp: tempfile::tempdir().expect("tempdir") }
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        self.tmp.path()
    }

    /// A path inside it.
    pub fn join(&self, rel: &str) -> PathBuf {
        self.tmp.path().join(rel)
    }

    /// A `usplat4d` command with this directory as working directory.
    pub fn command(&self, args: &[&str]) -> Command {
        let mut c = bin();
        c.args(args).current_dir(self.path());
        c
    }

    /// Run `usplat4d args...`, returning its output whatever the exit code.
    pub fn run(&self, args: &[&str]) -> Output {
        self.command(args).output().expect("spawn usplat4d")
    }

    /// Run and require success; returns stdout.
    pub fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "usplat4d {args:?} failed ({}):\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// Run and require failure with `code`; returns stderr.
    pub fn fails(&self, args: &[&str], code: i32) -> String {
        let out = self.run(args);
        assert_eq!(
            out.status.code(),
            Some(code),
            "usplat4d {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stderr).into_owned()
    }
}

/// `../shared/data/<rel>` beside the repository (or beside a worktree), if present.
#[allow(dead_code)]
pub fn shared_data(rel: &str) -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    [root.join("../shared/data"), root.join("../../shared/data")]
        .into_iter()
        .map(|d| d.join(rel))
        .find(|p| p.exists())
}

/// The repository root.
#[allow(dead_code)]
pub fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Copy a directory tree.
#[allow(dead_code)]
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

/// `(converged, u)` of every frame of the `uncertainty` output in `dir`, in row order.
#[allow(dead_code)]
pub fn converged_and_u(dir: &Path) -> (Vec<bool>, Vec<f32>) {
    let path = dir.join("uncertainty.parquet");
    let r = usplat4d::tables::uncertainty::UncertaintyReader::open(&path).unwrap();
    let (mut c, mut u) = (Vec::new(), Vec::new());
    for t in 0..r.num_frames() {
        let f = r.frame(t).unwrap();
        c.extend(f.converged);
        u.extend(f.u);
    }
    (c, u)
}

/// The three-frame demo scene and model in `dir/demo`, with the model rendered into the
/// training cameras under `dir/R` (scene-relative image paths).
#[allow(dead_code)]
pub fn demo_with_training_renders(dir: &Dir) {
    usplat4d::datasets::demo::write_demo_scene(&dir.join("demo"), 3).unwrap();
    dir.ok(&[
        "render",
        "--model",
        "demo/model",
        "--scene",
        "demo/scene",
        "--out",
        "R",
        "--split",
        "train",
    ]);
}

/// Length of the diagonal of the bounding box of `p` `[N, 3]`.
#[allow(dead_code)]
pub fn bbox_diagonal(p: &[[f32; 3]]) -> f32 {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for q in p {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f32>().sqrt()
}

/// Where [`drifted_prior`] displaced the oracle.
#[allow(dead_code)]
pub struct Drift {
    /// Whether Gaussian i is displaced at frame t, `[N][T]`.
    pub window: Vec<Vec<bool>>,
    /// Whether each Gaussian drifted `[N]`.
    pub drifted: Vec<bool>,
    /// Length of the displacement, world units.
    pub offset: f32,
}

#[allow(dead_code)]
impl Drift {
    /// The displaced (Gaussian row, frame) pairs, by row then frame.
    pub fn pairs(&self) -> Vec<(usize, usize)> {
        let rows = self.window.iter().enumerate();
        rows.flat_map(|(i, w)| w.iter().enumerate().filter(|(_, d)| **d).map(move |(t, _)| (i, t)))
            .collect()
    }
}

/// Which way [`drifted_prior`] displaces a Gaussian.
#[allow(dead_code)]
pub enum DriftDirection<'a> {
    /// One random direction per Gaussian: a drifted point may come out from behind its
    /// occluder and be seen.
    Random,
    /// Away from the camera centre of each frame (`[T]`), along the viewing ray: an occluded
    /// point stays occluded, as under a monocular depth error.
    AwayFrom(&'a [[f64; 3]]),
    /// A given direction per Gaussian (`[N]`, unnormalised; `None`: not displaced), for a
    /// caller that chooses them (the recovery test's directions that keep points hidden).
    Given(&'a [Option<[f64; 3]>]),
}

/// The drifted prior of `oracle` in `dir/drifted`: a seeded half of the dynamic Gaussians
/// (seed 5), each displaced by `fraction` of the bounding-box diagonal of frame 0 in the
/// direction `towards`, at the frames where `unseen(i, t)` (the oracle run does not see
/// Gaussian i at frame t) and `margin` frames either side.
#[allow(dead_code)]
pub fn drifted_prior(
    dir: &Dir,
    oracle: &usplat4d::model::Model,
    unseen: impl Fn(usize, usize) -> bool,
    (fraction, towards): (f32, DriftDirection),
    margin: usize,
) -> Drift {
    let mut states: Vec<_> = (0..oracle.num_frames()).map(|t| oracle.frame(t).unwrap()).collect();
    let (n, nt) = (oracle.gaussians.len(), states.len());
    let offset = fraction * bbox_diagonal(&states[0].position);
    let mut rng = usplat4d::util::rng::Rng::new(5);
    let mut window = vec![vec![false; nt]; n];
    let mut drifted = vec![false; n];
    for i in (0..n).filter(|&i| oracle.gaussians.dynamic[i]) {
        let (pick, mut dir3) = (rng.uniform() < 0.5, [rng.normal(), rng.normal(), rng.normal()]);
        if let DriftDirection::Given(given) = towards {
            match given[i] {
                Some(g) => dir3 = g,
                None => continue,
            }
        }
        let unseen: Vec<usize> = (0..nt).filter(|&t| unseen(i, t)).collect();
        if !pick || unseen.is_empty() {
            continue;
        }
        drifted[i] = true;
        let len = dir3.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-9);
        let d = dir3.map(|v| (v / len) as f32 * offset);
        for &t in &unseen {
            for w in t.saturating_sub(margin)..(t + margin + 1).min(nt) {
                window[i][w] = true;
            }
        }
        for (t, (s, _)) in states.iter_mut().zip(&window[i]).enumerate().filter(|(_, (_, w))| **w) {
            let d = match towards {
                DriftDirection::Random | DriftDirection::Given(_) => d,
                DriftDirection::AwayFrom(c) => {
                    let r = [0, 1, 2].map(|k| s.position[i][k] as f64 - c[t][k]);
                    let len = r.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-9);
                    r.map(|v| (v / len) as f32 * offset)
                }
            };
            for k in 0..3 {
                s.position[i][k] += d[k];
            }
        }
    }
    usplat4d::model::Model::save(
        &dir.join("drifted"),
        &oracle.gaussians,
        states.into_iter().map(Ok),
        &usplat4d::tables::Provenance::default(),
    )
    .unwrap();
    Drift { window, drifted, offset }
}
