//! End-to-end measurements of issue 5 on a small synthetic Fox scene (`synth` on
//! `pipelines/data/Fox.glb`, Walk, 16 frames at 128×128, 3000 oracle Gaussians):
//!
//! 1. Key-node coverage: after `uncertainty` → `keynodes` on the oracle model (paper and release
//!    profiles), the fraction of occupied voxels (frame-0 positions of all Gaussians, voxel
//!    = 1/10 of their bounding-box diagonal) that have a key node within one voxel
//!    (26-neighbourhood including itself). The paper profile's `auto` voxel must land on its
//!    2% key budget; its former fixed 2% voxel, ablation (d) (no voxel grid) and the same
//!    number of keys drawn uniformly at random from all Gaussians (confident or not) are
//!    printed for comparison; the voxel grid must cover at least 5 points more than (d).
//!    Random Gaussians cover more than any key set: keys must be confident in the training
//!    view, so the side never seen confidently has none. Then the release's non-key cap
//!    (rows 33-35): with `--nonkey-cap 500` at most 499 non-keys stay in the graph, the rest are `culled` (or
//!    `unlinked` with `--unselected-nonkeys keep`), and `edges` gives them no edges.
//! 2. Drifting-prior separation (paper profile): a seeded half of the dynamic Gaussians is
//!    displaced by a fixed offset in the frames where the oracle run does not see them in the
//!    training camera, widened by two frames on each side (where they are seen and now render
//!    at a wrong place); `uncertainty` on that drifted model must leave the drifted, seen
//!    (Gaussian, frame) pairs unconverged (u = φ) at least twice as often as the same pairs on
//!    the oracle and more often than the untouched seen pairs, and must turn pairs converged
//!    on the oracle unconverged at least 10× more often for drifted than for untouched pairs.
//!    "Seen" means n_pixels > 0 on the oracle run. The paper profile's gates are strict, so
//!    many untouched oracle pairs are unconverged too: the paired comparisons are the sharp ones.
//!
//! Both tests print their numbers (`cargo test --test tests graph_fox -- --nocapture`).
//! Not validated here: that the key nodes are the *right* ones (only that they spread over the
//! object), the graph edges and segmentation built on them, uncertainty on real captures, and
//! drift that stays entirely inside occluded frames (unseen Gaussians get u = φ whatever their
//! position, so such drift is invisible to the uncertainty by construction).

use std::collections::HashSet;
use std::path::Path;

use usplat4d::model::Model;
use usplat4d::tables::key_nodes::{self, KeyNodes, Role};
use usplat4d::tables::uncertainty::{UncertaintyFrame, UncertaintyReader};
use usplat4d::util::rng::Rng;

use crate::util::{Dir, Drift, DriftDirection, bbox_diagonal, drifted_prior, repo};

/// Drift offset as a fraction of the bounding-box diagonal.
const DRIFT: f32 = 0.15;
/// Frames added on each side of an unseen frame to the drift window.
const MARGIN: usize = 2;

/// The synthetic Fox scene in `dir/S` (oracle model in `dir/S/oracle`).
fn fox_scene(dir: &Dir) {
    let gltf = repo().join("pipelines/data/Fox.glb");
    dir.ok(&[
        "synth",
        "--gltf",
        gltf.to_str().unwrap(),
        "--animation",
        "Walk",
        "--out",
        "S",
        "--frames",
        "16",
        "--width",
        "128",
        "--height",
        "128",
        "--gaussians",
        "3000",
        "--tracks",
        "64",
    ]);
}

/// All frames of an uncertainty table, and its Gaussian order `[N]`.
fn uncertainty(path: &Path) -> (Vec<u32>, Vec<UncertaintyFrame>) {
    let r = UncertaintyReader::open(path).unwrap();
    let frames = (0..r.num_frames()).map(|t| r.frame(t).unwrap()).collect();
    (r.ids().to_vec(), frames)
}

