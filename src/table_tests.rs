//! Round trips, validation messages and the schema-versus-documentation check of the
//! tables, through the model and scene directories that store them (so these tests sit
//! above `tables`, `model` and `scene`, not inside `tables`).

use std::path::{Path, PathBuf};

use crate::model::{FrameState, Model, sample_model};
use crate::scene::{Camera, Pinhole, Scene, Split};
use crate::tables::io::{self, TableReader};
use crate::tables::*;

/// Parse the `| column | type | ...` rows of a `data_schema/*.md` file.
fn documented_columns(md: &str) -> Vec<(String, String)> {
    md.lines()
        .filter(|l| l.starts_with('|'))
        .map(|l| l.split('|').map(str::trim).collect::<Vec<_>>())
        .filter(|c| c.len() > 3 && c[1] != "column" && !c[1].starts_with("---"))
        .map(|c| (c[1].to_string(), c[2].to_string()))
        .collect()
}

#[test]
fn every_table_matches_its_documentation() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data_schema");
    let mut problems = Vec::new();
    for TableKind { name, schema, .. } in registry() {
        let path = dir.join(format!("{name}.md"));
        let Ok(md) = std::fs::read_to_string(&path) else {
            problems.push(format!("{name}: no {}", path.display()));
            continue;
        };
        let doc = documented_columns(&md);
        let code: Vec<(String, String)> = schema
            .fields()
            .iter()
            .map(|f| (f.name().clone(), io::type_name(f.data_type())))
            .collect();
        if doc != code {
            problems.push(format!("{name}: documented {doc:?}\n  code {code:?}"));
        }
    }
    assert!(problems.is_empty(), "schema/doc mismatches:\n{}", problems.join("\n"));
}

pub(crate) fn sample_cameras() -> Vec<Camera> {
    (0..3)
        .map(|i| Camera {
            frame: i,
            camera: if i < 2 { "cam00".into() } else { "cam01".into() },
            split: if i < 2 { Split::Train } else { Split::Eval },
            pinhole: Pinhole {
                fx: 100.0 + i as f64,
                fy: 101.0,
                cx: 32.0,
                cy: 24.0,
                width: 64,
                height: 48,
                w2c: Camera::w2c_from_mat(glam::DMat4::from_translation(glam::DVec3::new(
                    0.0,
                    0.0,
                    3.0 + i as f64,
                ))),
            },
            image_path: format!("rgb/cam00/{i:05}.png"),
            depth_path: (i == 0).then(|| "depth/cam00/00000.npy".to_string()),
            mask_path: None,
            angle_offset_deg: (i == 2).then_some(30.0),
            distortion: (i == 1).then_some([0.1, 0.0, 0.0, 0.001, 0.0]),
        })
        .collect()
}

