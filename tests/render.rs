//! `usplat4d render` through the real binary on the hand-made demo scene.

use usplat4d::datasets::demo::write_demo_scene;

#[test]
fn render_cli_writes_every_image_of_a_split_and_a_manifest() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, model) = write_demo_scene(dir.path(), 2).unwrap();
    let out = dir.path().join("renders");
    let status = crate::util::bin()
        .args(["--quiet", "render", "--split", "all", "--alpha-max", "0.999", "--depth"])
        .arg("--model")
        .arg(&model)
        .arg("--scene")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    for cam in ["cam00", "cam01"] {
        for t in 0..2 {
            let img = usplat4d::formats::png::read_png(&out.join(format!("rgb/{cam}/{t:05}.png")))
                .unwrap();
            assert_eq!((img.width, img.height, img.channels), (80, 60, 4));
            assert!(out.join(format!("depth/{cam}/{t:05}.npy")).exists());
        }
    }
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("renders.json")).unwrap()).unwrap();
    assert_eq!((manifest["count"].as_u64(), manifest["split"].as_str()), (Some(4), Some("all")));
}

#[test]
fn render_cli_names_the_missing_model_file() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, _) = write_demo_scene(dir.path(), 1).unwrap();
    let missing = dir.path().join("nope");
    let output = crate::util::bin()
        .args(["render", "--model"])
        .arg(&missing)
        .arg("--scene")
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("o"))
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("nope/gaussians.parquet"), "{stderr}");
}