/// Fraction of the voxels (edge `voxel`) occupied by `p` `[N, 3]` that have a voxel holding
/// a key point (`is_key` `[N]`) among their 26 neighbours or themselves.
fn key_coverage(p: &[[f32; 3]], is_key: &[bool], voxel: f32) -> f64 {
    let cell = |q: &[f32; 3]| q.map(|v| (v / voxel).floor() as i64);
    let occupied: HashSet<[i64; 3]> = p.iter().map(cell).collect();
    let keys: HashSet<[i64; 3]> =
        p.iter().zip(is_key).filter(|(_, k)| **k).map(|(q, _)| cell(q)).collect();
    let near_key = |c: &[i64; 3]| {
        (-1..=1).any(|dx| {
            (-1..=1).any(|dy| (-1..=1).any(|dz| keys.contains(&[c[0] + dx, c[1] + dy, c[2] + dz])))
        })
    };
    occupied.iter().filter(|c| near_key(c)).count() as f64 / occupied.len() as f64
}

/// The keys of `keys` as a mask `[N]` in the model's Gaussian order.
fn key_mask(model: &Model, keys: &KeyNodes) -> Vec<bool> {
    let ids: HashSet<u32> = keys.rows(Role::Key).into_iter().map(|i| keys.id[i]).collect();
    model.gaussians.id.iter().map(|i| ids.contains(i)).collect()
}

#[test]
fn key_nodes_cover_the_fox() {
    let dir = Dir::new();
    fox_scene(&dir);
    let model = Model::load(&dir.join("S/oracle")).unwrap();
    let p0 = model.frame(0).unwrap().position;
    let voxel = bbox_diagonal(&p0) / 10.0;
    for profile in ["paper", "release"] {
        let u = format!("U_{profile}");
        // The literal covered-pixel set (τ = 0), on which this test's coverage margins were
        // set (issue 5); `covered_pixel_floor_is_measured` prints the coverage at every τ,
        // the paper default's included.
        let common = ["--model", "S/oracle", "--profile", profile, "--cover-min-weight", "0"];
        dir.ok(&[&["uncertainty"], &common[..], &["--scene", "S", "--out", &u]].concat());
    }
    let runs: [(&str, &str, &[&str]); 4] = [
        ("paper", "K_paper", &[]),
        ("paper", "K_paper_fixed", &["--voxel-size", "2%"]),
        ("paper", "K_paper_ablation_d", &["--candidate-sampling", "random"]),
        ("release", "K_release", &[]),
    ];
    let mut coverages = std::collections::HashMap::new();
    for (profile, k, extra) in runs {
        let u = format!("U_{profile}");
        let args = ["keynodes", "--model", "S/oracle", "--profile", profile, "--uncertainty", &u];
        dir.ok(&[&args[..], &["--out", k], extra].concat());
        let keys = key_nodes::read(&dir.join(k).join("key_nodes.parquet")).unwrap();
        let is_key = key_mask(&model, &keys);
        let coverage = key_coverage(&p0, &is_key, voxel);
        let mut rng = Rng::new(11);
        let mut random = vec![false; p0.len()];
        while random.iter().filter(|r| **r).count() < keys.num_keys().min(p0.len()) {
            random[(rng.next_u64() % p0.len() as u64) as usize] = true;
        }
        println!(
            "key-node coverage [{k}]: {} key nodes of {} Gaussians in the graph ({} in the \
             model), {:.1}% of occupied voxels within one voxel (edge {voxel:.3}) of a key node \
             ({:.1}% for as many random Gaussians); {} non-keys, {} culled",
            keys.num_keys(),
            keys.id.len(),
            p0.len(),
            100.0 * coverage,
            100.0 * key_coverage(&p0, &random, voxel),
            keys.count(Role::Nonkey),
            keys.count(Role::Culled),
        );
        assert!(keys.num_keys() >= 10, "{k}: only {} key nodes", keys.num_keys());
        coverages.insert(k, coverage);
        assert_eq!(keys.count(Role::Unlinked), 0, "{k}");
        if k == "K_paper" || k == "K_paper_ablation_d" {
            // the auto voxel lands on the 1:49 budget, 2% of the graph's Gaussians
            let budget = (0.02 * keys.id.len() as f64).round() as usize;
            assert_eq!(keys.num_keys(), budget, "{k}");
        }
        if profile == "paper" {
            assert_eq!(keys.count(Role::Culled), 0, "{k}: the paper culls nothing");
        }
    }

    for k in ["K_paper", "K_paper_fixed", "K_release"] {
        assert!(coverages[k] >= 0.8, "{k}: key-node coverage {:.3}", coverages[k]);
    }
    // the voxel grid is what spreads the keys (paper Table 3 (d)): same count, wider cover
    let (voxel, d) = (coverages["K_paper"], coverages["K_paper_ablation_d"]);
    assert!(voxel >= d + 0.05, "voxel-grid coverage {voxel:.3} vs ablation (d) {d:.3}");

    // The release's non-key cap: at most cap - 1 non-keys stay (strict test), the others are
    // culled, or unlinked when kept, and get no edges.
    let release = key_nodes::read(&dir.join("K_release/key_nodes.parquet")).unwrap();
    let args = ["keynodes", "--model", "S/oracle", "--profile", "release", "--uncertainty"];
    dir.ok(&[&args[..], &["U_release", "--nonkey-cap", "500", "--out", "K_cap"]].concat());
    let capped = key_nodes::read(&dir.join("K_cap/key_nodes.parquet")).unwrap();
    let (nonkeys, culled) = (capped.count(Role::Nonkey), capped.count(Role::Culled));
    println!(
        "release non-key cap 500: {} keys, {nonkeys} non-keys, {culled} culled (default cap: {})",
        capped.num_keys(),
        release.count(Role::Culled)
    );
    assert_eq!(capped.rows(Role::Key), release.rows(Role::Key));
    assert!(release.count(Role::Nonkey) >= 500, "the cap must bind for this test");
    assert!((400..500).contains(&nonkeys), "{nonkeys} non-keys");
    assert_eq!(capped.num_keys() + nonkeys + culled, capped.id.len());
    let keep = [&args[..], &["U_release", "--nonkey-cap", "500", "--out", "K_keep"]].concat();
    dir.ok(&[&keep[..], &["--unselected-nonkeys", "keep"]].concat());
    let kept = key_nodes::read(&dir.join("K_keep/key_nodes.parquet")).unwrap();
    assert_eq!((kept.count(Role::Unlinked), kept.count(Role::Culled)), (culled, 0));
    let edges = ["edges", "--model", "S/oracle", "--profile", "release", "--uncertainty"];
    dir.ok(&[&edges[..], &["U_release", "--keynodes", "K_cap", "--out", "E_cap"]].concat());
    let e = usplat4d::tables::edges::read(&dir.join("E_cap/edges.parquet")).unwrap();
    let role: std::collections::HashMap<u32, Role> =
        capped.id.iter().copied().zip(capped.role.iter().copied()).collect();
    let sources: HashSet<u32> = e.src.iter().copied().collect();
    assert!(e.src.iter().chain(&e.dst).all(|id| matches!(role[id], Role::Key | Role::Nonkey)));
    assert!(capped.rows(Role::Nonkey).iter().all(|&i| sources.contains(&capped.id[i])));
}