#[test]
fn cameras_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene { dir: dir.path().into(), cameras: sample_cameras() };
    scene.save(&Provenance::new("test", &serde_json::json!({"a": 1}))).unwrap();
    let back = Scene::load(dir.path()).unwrap();
    assert_eq!(back.cameras, scene.cameras);
    assert_eq!(back.num_frames(), 2);
    let r = TableReader::open::<cameras::CamerasTable>(&Scene::cameras_path(dir.path())).unwrap();
    assert_eq!(r.metadata_value(io::KEY_STAGE).as_deref(), Some("test"));
    assert_eq!(r.metadata_value(io::KEY_PARAMS).as_deref(), Some(r#"{"a":1}"#));
}

#[test]
fn model_round_trip_streams_frames() {
    let dir = tempfile::tempdir().unwrap();
    let (g, frames) = sample_model();
    Model::save(dir.path(), &g, frames.clone().into_iter().map(Ok), &Provenance::default())
        .unwrap();
    let m = Model::load(dir.path()).unwrap();
    assert_eq!(m.gaussians, g);
    assert_eq!(m.num_frames(), 2);
    assert_eq!(m.frame(1).unwrap(), frames[1]);
    let r =
        TableReader::open::<trajectories::TrajectoriesTable>(&Model::trajectories_path(dir.path()))
            .unwrap();
    assert_eq!(r.num_row_groups(), 2, "one row group per frame");
}

fn write_bad_model(dir: &Path, edit: impl Fn(&mut Vec<FrameState>)) -> PathBuf {
    let (g, mut frames) = sample_model();
    edit(&mut frames);
    let p = Model::trajectories_path(dir);
    tables::gaussians::write(&Model::gaussians_path(dir), &g, &Provenance::default()).unwrap();
    let mut w =
        TableWriter::create::<trajectories::TrajectoriesTable>(&p, &Provenance::default()).unwrap();
    for f in &frames {
        w.write_group(&trajectories::frame_batch(&g.id, f)).unwrap();
    }
    w.finish().unwrap();
    p
}

use crate::tables;

#[test]
fn bad_trajectories_name_file_column_and_row() {
    let dir = tempfile::tempdir().unwrap();
    // The error of reading frame `t` of the model edited by `edit`, and its trajectories file.
    let frame_err = |t: usize, edit: fn(&mut Vec<FrameState>)| {
        let p = write_bad_model(dir.path(), edit);
        (
            Model::load(dir.path()).unwrap().frame(t).unwrap_err().to_string(),
            p.display().to_string(),
        )
    };
    let (err, p) = frame_err(1, |f| f[1].position[2][1] = f32::NAN);
    assert_eq!(err, format!("{p}: column 'y', row 5: non-finite value NaN"));
    let (err, p) = frame_err(0, |f| f[0].rotation[1] = [0.0, 0.0, 0.0, 0.0]);
    assert_eq!(
        err,
        format!("{p}: column 'qw,qx,qy,qz', row 1: quaternion (0, 0, 0, 0) has norm 0, expected 1")
    );
    let (err, p) = frame_err(1, |f| f[1].frame = 2);
    assert_eq!(
        err,
        format!(
            "{p}: frame 1: row 3 has frame 2, expected 1 (frames must be 0..T-1 without gaps, one row group each)"
        )
    );
}

#[test]
fn wrong_table_kind_and_truncation_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene { dir: dir.path().into(), cameras: sample_cameras() };
    scene.save(&Provenance::default()).unwrap();
    let cams = Scene::cameras_path(dir.path());
    let err = tables::gaussians::read(&cams).unwrap_err().to_string();
    assert!(
        err.starts_with(&format!(
            "{}: not a valid 'gaussians' table: it is a 'cameras' table; missing column 'gaussian_id' (u32)",
            cams.display()
        )),
        "{err}"
    );
    let bytes = std::fs::read(&cams).unwrap();
    std::fs::write(&cams, &bytes[..bytes.len() / 2]).unwrap();
    let err = Scene::load(dir.path()).unwrap_err().to_string();
    assert!(err.starts_with(&format!("{}: ", cams.display())), "{err}");
}

#[test]
fn duplicate_ids_and_bad_opacity_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("gaussians.parquet");
    // The error of reading back the sample Gaussians edited by `edit`.
    let read_err = |edit: fn(&mut gaussians::Gaussians)| {
        let (mut g, _) = sample_model();
        edit(&mut g);
        tables::gaussians::write(&p, &g, &Provenance::default()).unwrap();
        tables::gaussians::read(&p).unwrap_err().to_string()
    };
    assert_eq!(
        read_err(|g| g.id[2] = 7),
        format!("{}: column 'gaussian_id', row 2: duplicate id 7 (first at row 0)", p.display())
    );
    assert_eq!(
        read_err(|g| g.opacity[1] = 1.5),
        format!("{}: column 'opacity', row 1: value 1.5 outside [0, 1]", p.display())
    );
}

#[test]
fn reading_from_bytes_matches_file() {
    let dir = tempfile::tempdir().unwrap();
    let (g, frames) = sample_model();
    Model::save(dir.path(), &g, frames.into_iter().map(Ok), &Provenance::default()).unwrap();
    let p = Model::trajectories_path(dir.path());
    let bytes = bytes::Bytes::from(std::fs::read(&p).unwrap());
    let from_bytes = TableReader::new::<trajectories::TrajectoriesTable>(&p, bytes).unwrap();
    let from_file = TableReader::open::<trajectories::TrajectoriesTable>(&p).unwrap();
    assert_eq!(from_bytes.read_group(1).unwrap(), from_file.read_group(1).unwrap());
}

