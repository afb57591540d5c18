//! Round trips, validation messages and the schema-versus-documentation check of the
//! lead-owned tables.

use std::path::{Path, PathBuf};

use super::*;
use crate::model::{FrameState, Gaussians, Model};
use crate::scene::{Camera, Scene, Split};

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
            image_path: format!("rgb/cam00/{i:05}.png"),
            depth_path: (i == 0).then(|| "depth/cam00/00000.npy".to_string()),
            mask_path: None,
            angle_offset_deg: (i == 2).then_some(30.0),
            distortion: (i == 1).then_some([0.1, 0.0, 0.0, 0.001, 0.0]),
        })
        .collect()
}

pub(crate) fn sample_model() -> (Gaussians, Vec<FrameState>) {
    let g = Gaussians {
        id: vec![7, 3, 11],
        dynamic: vec![true, false, true],
        scale: vec![[0.1, 0.2, 0.3]; 3],
        opacity: vec![0.5, 1.0, 0.0],
        color: vec![[1.0, 0.5, 0.0]; 3],
        sh_degree: 1,
        sh_rest: (0..27).map(|i| i as f32 * 0.01).collect(),
    };
    let frames = (0..2)
        .map(|t| FrameState {
            frame: t,
            position: vec![[t as f32, 1.0, 2.0]; 3],
            rotation: vec![[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]],
        })
        .collect();
    (g, frames)
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
    let p = write_bad_model(dir.path(), |f| f[1].position[2][1] = f32::NAN);
    let m = Model::load(dir.path()).unwrap();
    assert_eq!(
        m.frame(1).unwrap_err().to_string(),
        format!("{}: column 'y', row 5: non-finite value NaN", p.display())
    );
    let p = write_bad_model(dir.path(), |f| f[0].rotation[1] = [0.0, 0.0, 0.0, 0.0]);
    let m = Model::load(dir.path()).unwrap();
    assert_eq!(
        m.frame(0).unwrap_err().to_string(),
        format!(
            "{}: column 'qw,qx,qy,qz', row 1: quaternion (0, 0, 0, 0) has norm 0, expected 1",
            p.display()
        )
    );
    let p = write_bad_model(dir.path(), |f| f[1].frame = 2);
    let m = Model::load(dir.path()).unwrap();
    assert_eq!(
        m.frame(1).unwrap_err().to_string(),
        format!(
            "{}: frame 1: row 3 has frame 2, expected 1 (frames must be 0..T-1 without gaps, one row group each)",
            p.display()
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
    let (mut g, _) = sample_model();
    g.id[2] = 7;
    tables::gaussians::write(&p, &g, &Provenance::default()).unwrap();
    assert_eq!(
        tables::gaussians::read(&p).unwrap_err().to_string(),
        format!("{}: column 'gaussian_id', row 2: duplicate id 7 (first at row 0)", p.display())
    );
    let (mut g, _) = sample_model();
    g.opacity[1] = 1.5;
    tables::gaussians::write(&p, &g, &Provenance::default()).unwrap();
    assert_eq!(
        tables::gaussians::read(&p).unwrap_err().to_string(),
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
