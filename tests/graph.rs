//! End-to-end tests of the graph stages through the CLI: `keynodes` → `edges` → `segment`
//! on a hand-made model of two rigid objects that touch but move differently, with a
//! hand-made uncertainty table (the renderer is not involved).
//!
//! Not validated here: the `uncertainty` stage (it needs the renderer and a scene; its pure
//! parts are unit-tested in `src/stages/uncertainty.rs`).

use std::path::Path;

use usplat4d::model::{FrameState, Gaussians, Model};
use usplat4d::stages::graph::spectral::adjusted_rand_index;
use usplat4d::stages::graph::tracks::Tracks;
use usplat4d::tables::Provenance;
use usplat4d::tables::uncertainty::{UncertaintyFrame, UncertaintyWriter};
use usplat4d::util::rng::Rng;

use crate::util::words;

const N: usize = 1200;
const T: usize = 24;

/// Two touching blobs: group 0 turns about z around its centre, group 1 slides along y.
fn two_objects(seed: u64) -> (Tracks, Vec<u32>) {
    let mut rng = Rng::new(seed);
    let mut tr = Tracks {
        ids: (0..N as u32).map(|i| 1000 + 3 * i).collect(),
        num_frames: T,
        ..Default::default()
    };
    let mut group = Vec::new();
    for i in 0..N {
        let g = (i % 2) as u32;
        group.push(g);
        let c = if g == 0 { [-0.6, 0.0, 0.0] } else { [0.6, 0.0, 0.0] };
        let o = [rng.normal() * 0.25, rng.normal() * 0.25, rng.normal() * 0.25];
        let u0 = (0.05 * (0.5 * rng.normal()).exp()) as f32;
        for t in 0..T {
            let p = if g == 0 {
                let a = 0.08 * t as f64;
                [
                    c[0] + a.cos() * o[0] - a.sin() * o[1],
                    c[1] + a.sin() * o[0] + a.cos() * o[1],
                    c[2] + o[2],
                ]
            } else {
                [c[0] + o[0], c[1] + o[1] + 0.05 * t as f64, c[2] + o[2]]
            };
            tr.positions.push(p.map(|v| v as f32));
            let hidden = rng.uniform() < 0.1;
            tr.u.push(if hidden { 1e8 } else { u0 * (0.2 * rng.normal()).exp() as f32 });
            tr.reliable.push(!hidden);
        }
    }
    (tr, group)
}

fn write_inputs(dir: &Path, tr: &Tracks) {
    let n = tr.len();
    let g = Gaussians {
        id: tr.ids.clone(),
        dynamic: vec![true; n],
        scale: vec![[0.01; 3]; n],
        opacity: vec![0.9; n],
        color: vec![[0.5; 3]; n],
        sh_degree: 0,
        sh_rest: Vec::new(),
    };
    let frames = (0..T).map(|t| {
        Ok(FrameState {
            frame: t as u32,
            position: (0..n).map(|i| tr.pos(i, t)).collect(),
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
        })
    });
    Model::save(&dir.join("model"), &g, frames, &Provenance::default()).unwrap();
    let path = dir.join("unc/uncertainty.parquet");
    let mut w = UncertaintyWriter::create(&path, &tr.ids, &Provenance::default()).unwrap();
    for t in 0..T {
        let u: Vec<f32> = (0..n).map(|i| tr.u(i, t)).collect();
        let converged: Vec<bool> = (0..n).map(|i| tr.reliable(i, t)).collect();
        w.write(&UncertaintyFrame {
            frame: t as u32,
            sum_w2: u.iter().zip(&converged).map(|(u, c)| if *c { 1.0 / u } else { 0.5 }).collect(),
            sum_w: vec![1.0; n],
            n_pixels: vec![4; n],
            converged,
            u,
        })
        .unwrap();
    }
    w.finish().unwrap();
}

/// `keynodes` on the inputs of [`write_inputs`].
const KEYNODES: &str = "keynodes --model model --uncertainty unc --out kn";
/// `edges` on the inputs of [`write_inputs`] and the output of [`KEYNODES`].
const EDGES: &str = "edges --model model --uncertainty unc --keynodes kn --out ed";

fn usplat4d(dir: &Path, args: &[&str]) -> String {
    let out = crate::util::bin().current_dir(dir).args(args).output().unwrap();
    let text =
        format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "usplat4d {args:?} failed:\n{text}");
    text
}

/// Run the three stages with `profile` and extra edge arguments; returns the ARI of the
/// segments and the edges file bytes.
fn pipeline(dir: &Path, profile: &str, edge_args: &[&str], threads: &str) -> (f64, Vec<u8>) {
    let mut kn = vec!["--threads", threads];
    kn.extend(words(KEYNODES));
    kn.extend(["--profile", profile]);
    kn.extend(["--voxel-size", "0.15", "--candidates-per-frame", "30%"]);
    usplat4d(dir, &kn);
    let mut ed = vec!["--threads", threads];
    ed.extend(words(EDGES));
    ed.extend(["--profile", profile, "--r-xyz", "1,1,1"]);
    ed.extend(edge_args);
    usplat4d(dir, &ed);
    usplat4d(dir, &["segment", "--edges", "ed", "--out", "seg"]);
    let seg = usplat4d::tables::segments::read(&dir.join("seg/segments.parquet")).unwrap();
    let (_, group) = two_objects(5);
    let truth: Vec<u32> = seg.id.iter().map(|id| group[((id - 1000) / 3) as usize]).collect();
    assert!(dir.join("seg/weights.png").exists());
    (
        adjusted_rand_index(&seg.segment, &truth),
        std::fs::read(dir.join("ed/edges.parquet")).unwrap(),
    )
}

#[test]
fn two_rigid_objects_are_segmented_apart() {
    let dir = tempfile::tempdir().unwrap();
    let (tr, _) = two_objects(5);
    write_inputs(dir.path(), &tr);
    let (ari, one) = pipeline(dir.path(), "paper", &[], "1");
    assert!(ari > 0.9, "paper profile: ARI {ari}");
    let (ari2, two) = pipeline(dir.path(), "paper", &[], "2");
    assert_eq!(ari, ari2);
    assert!(one == two, "edges.parquet differs between 1 and 2 threads");
    let (ari, _) = pipeline(
        dir.path(),
        "release",
        &["--key-edge-weights", "rigidity", "--contrib-threshold", "1"],
        "2",
    );
    assert!(ari > 0.9, "release profile with rigidity weights: ARI {ari}");
}

#[test]
fn edges_name_the_missing_scene() {
    let dir = tempfile::tempdir().unwrap();
    let (tr, _) = two_objects(1);
    write_inputs(dir.path(), &tr);
    usplat4d(dir.path(), &words(KEYNODES));
    let out = crate::util::bin().current_dir(dir.path()).args(words(EDGES)).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("pass --scene"), "{err}");
}
