//! DyCheck's masked metrics against the values MoSca's `eval_utils/dycheck_metrics.py`
//! computes (`../shared/data/fixtures/dycheck-metrics`, made with the upstream code).
//!
//! The fixture's `float64_jax_x64` set is the same code in f64, which is what [`psnr`] and
//! [`ssim`] compute; MoSca's own evaluation runs jax in f32 (`float32_jax_default`), whose
//! values differ from f64 by up to about 5e-6. Both sets are checked to 1e-4 (issue 13).
//! Not validated here: LPIPS (see `lpips-golden`), and the covisibility masks' production.

use std::path::{Path, PathBuf};

use super::{psnr::psnr, ssim::ssim};
use crate::formats::png::read_png;

/// `../shared/data/fixtures/dycheck-metrics` from a worktree or from the main checkout.
fn fixture_dir() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    ["../shared/data", "../../shared/data"]
        .iter()
        .map(|d| root.join(d).join("fixtures/dycheck-metrics"))
        .find(|p| p.is_dir())
}

#[test]
fn masked_metrics_equal_moscas_dycheck_code() {
    let Some(dir) = fixture_dir() else {
        eprintln!("SKIP dycheck metrics fixture: ../shared/data/fixtures not found");
        return;
    };
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("dycheck_metrics_expected.json")).unwrap())
            .unwrap();
    let mut worst = 0.0f64;
    for set in ["float64_jax_x64", "float32_jax_default"] {
        let results = &json["results"][set];
        let mut means = [0.0f64; 4];
        let images = results["per_image"].as_array().unwrap();
        for case in images {
            let name = case["name"].as_str().unwrap();
            let gt = read_png(&dir.join(format!("{name}_gt.png"))).unwrap();
            let pred = read_png(&dir.join(format!("{name}_pred.png"))).unwrap();
            let covis = read_png(&dir.join(format!("{name}_covis.png"))).unwrap();
            let mask: Vec<f32> =
                covis.data.iter().map(|&v| if v > 0.0 { 1.0 } else { 0.0 }).collect();
            let mask_sum: f32 = mask.iter().sum();
            assert_eq!(mask_sum as f64, case["mask_sum"].as_f64().unwrap(), "{name} mask");
            let got = [
                psnr(&pred, &gt, None).unwrap(),
                ssim(&pred, &gt, None).unwrap(),
                psnr(&pred, &gt, Some(&mask)).unwrap(),
                ssim(&pred, &gt, Some(&mask)).unwrap(),
            ];
            for (k, (key, g)) in ["psnr", "ssim", "mpsnr", "mssim"].iter().zip(got).enumerate() {
                let want = case[*key].as_f64().unwrap();
                means[k] += g / images.len() as f64;
                let err = (g - want).abs();
                worst = worst.max(err);
                assert!(err < 1e-4, "{set} {name} {key}: {g} vs {want}");
            }
        }
        for (key, g) in ["mean_psnr", "mean_ssim", "mean_mpsnr", "mean_mssim"].iter().zip(means) {
            let want = results[*key].as_f64().unwrap();
            assert!((g - want).abs() < 1e-4, "{set} {key}: {g} vs {want}");
        }
    }
    eprintln!("dycheck metrics fixture: largest difference {worst:.2e}");
}
