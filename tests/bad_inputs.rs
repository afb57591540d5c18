//! The bad-input corpus (`tests/bad_inputs/`, made by `gen_bad_inputs.py`): one test per
//! case pinning the exact message, and a guard that fails when a case has no test.
//! Not validated here: inputs that only a stage's own parameters make invalid (each stage
//! tests those).

use crate::util::{Dir, repo};

/// (case directory, expected stderr after "error: ").
const CASES: &[(&str, &str)] = &[
    (
        "model_nan_position",
        "tests/bad_inputs/model_nan_position/trajectories.parquet: column 'x', row 6: non-finite value NaN",
    ),
    (
        "model_frame_gap",
        "tests/bad_inputs/model_frame_gap/trajectories.parquet: frame 1: row 4 has frame 2, expected 1 (frames must be 0..T-1 without gaps, one row group each)",
    ),
    (
        "model_zero_quaternion",
        "tests/bad_inputs/model_zero_quaternion/trajectories.parquet: column 'qw,qx,qy,qz', row 9: quaternion (0, 0, 0, 0) has norm 0, expected 1",
    ),
    (
        "model_missing_column",
        "tests/bad_inputs/model_missing_column/gaussians.parquet: not a valid 'gaussians' table: missing column 'opacity' (f32)",
    ),
];

fn run_case(case: &str) -> String {
    let dir = Dir::new();
    let out = dir
        .command(&["check", &format!("tests/bad_inputs/{case}")])
        .current_dir(repo())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{case}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stderr).trim_end().to_string()
}

#[test]
fn pinned_messages() {
    for (case, msg) in CASES {
        assert_eq!(run_case(case), format!("error: {msg}"), "case {case}");
    }
}

#[test]
fn truncated_file_names_the_file() {
    let err = run_case("model_truncated_gaussians");
    assert!(
        err.starts_with(
            "error: tests/bad_inputs/model_truncated_gaussians/gaussians.parquet: Parquet error:"
        ),
        "{err}"
    );
}

#[test]
fn every_case_has_a_test() {
    let mut untested = Vec::new();
    for e in std::fs::read_dir(repo().join("tests/bad_inputs")).unwrap() {
        let e = e.unwrap();
        let name = e.file_name().to_string_lossy().into_owned();
        if e.path().is_dir()
            && name != "model_truncated_gaussians"
            && !CASES.iter().any(|(c, _)| *c == name)
        {
            untested.push(name);
        }
    }
    assert!(untested.is_empty(), "bad inputs without a test: {untested:?}");
}

/// The Parquet files that crashed parquet-rs 60 inside its footer and dictionary decoding
/// (`../shared/data/bad-parquet/`): every command that reads them exits 2 with an error
/// naming the file, never a panic (101).
#[test]
fn corrupted_parquet_exits_2_naming_the_file() {
    let Some(dir) = crate::util::shared_data("bad-parquet") else {
        eprintln!("SKIP corrupted_parquet_exits_2_naming_the_file: no ../shared/data/bad-parquet");
        return;
    };
    let work = Dir::new();
    let (scene, model) =
        usplat4d::datasets::demo::write_demo_scene(&work.join("valid"), 2).unwrap();
    let (scene, model) = (scene.to_str().unwrap().to_string(), model.to_str().unwrap().to_string());
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .collect();
    files.sort();
    for (i, f) in files.iter().enumerate() {
        let bytes = std::fs::read(f).unwrap();
        let kind = ["cameras", "gaussians", "uncertainty", "edges"]
            .into_iter()
            .find(|k| bytes.windows(k.len() + 1).any(|w| w[1..] == *k.as_bytes() && w[0] < b' '))
            .unwrap_or_else(|| panic!("{}: unknown table kind", f.display()));
        let case = work.join(&format!("case{i}"));
        std::fs::create_dir_all(&case).unwrap();
        let file = case.join(format!("{kind}.parquet"));
        std::fs::write(&file, &bytes).unwrap();
        let case = case.to_str().unwrap();
        let out = work.join(&format!("out{i}"));
        let out = out.to_str().unwrap();
        let mut commands: Vec<Vec<&str>> = vec![vec!["inspect", file.to_str().unwrap()]];
        match kind {
            "cameras" => {
                commands.push(vec!["check", case]);
                commands.push(vec!["render", "--model", &model, "--scene", case, "--out", out]);
            }
            "gaussians" => {
                std::fs::copy(
                    format!("{model}/trajectories.parquet"),
                    format!("{case}/trajectories.parquet"),
                )
                .unwrap();
                commands.push(vec!["check", case]);
                commands.push(vec!["render", "--model", case, "--scene", &scene, "--out", out]);
            }
            "uncertainty" => commands.push(vec![
                "keynodes",
                "--model",
                &model,
                "--uncertainty",
                case,
                "--out",
                out,
            ]),
            _ => commands.push(vec!["segment", "--edges", case, "--out", out]),
        }
        for args in commands {
            let err = work.fails(&args, 2);
            assert!(
                err.starts_with(&format!("error: {}: ", file.display())),
                "usplat4d {args:?}: {err}"
            );
        }
    }
}