/// Unconverged rate and median u of a set of (Gaussian row, frame) pairs.
fn pair_stats(u: &[UncertaintyFrame], pairs: &[(usize, usize)]) -> (f64, f32) {
    let unconverged = pairs.iter().filter(|&&(i, t)| !u[t].converged[i]).count();
    let mut v: Vec<f32> = pairs.iter().map(|&(i, t)| u[t].u[i]).collect();
    v.sort_by(f32::total_cmp);
    (unconverged as f64 / pairs.len() as f64, v[v.len() / 2])
}

/// Fraction of the `pairs` converged in `before` that are unconverged in `after`.
fn flip_rate(
    before: &[UncertaintyFrame],
    after: &[UncertaintyFrame],
    pairs: &[(usize, usize)],
) -> f64 {
    let ok: Vec<_> = pairs.iter().filter(|&&(i, t)| before[t].converged[i]).collect();
    ok.iter().filter(|&&&(i, t)| !after[t].converged[i]).count() as f64 / ok.len() as f64
}

/// The drifted prior of the oracle in `dir/drifted`: a seeded half of the dynamic Gaussians
/// displaced in a window around the frames the oracle run `u0` does not see them in.
fn drifted_model(dir: &Dir, oracle: &Model, u0: &[UncertaintyFrame]) -> Drift {
    drifted_prior(
        dir,
        oracle,
        |i, t| u0[t].n_pixels[i] == 0,
        (DRIFT, DriftDirection::Random),
        MARGIN,
    )
}