/// A bad value in a fixed-size list column is reported at its row, not at its flattened index.
#[test]
fn non_finite_list_items_name_their_row() {
    let dir = tempfile::tempdir().unwrap();
    let mut cameras: Vec<Camera> = (0..10).flat_map(|_| sample_cameras()).collect();
    for (i, c) in cameras.iter_mut().enumerate() {
        c.frame = i as u32;
    }
    cameras[8].pinhole.w2c[3] = f64::NAN;
    cameras[9].distortion = Some([0.1, 0.0, 0.0, f64::INFINITY, 0.0]);
    // The error of loading a scene of `cameras`.
    let load_err = |cameras: &[Camera]| {
        let scene = Scene { dir: dir.path().into(), cameras: cameras.to_vec() };
        scene.save(&Provenance::default()).unwrap();
        Scene::load(dir.path()).unwrap_err().to_string()
    };
    let p = Scene::cameras_path(dir.path());
    assert_eq!(
        load_err(&cameras),
        format!("{}: column 'w2c', row 8: non-finite value NaN (item 3 of 16)", p.display())
    );
    cameras[8].pinhole.w2c[3] = 0.0;
    assert_eq!(
        load_err(&cameras),
        format!("{}: column 'distortion', row 9: non-finite value inf (item 3 of 5)", p.display())
    );
    let (mut g, _) = sample_model();
    let k3 = g.sh_rest_len();
    g.sh_rest[2 * k3 + 1] = f32::NAN;
    let gp = dir.path().join("gaussians.parquet");
    tables::gaussians::write(&gp, &g, &Provenance::default()).unwrap();
    assert_eq!(
        tables::gaussians::read(&gp).unwrap_err().to_string(),
        format!("{}: column 'sh_rest', row 2: non-finite value NaN (item 1 of {k3})", gp.display())
    );
}

/// Reads `path` with every table reader (whole tables and every frame of per-frame
/// tables), returning each reader's error message; Ok results are reported as `None`.
pub(crate) fn read_with_every_reader(path: &Path) -> Vec<(&'static str, Option<String>)> {
    /// The first error of opening a per-frame table or reading any of its frames.
    macro_rules! frames {
        ($open:expr) => {
            match $open {
                Ok(r) => (0..r.num_frames()).find_map(|t| r.frame(t).err().map(|e| e.to_string())),
                Err(e) => Some(e.to_string()),
            }
        };
    }
    vec![
        ("cameras", cameras::read(path).err().map(|e| e.to_string())),
        ("gaussians", gaussians::read(path).err().map(|e| e.to_string())),
        ("edges", edges::read(path).err().map(|e| e.to_string())),
        ("key_nodes", key_nodes::read(path).err().map(|e| e.to_string())),
        ("metrics", metrics::read(path).err().map(|e| e.to_string())),
        ("segments", segments::read(path).err().map(|e| e.to_string())),
        ("uncertainty", frames!(uncertainty::UncertaintyReader::open(path))),
        ("trajectories", frames!(trajectories::TrajectoryReader::open(path, &sample_model().0.id))),
        ("tracks_2d", frames!(tracks_2d::Tracks2dReader::open(path))),
        ("tracks_3d", frames!(tracks_3d::Tracks3dReader::open(path))),
    ]
}

/// The `.parquet` files of `dir`, sorted.
fn parquet_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .collect();
    files.sort();
    files
}

/// The Parquet files that crashed parquet-rs 60 (`../shared/data/bad-parquet/`, corrupted
/// footers and dictionary pages) are errors naming the file in every reader.
#[test]
fn corrupted_parquet_is_an_error_in_every_reader() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let Some(dir) =
        [root.join("../shared/data/bad-parquet"), root.join("../../shared/data/bad-parquet")]
            .into_iter()
            .find(|d| d.is_dir())
    else {
        eprintln!(
            "SKIP corrupted_parquet_is_an_error_in_every_reader: no ../shared/data/bad-parquet"
        );
        return;
    };
    let files = parquet_files(&dir);
    assert_eq!(files.len(), 9);
    for f in &files {
        for (reader, result) in read_with_every_reader(f) {
            let msg = result.unwrap_or_else(|| panic!("{reader} accepted {}", f.display()));
            assert!(msg.starts_with(&format!("{}: ", f.display())), "{reader}: {msg}");
        }
    }
}

