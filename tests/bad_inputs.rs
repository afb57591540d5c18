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