/// (Gaussian row, frame) pairs.
type Pairs = Vec<(usize, usize)>;

/// Seen pairs (the oracle run saw the Gaussian in that frame) inside the drift window, and
/// the seen pairs of untouched Gaussians.
fn seen_pairs(u0: &[UncertaintyFrame], window: &[Vec<bool>], drifted: &[bool]) -> (Pairs, Pairs) {
    let (n, nt) = (window.len(), u0.len());
    let seen = |i: usize, t: usize| u0[t].n_pixels[i] > 0;
    let all = (0..n).flat_map(|i| (0..nt).map(move |t| (i, t)));
    let drift_seen: Vec<_> = all.clone().filter(|&(i, t)| window[i][t] && seen(i, t)).collect();
    let clean_seen: Vec<_> = all.filter(|&(i, t)| !drifted[i] && seen(i, t)).collect();
    (drift_seen, clean_seen)
}

#[test]
fn drifting_prior_raises_uncertainty() {
    let dir = Dir::new();
    fox_scene(&dir);
    dir.ok(&["uncertainty", "--model", "S/oracle", "--scene", "S", "--out", "U0"]);
    let oracle = Model::load(&dir.join("S/oracle")).unwrap();
    let (ids, u0) = uncertainty(&dir.join("U0/uncertainty.parquet"));
    assert_eq!(ids, oracle.gaussians.id, "the paper scope lists every Gaussian in model order");
    let Drift { window, drifted, offset } = drifted_model(&dir, &oracle, &u0);
    let n = ids.len();
    dir.ok(&["uncertainty", "--model", "drifted", "--scene", "S", "--out", "U1"]);
    let (_, u1) = uncertainty(&dir.join("U1/uncertainty.parquet"));

    // Seen = the oracle run saw the Gaussian in that frame (so its drift there is visible).
    let (drift_seen, clean_seen) = seen_pairs(&u0, &window, &drifted);
    let (rate_d, med_d) = pair_stats(&u1, &drift_seen);
    let (rate_c, med_c) = pair_stats(&u1, &clean_seen);
    let (rate_d0, _) = pair_stats(&u0, &drift_seen);
    let (flip_d, flip_c) = (flip_rate(&u0, &u1, &drift_seen), flip_rate(&u0, &u1, &clean_seen));
    println!(
        "drifting prior [paper]: {} of {n} Gaussians drifted by {offset:.3} in {} \
         (Gaussian, frame) pairs",
        drifted.iter().filter(|d| **d).count(),
        window.iter().flatten().filter(|w| **w).count(),
    );
    println!(
        "  drifted seen pairs:   {:6} unconverged {:5.1}% (same pairs on the oracle {:5.1}%), \
         converged-on-oracle turned unconverged {:5.1}%, median u {med_d:.3e}",
        drift_seen.len(),
        100.0 * rate_d,
        100.0 * rate_d0,
        100.0 * flip_d,
    );
    println!(
        "  untouched seen pairs: {:6} unconverged {:5.1}%, converged-on-oracle turned \
         unconverged {:5.1}%, median u {med_c:.3e}",
        clean_seen.len(),
        100.0 * rate_c,
        100.0 * flip_c,
    );
    assert!(drift_seen.len() >= 100, "only {} drifted seen pairs", drift_seen.len());
    assert!(
        rate_d >= 2.0 * rate_d0,
        "drifted {rate_d:.3} vs the same pairs on the oracle {rate_d0:.3}"
    );
    assert!(rate_d > rate_c, "drifted {rate_d:.3} vs untouched {rate_c:.3}");
    assert!(flip_d >= 10.0 * flip_c, "flips: drifted {flip_d:.3} vs untouched {flip_c:.3}");
}

