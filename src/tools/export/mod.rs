//! `usplat4d export ply|gltf`: a model's frames as files that Gaussian-splat viewers open,
//! one per frame (`OUT/frame_00012.ply` or `.glb`), each holding every Gaussian at that
//! frame's pose.
//!
//! [`splats`] turns a model frame into 3DGS terms (world-frame SH), [`ply`] writes the 3DGS
//! PLY and [`glb`] the glTF with `KHR_gaussian_splatting`. Files are written into a staging
//! directory beside OUT and moved in once every frame is written, so a bad frame leaves no
//! partial output.

pub mod glb;
pub mod ply;
pub mod splats;

use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::context::Context;
use crate::model::Model;
use crate::util::fs::{publish, staging_dir};

use splats::Splats;

/// `usplat4d export ...`
#[derive(Debug, clap::Subcommand)]
pub enum ExportCommand {
    /// One 3DGS PLY per frame (binary little-endian; f_dc/f_rest, opacity logit, log
    /// scales, rotation w x y z), as splat viewers read them.
    Ply(ExportParams),
    /// One binary glTF per frame with the KHR_gaussian_splatting extension (linear scales,
    /// opacity in [0, 1], rotation x y z w).
    Gltf(ExportParams),
}

/// Parameters of `usplat4d export ply|gltf`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ExportParams {
    /// Model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, help_heading = "Inputs")]
    pub model: PathBuf,
    /// Output directory; frame t goes to OUT/frame_<t:05>.<ext>.
    #[arg(long, help_heading = "Outputs")]
    pub out: PathBuf,
    /// Frames to export: comma-separated frames and inclusive ranges (`0,5,10-20`); all
    /// frames when absent.
    #[arg(long, value_parser = parse_frames, help_heading = "Selection")]
    #[serde(default)]
    pub frames: Option<FrameList>,
}

/// A list of frame indices in the order given (duplicates removed).
#[derive(Debug, Clone, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
pub struct FrameList(pub Vec<usize>);

fn parse_frames(s: &str) -> Result<FrameList, String> {
    let mut out: Vec<usize> = Vec::new();
    for part in s.split(',').map(str::trim) {
        let num = |t: &str| {
            t.trim()
                .parse::<usize>()
                .map_err(|_| format!("'{t}' is not a frame index (expected e.g. 0,5,10-20)"))
        };
        let range = match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (num(a)?, num(b)?);
                if a > b {
                    return Err(format!("range '{part}' is empty (start after end)"));
                }
                a..=b
            }
            None => {
                let a = num(part)?;
                a..=a
            }
        };
        for t in range {
            if !out.contains(&t) {
                out.push(t);
            }
        }
    }
    Ok(FrameList(out))
}

/// File format of an export.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// 3DGS PLY.
    Ply,
    /// Binary glTF with `KHR_gaussian_splatting`.
    Glb,
}

impl Format {
    fn extension(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::Glb => "glb",
        }
    }
}

/// Run `usplat4d export`.
pub fn run_command(c: &ExportCommand, ctx: &Context) -> anyhow::Result<()> {
    match c {
        ExportCommand::Ply(p) => run(p, Format::Ply, ctx),
        ExportCommand::Gltf(p) => run(p, Format::Glb, ctx),
    }
}

/// File name of frame `t`.
pub fn file_name(t: usize, format: Format) -> String {
    format!("frame_{t:05}.{}", format.extension())
}

