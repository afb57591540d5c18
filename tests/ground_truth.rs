//! Issue 15 item 2: what a scene's image alpha means comes from the scene
//! (`usplat4d.gt_alpha` in the cameras table's metadata): coverage for synthetic scenes
//! (ground truth composited over the render background), plain RGB for DyCheck (alpha 0
//! marks missing LiDAR depth over valid colour). The demo scene's training images are
//! replaced by the model's own render (opaque), then by the same colours with alpha 0 on
//! the left half, as a DyCheck frame without depth there. Not validated: real DyCheck
//! frames (the fixture has no training images).

use usplat4d::formats::png::{Image, read_png, write_png};
use usplat4d::scene::{GtAlpha, Scene};
use usplat4d::stages::optimize::step::TrainingViews;
use usplat4d::tables::Provenance;

use crate::util::{Dir, converged_and_u, demo_with_training_renders};

/// The training images of `scene` set to `renders` (opaque colour over white), with alpha
/// 0 on the left half when `holes`; the scene saved with `mode`.
fn set_images(dir: &Dir, scene: &str, holes: bool, mode: GtAlpha) {
    let s = Scene::load(&dir.join(scene)).unwrap();
    for cam in s.train() {
        let img = read_png(&dir.join("R").join(&cam.image_path)).unwrap().rgb_over([1.0; 3]);
        let mut data = Vec::new();
        for (i, p) in img.data.chunks_exact(3).enumerate() {
            let hole = holes && i % img.width < img.width / 2;
            data.extend_from_slice(&[p[0], p[1], p[2], if hole { 0.0 } else { 1.0 }]);
        }
        let out = Image { width: img.width, height: img.height, channels: 4, data };
        let to = s.resolve(&cam.image_path);
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        write_png(&to, &out).unwrap();
    }
    s.save_with(&Provenance::default(), mode).unwrap();
}

/// `(converged, u)` of every frame of an uncertainty run on `scene`.
fn uncertainty(dir: &Dir, scene: &str, out: &str) -> (Vec<bool>, Vec<f32>) {
    // every touched pixel counts (τ = 0), so a wrong pixel fails its Gaussians
    let tau = ["--cover-min-weight", "0"];
    dir.ok(&[&["uncertainty", "--model", "demo/model", "--scene", scene, "--out", out], &tau[..]]
        .concat());
    converged_and_u(&dir.join(out))
}

#[test]
fn dycheck_alpha_is_not_coverage() {
    let dir = Dir::new();
    demo_with_training_renders(&dir);
    set_images(&dir, "demo/scene", false, GtAlpha::Coverage);
    let reference = uncertainty(&dir, "demo/scene", "U_ref");
    let seen = reference.0.iter().filter(|c| **c).count();
    assert!(seen > 500, "{seen} converged pairs on the model's own render");

    set_images(&dir, "demo/scene", true, GtAlpha::Ignore);
    let scene = Scene::load(&dir.join("demo/scene")).unwrap();
    assert_eq!(scene.gt_alpha().unwrap(), GtAlpha::Ignore);
    assert_eq!(uncertainty(&dir, "demo/scene", "U_dycheck"), reference);
    // the optimiser's image loss reads the same ground truth
    let model = usplat4d::model::Model::load(&dir.join("demo/model")).unwrap();
    let views = TrainingViews::new(&scene, &model).unwrap();
    let opaque = scene.train_by_frame()[0].clone();
    let truth = views.truth(0, [1.0; 3]).unwrap();
    let render = read_png(&dir.join("R").join(&opaque.image_path)).unwrap().rgb_over([1.0; 3]);
    assert_eq!(truth.rgb.len(), render.data.len());
    let err = truth.rgb.iter().zip(&render.data).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(err <= 1.0 / 255.0 + 1e-6, "optimiser ground truth off by {err}");

    // Read as coverage (the behaviour before the fix), the holes turn white and the
    // Gaussians there fail the colour test.
    set_images(&dir, "demo/scene", true, GtAlpha::Coverage);
    let coverage = uncertainty(&dir, "demo/scene", "U_coverage");
    let lost = coverage.0.iter().filter(|c| **c).count();
    println!("converged pairs: {seen} on opaque images and on DyCheck alpha, {lost} if coverage");
    assert!(lost < seen * 3 / 4, "{lost} of {seen}");
}