/// Issue 15 item 4: the covered-pixel set of the paper's all-covered-pixels test, measured.
/// For each floor τ of `--cover-min-weight` (a pixel counts when the Gaussian's T·α ≥ τ;
/// 0 = every touched pixel, the paper read literally), the fraction of seen (Gaussian,
/// frame) pairs marked unreliable on the oracle (a perfect model: ideally none), and on the
/// drifted prior the unconverged rate of drifted and untouched seen pairs and the flips
/// from converged on the oracle. The paper profile's default must keep the oracle's
/// unreliable fraction at most 10% (literal reading τ = 0: 60% here, 42% on the default
/// 512² Fox) while still separating the drifted pairs.
#[test]
fn covered_pixel_floor_is_measured() {
    let dir = Dir::new();
    fox_scene(&dir);
    let run = |model: &str, out: &str, tau: Option<&str>| {
        let base = ["uncertainty", "--model", model, "--scene", "S", "--out", out];
        match tau {
            Some(t) => dir.ok(&[&base[..], &["--cover-min-weight", t]].concat()),
            None => dir.ok(&base),
        };
        uncertainty(&dir.join(out).join("uncertainty.parquet")).1
    };
    let u0 = run("S/oracle", "U0", Some("0"));
    let oracle = Model::load(&dir.join("S/oracle")).unwrap();
    let Drift { window, drifted, .. } = drifted_model(&dir, &oracle, &u0);
    let (drift_seen, clean_seen) = seen_pairs(&u0, &window, &drifted);
    let n = oracle.gaussians.len();
    let p0 = oracle.frame(0).unwrap().position;
    let voxel = bbox_diagonal(&p0) / 10.0;
    let all_seen: Vec<(usize, usize)> = (0..n)
        .flat_map(|i| (0..u0.len()).map(move |t| (i, t)))
        .filter(|&(i, t)| u0[t].n_pixels[i] > 0)
        .collect();
    println!(
        "covered-pixel floor τ (seen pairs: {} oracle, {} drifted):",
        all_seen.len(),
        drift_seen.len()
    );
    let mut at_default = None;
    for tau in [Some("0"), Some("0.01"), Some("0.05"), Some("0.1"), Some("0.2"), Some("0.5"), None]
    {
        let name = tau.unwrap_or("default");
        let uo = run("S/oracle", &format!("Uo_{name}"), tau);
        let ud = run("drifted", &format!("Ud_{name}"), tau);
        let (oracle_rate, _) = pair_stats(&uo, &all_seen);
        let (rate_d, _) = pair_stats(&ud, &drift_seen);
        let (rate_c, _) = pair_stats(&ud, &clean_seen);
        let (rate_d0, _) = pair_stats(&uo, &drift_seen);
        let (flip_d, flip_c) = (flip_rate(&uo, &ud, &drift_seen), flip_rate(&uo, &ud, &clean_seen));
        // key-node coverage of the paper's keys (voxel grid and ablation (d)) on the oracle
        let cover = |extra: &[&str], k: &str| {
            let args = ["keynodes", "--model", "S/oracle", "--uncertainty"];
            dir.ok(&[&args[..], &[&format!("Uo_{name}"), "--out", k], extra].concat());
            let keys = key_nodes::read(&dir.join(k).join("key_nodes.parquet")).unwrap();
            key_coverage(&p0, &key_mask(&oracle, &keys), voxel)
        };
        let cov = cover(&[], &format!("K_{name}"));
        let cov_d = cover(&["--candidate-sampling", "random"], &format!("Kd_{name}"));
        println!(
            "  τ {name:>7}: oracle unreliable {:5.1}%; drifted prior: drifted seen pairs \
             unconverged {:5.1}% (oracle {:5.1}%), untouched {:5.1}%, flips {:5.1}% vs {:5.1}%; \
             key coverage {:5.1}% (ablation d {:5.1}%)",
            100.0 * oracle_rate,
            100.0 * rate_d,
            100.0 * rate_d0,
            100.0 * rate_c,
            100.0 * flip_d,
            100.0 * flip_c,
            100.0 * cov,
            100.0 * cov_d
        );
        if tau.is_none() {
            at_default = Some((oracle_rate, rate_d, rate_d0, rate_c, flip_d, flip_c));
        }
    }
    let (oracle_rate, rate_d, rate_d0, rate_c, flip_d, flip_c) = at_default.unwrap();
    assert!(
        oracle_rate <= 0.1,
        "the paper default marks {oracle_rate:.3} of the oracle unreliable"
    );
    assert!(rate_d >= 2.0 * rate_d0 && rate_d > rate_c, "{rate_d:.3} vs {rate_d0:.3}, {rate_c:.3}");
    assert!(flip_d >= 10.0 * flip_c, "flips: drifted {flip_d:.3} vs untouched {flip_c:.3}");
}