/// Export the frames `p` selects of `p.model` into `p.out`.
pub fn run(p: &ExportParams, format: Format, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("export", format = format.extension()).entered();
    let model = Model::load(&p.model)?;
    let t_max = model.num_frames();
    let frames: Vec<usize> = match &p.frames {
        Some(FrameList(f)) => f.clone(),
        None => (0..t_max).collect(),
    };
    if let Some(t) = frames.iter().find(|t| **t >= t_max) {
        anyhow::bail!(
            "--frames: frame {t} is out of range: {} has {t_max} frames (0..={})",
            Model::trajectories_path(&p.model).display(),
            t_max.saturating_sub(1)
        );
    }
    let staging = staging_dir(&p.out, ".export-")?;
    let bar = ctx.progress(frames.len() as u64, "export");
    for &t in &frames {
        let state = model.frame(t)?;
        let splats = Splats::from_frame(&model.gaussians, model.sh_frame, &state);
        let bytes = match format {
            Format::Ply => ply::encode(&splats),
            Format::Glb => glb::encode(&splats, &format!("frame {t}")),
        };
        let path = staging.path().join(file_name(t, format));
        std::fs::write(&path, bytes).with_context(|| path.display().to_string())?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    publish(staging.path(), &p.out)?;
    ctx.info(format!(
        "exported {} frames of {} Gaussians into {}",
        frames.len(),
        model.gaussians.len(),
        p.out.display()
    ));
    Ok(())
}

/// The exported file of frame `t` in `dir`.
pub fn frame_path(dir: &Path, t: usize, format: Format) -> PathBuf {
    dir.join(file_name(t, format))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{FrameState, Gaussians};
    use crate::render::sh::C0;
    use crate::tables::Provenance;

    /// A model of degree-3 SH whose frames differ, with the extreme opacities and a zero
    /// scale the encoders clamp.
    fn model(dir: &Path) -> (Gaussians, Vec<FrameState>) {
        let (mut g, mut frames) = crate::model::sample_model();
        g.sh_degree = 3;
        g.sh_rest = (0..g.len() * 45).map(|i| (i as f32 * 0.37).sin() * 0.2).collect();
        g.opacity[0] = 1.0;
        g.opacity[1] = 0.0;
        g.scale[1][2] = 0.0;
        for (t, f) in frames.iter_mut().enumerate() {
            for (i, p) in f.position.iter_mut().enumerate() {
                p[0] += t as f32;
                p[1] -= i as f32 * 0.5;
            }
        }
        Model::save(dir, &g, frames.clone().into_iter().map(Ok), &Provenance::default()).unwrap();
        (g, frames)
    }

    fn close(a: f32, b: f64, what: &str) {
        assert!((a as f64 - b).abs() <= 1e-5 * (1.0 + b.abs()), "{what}: {a} vs {b}");
    }

    /// Every attribute of every Gaussian read back from the PLY of a frame: positions of
    /// that frame, zero normals, f_dc, channel-major f_rest, opacity logit (clamped), log
    /// scale (clamped), unit rotation w x y z.
    #[test]
    fn ply_files_hold_every_attribute_of_their_frame() {
        let tmp = tempfile::tempdir().unwrap();
        let (g, frames) = model(&tmp.path().join("m"));
        let out = tmp.path().join("ply");
        let p = ExportParams {
            model: tmp.path().join("m"),
            out: out.clone(),
            frames: Some(parse_frames("1").unwrap()),
        };
        run(&p, Format::Ply, &Context::quiet()).unwrap();
        let names: Vec<_> =
            std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["frame_00001.ply"]);
        let (props, rows) =
            ply::read::decode(&std::fs::read(frame_path(&out, 1, Format::Ply)).unwrap());
        assert_eq!(props, ply::property_names(15));
        assert_eq!(props.len(), 62, "the 3DGS layout of degree 3");
        assert_eq!(rows.len(), g.len());
        let col = |name: &str| props.iter().position(|p| p == name).unwrap();
        let f = &frames[1];
        for (i, row) in rows.iter().enumerate() {
            for c in 0..3 {
                close(row[col(["x", "y", "z"][c])], f.position[i][c] as f64, "position");
                assert_eq!(row[col(["nx", "ny", "nz"][c])], 0.0);
                close(row[col(&format!("f_dc_{c}"))], (g.color[i][c] as f64 - 0.5) / C0, "f_dc");
                for k in 0..15 {
                    let want = g.sh_rest[i * 45 + k * 3 + c] as f64;
                    close(row[col(&format!("f_rest_{}", c * 15 + k))], want, "f_rest");
                }
                let s = (g.scale[i][c] as f64).max(ply::MIN_SCALE);
                close(row[col(&format!("scale_{c}"))], s.ln(), "scale");
            }
            let o = (g.opacity[i] as f64).clamp(ply::OPACITY_EPS, 1.0 - ply::OPACITY_EPS);
            close(row[col("opacity")], (o / (1.0 - o)).ln(), "opacity");
            let q = crate::math::quat::normalize(f.rotation[i]).unwrap().0;
            for c in 0..4 {
                close(row[col(&format!("rot_{c}"))], q[c] as f64, "rotation");
            }
            assert!(row.iter().all(|v| v.is_finite()), "row {i}: {row:?}");
        }
    }

    /// Every attribute read back from the glTF of a frame: the extension's semantics,
    /// linear scales, opacity in [0, 1], rotation x y z w, SH coefficients by degree and
    /// order, POSITION bounds.
    #[test]
    fn gltf_files_hold_every_attribute_of_their_frame() {
        let tmp = tempfile::tempdir().unwrap();
        let (g, frames) = model(&tmp.path().join("m"));
        let out = tmp.path().join("glb");
        let p = ExportParams { model: tmp.path().join("m"), out: out.clone(), frames: None };
        run(&p, Format::Glb, &Context::quiet()).unwrap();
        for (t, f) in frames.iter().enumerate() {
            let bytes = std::fs::read(frame_path(&out, t, Format::Glb)).unwrap();
            let (doc, attrs) = glb::read::decode(&bytes);
            assert_eq!(doc["extensionsUsed"][0], glb::EXTENSION);
            let prim = &doc["meshes"][0]["primitives"][0];
            assert_eq!(prim["mode"], 0);
            assert_eq!(prim["extensions"][glb::EXTENSION]["kernel"], "ellipse");
            assert_eq!(attrs.len(), 5 + 15, "POSITION, ROTATION, SCALE, OPACITY and 16 SH");
            let a = |s: &str| &attrs[&format!("{}:{s}", glb::EXTENSION)];
            let n = g.len();
            for i in 0..n {
                for c in 0..3 {
                    close(attrs["POSITION"][i * 3 + c], f.position[i][c] as f64, "position");
                    close(a("SCALE")[i * 3 + c], g.scale[i][c] as f64, "scale");
                    let dc = (g.color[i][c] as f64 - 0.5) / C0;
                    close(a("SH_DEGREE_0_COEF_0")[i * 3 + c], dc, "sh0");
                    let mut j = 0;
                    for l in 1..=3 {
                        for m in 0..2 * l + 1 {
                            let v = a(&format!("SH_DEGREE_{l}_COEF_{m}"))[i * 3 + c];
                            close(v, g.sh_rest[i * 45 + j * 3 + c] as f64, "sh");
                            j += 1;
                        }
                    }
                }
                close(a("OPACITY")[i], g.opacity[i] as f64, "opacity");
                let q = crate::math::quat::normalize(f.rotation[i]).unwrap().0;
                let xyzw = [q[1], q[2], q[3], q[0]];
                for c in 0..4 {
                    close(a("ROTATION")[i * 4 + c], xyzw[c] as f64, "rotation");
                }
            }
            let acc = &doc["accessors"][prim["attributes"]["POSITION"].as_u64().unwrap() as usize];
            let lo = f.position.iter().map(|p| p[0]).fold(f32::INFINITY, f32::min);
            assert_eq!(acc["min"][0].as_f64().unwrap() as f32, lo);
        }
    }

    /// A frame beyond the model is an error naming the trajectories file, and nothing is
    /// written; a malformed list names what was expected.
    #[test]
    fn bad_frames_are_rejected_and_leave_no_output() {
        let tmp = tempfile::tempdir().unwrap();
        model(&tmp.path().join("m"));
        let out = tmp.path().join("x");
        let p = ExportParams {
            model: tmp.path().join("m"),
            out: out.clone(),
            frames: Some(parse_frames("0,99").unwrap()),
        };
        let e = format!("{:#}", run(&p, Format::Ply, &Context::quiet()).unwrap_err());
        assert!(e.contains("frame 99") && e.contains("trajectories.parquet"), "{e}");
        assert!(!out.exists());
        let left: Vec<_> =
            std::fs::read_dir(tmp.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, ["m"], "no staging directory left");
        assert_eq!(parse_frames("3, 1-2,3").unwrap(), FrameList(vec![3, 1, 2]));
        assert!(parse_frames("2-1").unwrap_err().contains("empty"));
        assert!(parse_frames("a").unwrap_err().contains("not a frame index"));
    }
}
