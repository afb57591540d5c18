//! `usplat4d report`: the HTML page of a small run has every section, every embedded image
//! decodes, and bad inputs are named.

use crate::util::{Dir, repo};

/// The chain synth -> render -> evaluate -> uncertainty -> keynodes -> edges -> segment on
/// a tiny Fox scene, then the report of all of it.
#[test]
fn report_has_every_section_and_its_images_decode() {
    let d = Dir::new();
    let fox = repo().join("pipelines/data/Fox.glb");
    let fox = fox.to_str().unwrap();
    for cmd in [
        format!("synth --gltf {fox} --frames 6 --width 64 --height 64 --gaussians 1500 --out s"),
        "render --model s/oracle --scene s --split eval --out r".into(),
        "evaluate --renders r --scene s --model s/oracle --lpips off --out e".into(),
        "uncertainty --model s/oracle --scene s --out u".into(),
        "keynodes --model s/oracle --uncertainty u --out k".into(),
        "edges --model s/oracle --scene s --uncertainty u --keynodes k --out ed".into(),
        "segment --edges ed --out sg".into(),
        "report --scene s --eval base=e --eval other=e --renders base=r --model s/oracle \
         --uncertainty u --segments sg --edges ed --out rep"
            .into(),
    ] {
        let args: Vec<&str> = ["-q"].into_iter().chain(cmd.split_whitespace()).collect();
        d.ok(&args);
    }
    let page = std::fs::read_to_string(d.join("rep/report.html")).unwrap();
    for id in ["metrics", "charts", "tracking", "views", "uncertainty", "segments", "graph"] {
        assert!(page.contains(&format!("<section id=\"{id}\">")), "section {id} missing");
        assert!(page.contains(&format!("<a href=\"#{id}\">")), "contents entry {id} missing");
    }
    assert!(page.trim_end().ends_with("</html>"));
    // Every embedded PNG decodes; there is one per grid cell, heat map, segment figure and
    // the weight matrix.
    use base64::Engine;
    let mut images = 0;
    for chunk in page.split("src=\"data:image/png;base64,").skip(1) {
        let b64 = &chunk[..chunk.find('"').unwrap()];
        let bytes = base64::engine::general_purpose::STANDARD.decode(b64).unwrap();
        image::load_from_memory(&bytes).unwrap();
        images += 1;
    }
    // 6 frames (3 shown) x (truth + 1 method) + 3 heat maps + 3 segment figures + 1 matrix.
    assert_eq!(images, 3 * 2 + 3 + 3 + 1);
    // Charts: PSNR and SSIM bars (LPIPS is off), and two colour bars.
    assert_eq!(page.matches("<svg").count(), 4);
    assert!(page.contains("Δ") && page.contains("(120°, 180°]"));
}

#[test]
fn report_names_bad_inputs() {
    let d = Dir::new();
    let fox = repo().join("pipelines/data/Fox.glb");
    let synth = format!(
        "-q synth --gltf {} --frames 2 --width 32 --height 32 --gaussians 200 --out s",
        fox.display()
    );
    d.ok(&synth.split_whitespace().collect::<Vec<_>>());
    let err = d.fails(&["report", "--scene", "s", "--eval", "e", "--out", "rep"], 2);
    assert!(err.contains("--eval 'e': expected NAME=DIR"), "{err}");
    let err = d.fails(&["report", "--scene", "s", "--out", "rep"], 2);
    assert!(err.contains("nothing to show"), "{err}");
    let err =
        d.fails(&["report", "--scene", "s", "--training-log", "x=nowhere", "--out", "rep"], 2);
    assert!(err.contains("nowhere/training_log.parquet"), "{err}");
    assert!(!d.join("rep/report.html").exists());
}