/// The files on which `fuzzed_tables_never_panic` found a panic (`tests/fuzz_crashes/`, one
/// per fault; each panicked inside parquet-rs before its check in `tables::pages`) are errors
/// naming the file in every reader.
#[test]
fn fuzz_crashes_are_errors_in_every_reader() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_crashes");
    let files = parquet_files(&dir);
    assert!(!files.is_empty());
    for f in &files {
        let results = std::panic::catch_unwind(|| read_with_every_reader(f))
            .unwrap_or_else(|_| panic!("a reader panicked on {}", f.display()));
        for (reader, result) in results {
            let msg = result.unwrap_or_else(|| panic!("{reader} accepted {}", f.display()));
            assert!(msg.starts_with(&format!("{}: ", f.display())), "{reader}: {msg}");
        }
    }
}

/// Fuzz target of the table readers: valid tables (dictionary-encoded, compressed) with
/// bytes flipped, runs overwritten (often in the footer) or cut short, read by every reader;
/// none may panic. `USPLAT4D_FUZZ_ITERS` mutations (default 2000, what CI runs),
/// `USPLAT4D_FUZZ_SECONDS` stops earlier, `USPLAT4D_FUZZ_SEED` picks the sequence.
#[test]
fn fuzzed_tables_never_panic() {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<u64>().ok());
    let iters = env("USPLAT4D_FUZZ_ITERS").unwrap_or(2000);
    let seconds = env("USPLAT4D_FUZZ_SECONDS");
    let mut rng = crate::util::rng::Rng::from_state(env("USPLAT4D_FUZZ_SEED").unwrap_or(1));
    let mut next = move || rng.next_u64();
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene { dir: dir.path().join("s"), cameras: sample_cameras() };
    scene.save(&Provenance::default()).unwrap();
    let (g, frames) = sample_model();
    Model::save(&dir.path().join("m"), &g, frames.into_iter().map(Ok), &Provenance::default())
        .unwrap();
    let ids: Vec<u32> = (0..40).collect();
    let unc = dir.path().join("uncertainty.parquet");
    let mut w = uncertainty::UncertaintyWriter::create(&unc, &ids, &Provenance::default()).unwrap();
    for t in 0..3u32 {
        w.write(&uncertainty::UncertaintyFrame {
            frame: t,
            sum_w2: ids.iter().map(|&i| (i % 5) as f32).collect(),
            sum_w: ids.iter().map(|&i| (i % 3) as f32).collect(),
            n_pixels: ids.iter().map(|&i| i % 4).collect(),
            converged: ids.iter().map(|&i| i % 2 == 0).collect(),
            u: ids.iter().map(|&i| 1.0 + (i % 6) as f32).collect(),
        })
        .unwrap();
    }
    w.finish().unwrap();
    let seeds: Vec<Vec<u8>> = [
        Scene::cameras_path(&scene.dir),
        Model::gaussians_path(&dir.path().join("m")),
        Model::trajectories_path(&dir.path().join("m")),
        unc,
    ]
    .iter()
    .map(|p| std::fs::read(p).unwrap())
    .collect();
    let target = dir.path().join("fuzzed.parquet");
    let start = std::time::Instant::now();
    let mut crashes = Vec::new();
    let mut done = 0;
    while done < iters && seconds.is_none_or(|s| start.elapsed().as_secs() < s) {
        let mut bytes = seeds[(next() % seeds.len() as u64) as usize].clone();
        let n = bytes.len() as u64;
        match next() % 8 {
            0 => bytes.truncate((next() % n) as usize),
            1..=3 => {
                // a run in the footer (the last quarter of the file)
                let at = n - 1 - next() % (n / 4);
                for i in 0..=next() % 8 {
                    if let Some(b) = bytes.get_mut((at + i) as usize) {
                        *b = next() as u8;
                    }
                }
            }
            _ => {
                for _ in 0..=next() % 4 {
                    let at = (next() % n) as usize;
                    bytes[at] ^= 1 << (next() % 8);
                }
            }
        }
        std::fs::write(&target, &bytes).unwrap();
        let result = std::panic::catch_unwind(|| read_with_every_reader(&target));
        if result.is_err() {
            let keep = dir.path().join(format!("crash-{done}.parquet"));
            std::fs::copy(&target, &keep).unwrap();
            crashes.push(done);
        }
        done += 1;
    }
    eprintln!(
        "fuzzed_tables_never_panic: {done} mutations in {:.0} s, {} panics",
        start.elapsed().as_secs_f64(),
        crashes.len()
    );
    if !crashes.is_empty() {
        let kept = dir.keep();
        panic!("panics at mutations {crashes:?}; files kept in {}", kept.display());
    }
}
