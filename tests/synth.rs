//! End-to-end tests of `usplat4d synth`: the embedded Fox and the shared SimpleSkin render
//! complete, consistent scenes at a tiny size; bad inputs give exact error messages.

use std::path::{Path, PathBuf};

use usplat4d::formats::{npy::read_npy_f32, png::read_png};
use usplat4d::model::Model;
use usplat4d::scene::{Scene, Split};
use usplat4d::tables::tracks_2d::Tracks2dReader;
use usplat4d::tables::tracks_3d::Tracks3dReader;

fn fox() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/data/Fox.glb")
}

/// Run `usplat4d -q synth ARGS`; returns (exit code, stderr).
fn synth(args: &[&str]) -> (i32, String) {
    crate::util::code_and_stderr(&[&["-q", "synth"], args].concat())
}

const TINY: [&str; 12] = [
    "--frames",
    "4",
    "--cameras",
    "3",
    "--width",
    "48",
    "--height",
    "40",
    "--gaussians",
    "300",
    "--tracks",
    "40",
];

/// Check every file and table of a tiny scene and their mutual consistency.
fn check_scene(dir: &Path) {
    let scene = Scene::load(dir).unwrap();
    assert_eq!(scene.cameras.len(), 12);
    assert_eq!(scene.num_frames(), 4);
    assert_eq!(scene.eval().count(), 8);
    let offsets: Vec<f32> =
        scene.cameras[..3].iter().map(|c| c.angle_offset_deg.unwrap()).collect();
    assert_eq!(offsets, vec![0.0, 120.0, 240.0]);
    let mut covered = 0;
    for c in &scene.cameras {
        let rgba = read_png(&scene.resolve(&c.image_path)).unwrap();
        assert_eq!((rgba.width, rgba.height, rgba.channels), (48, 40, 4));
        let mask = read_png(&scene.resolve(c.mask_path.as_deref().unwrap())).unwrap();
        let (shape, depth) =
            read_npy_f32(&scene.resolve(c.depth_path.as_deref().unwrap())).unwrap();
        assert_eq!(shape, vec![40, 48]);
        for i in 0..48 * 40 {
            let m = mask.data[i] > 0.5;
            assert_eq!(m, depth[i] > 0.0, "{} pixel {i}", c.image_path);
            // Coverage is k/ss²; the 8-bit alpha of exactly one half is 128/255.
            assert_eq!(m, rgba.data[i * 4 + 3] > 0.51, "{} pixel {i}", c.image_path);
            covered += m as usize;
        }
    }
    assert!(covered > 12 * 40, "the object covers {covered} pixels in 12 images");

    let t3 = Tracks3dReader::open(&dir.join("tracks_3d.parquet")).unwrap();
    let t2 = Tracks2dReader::open(&dir.join("tracks_2d.parquet")).unwrap();
    assert_eq!((t3.num_frames(), t3.num_tracks()), (4, 40));
    assert_eq!((t2.num_frames(), t2.num_tracks()), (4, 40));
    let (mut visible, mut on_mask) = (0, 0);
    for (t, cam) in scene.train_by_frame().into_iter().enumerate() {
        let p3 = t3.frame(t).unwrap();
        let f2 = t2.frame(t).unwrap();
        let mask = read_png(&scene.resolve(cam.mask_path.as_deref().unwrap())).unwrap();
        for i in 0..40 {
            let p = glam::DVec3::from(p3[i].map(f64::from));
            let (u, v, _) = cam.project(p).unwrap();
            assert!((u - f2.xy[i][0] as f64).abs() < 1e-2 && (v - f2.xy[i][1] as f64).abs() < 1e-2);
            if f2.visible[i] {
                visible += 1;
                let near_mask = (-1..=1).any(|dy| {
                    (-1..=1).any(|dx| {
                        let (x, y) = (u as i64 + dx, v as i64 + dy);
                        (0..48).contains(&x)
                            && (0..40).contains(&y)
                            && mask.data[(y * 48 + x) as usize] > 0.5
                    })
                });
                on_mask += near_mask as usize;
            }
        }
    }
    // A good part of the surface faces the camera; visible tracks land on the object or
    // within one pixel of it (silhouette pixels may have coverage below one half).
    assert!(visible > 4 * 40 / 5, "{visible} visible");
    assert!(on_mask as f64 >= 0.95 * visible as f64, "{on_mask} of {visible} on the mask");

    let oracle = Model::load(&dir.join("oracle")).unwrap();
    assert_eq!((oracle.gaussians.len(), oracle.num_frames()), (300, 4));
    assert!(oracle.gaussians.dynamic.iter().all(|d| *d));
    let f = oracle.frame(0).unwrap();
    let r = f
        .position
        .iter()
        .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
        .fold(0f32, f32::max);
    assert!(r <= 1.0 + 1e-4, "normalised into the unit sphere, max radius {r}");
    assert!(
        std::fs::read_to_string(dir.join("scene.json")).unwrap().contains("\"bbox_diagonal\": 2.0")
    );
    assert!(scene.train().all(|c| c.split == Split::Train && c.camera == "cam00"));
}

#[test]
fn embedded_fox_tiny_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("fox");
    let fox = fox();
    let mut args = vec![
        "--gltf",
        fox.to_str().unwrap(),
        "--animation",
        "Walk",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(TINY);
    let (code, err) = synth(&args);
    assert_eq!((code, err.as_str()), (0, ""));
    check_scene(&out);
}

#[test]
fn shared_simple_skin_tiny_scene() {
    let Some(data) = crate::util::shared_data("") else {
        eprintln!("SKIP shared_simple_skin_tiny_scene: ../shared/data not found");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("simple");
    let model = data.join("gltf/SimpleSkin.gltf");
    let mut args = vec!["--gltf", model.to_str().unwrap(), "--out", out.to_str().unwrap()];
    args.extend(TINY);
    let (code, err) = synth(&args);
    assert_eq!((code, err.as_str()), (0, ""));
    check_scene(&out);
}

#[test]
fn truncated_glb_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("cut.glb");
    std::fs::write(&bad, &std::fs::read(fox()).unwrap()[..1000]).unwrap();
    let out = tmp.path().join("out");
    let (code, err) = synth(&["--gltf", bad.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert_eq!(
        err,
        format!(
            "error: {}: not a usable glTF file: truncated: the GLB header declares 162852 bytes, the file has 1000\n",
            bad.display()
        )
    );
}

#[test]
fn unknown_animation_lists_the_available_ones() {
    let tmp = tempfile::tempdir().unwrap();
    let fox = fox();
    let out = tmp.path().join("out");
    let (code, err) = synth(&[
        "--gltf",
        fox.to_str().unwrap(),
        "--animation",
        "Jump",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert_eq!(
        err,
        format!(
            "error: {}: no animation named 'Jump' (available: 'Survey', 'Walk', 'Run')\n",
            fox.display()
        )
    );
}

/// A one-triangle glTF with an external buffer and, optionally, a texture image.
fn write_triangle(dir: &Path, image: Option<&str>) -> PathBuf {
    let mut bin = Vec::new();
    for v in [[0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
        for x in v {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    std::fs::write(dir.join("tri.bin"), &bin).unwrap();
    let (material, images) = match image {
        Some(uri) => (
            r#""material": 0,"#,
            format!(
                r#""materials": [{{"pbrMetallicRoughness": {{"baseColorTexture": {{"index": 0}}}}}}],
                "textures": [{{"source": 0}}], "images": [{{"uri": "{uri}"}}],"#
            ),
        ),
        None => ("", String::new()),
    };
    let json = format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [0]}}],
        "nodes": [{{"mesh": 0}}], {images}
        "meshes": [{{"primitives": [{{{material} "attributes": {{"POSITION": 0}}}}]}}],
        "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                        "min": [0, 0, 0], "max": [1, 1, 0]}}],
        "bufferViews": [{{"buffer": 0, "byteLength": 36}}],
        "buffers": [{{"uri": "tri.bin", "byteLength": 36}}]}}"#
    );
    let path = dir.join("tri.gltf");
    std::fs::write(&path, json).unwrap();
    path
}

#[test]
fn static_model_renders_with_warnings() {
    let tmp = tempfile::tempdir().unwrap();
    let model = write_triangle(tmp.path(), None);
    let out = tmp.path().join("out");
    let mut args = vec!["--gltf", model.to_str().unwrap(), "--out", out.to_str().unwrap()];
    args.extend(TINY);
    let (code, err) = synth(&args);
    assert_eq!(code, 0, "{err}");
    let name = model.display();
    assert_eq!(
        err,
        format!(
            "warning: {name}: the file has no animation; rendering a static scene\n\
             warning: {name}: no skinned mesh; only node and morph animation moves the model\n"
        )
    );
    let scene = Scene::load(&out).unwrap();
    assert_eq!(scene.cameras.len(), 12);
}

#[test]
fn missing_texture_names_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let model = write_triangle(tmp.path(), Some("skin.png"));
    let out = tmp.path().join("out");
    let (code, err) = synth(&["--gltf", model.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert_eq!(
        err,
        format!(
            "error: {}: texture image 0 refers to the missing file {}\n",
            model.display(),
            tmp.path().join("skin.png").display()
        )
    );
}

/// All files of a directory tree, relative path → bytes, sorted.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_bytes_whatever_the_thread_count() {
    let tmp = tempfile::tempdir().unwrap();
    let fox = fox();
    // The same output path both times: the tables' provenance records the parameters.
    let out = tmp.path().join("out");
    let run = |threads: &str| {
        let mut args = vec![
            "--threads",
            threads,
            "--gltf",
            fox.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(TINY);
        assert_eq!(synth(&args).0, 0);
        let files = tree(&out);
        std::fs::remove_dir_all(&out).unwrap();
        files
    };
    let (one, three) = (run("1"), run("3"));
    assert_eq!(one.len(), three.len());
    for (a, b) in one.iter().zip(&three) {
        assert!(a == b, "{} differs", a.0.display());
    }
}

#[test]
fn bad_trajectory_spec_names_the_flag() {
    let tmp = tempfile::tempdir().unwrap();
    let fox = fox();
    let out = tmp.path().join("out");
    let args = [
        "--gltf",
        fox.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--trajectory",
        "colmap:x",
    ];
    let (code, err) = synth(&args);
    assert_eq!(
        (code, err.as_str()),
        (2, "error: --trajectory: 'colmap:x' is not of the form dycheck:DIR\n")
    );
}
