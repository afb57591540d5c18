//! `usplat4d inspect` on the lead-owned tables: provenance, statistics, first rows; and its
//! error on a file that is not Parquet.

use crate::util::Dir;

#[test]
fn inspect_prints_schema_stats_and_rows() {
    let dir = Dir::new();
    let g = usplat4d::model::Gaussians {
        id: vec![4, 9],
        dynamic: vec![true, false],
        scale: vec![[0.1, 0.2, 0.3], [1.0, 2.0, 3.0]],
        opacity: vec![0.25, 0.75],
        color: vec![[0.0, 0.5, 1.0]; 2],
        sh_degree: 0,
        sh_rest: vec![],
    };
    let p = dir.join("gaussians.parquet");
    usplat4d::tables::gaussians::write(
        &p,
        &g,
        &usplat4d::tables::Provenance::new("synth", &serde_json::json!({"seed": 3})),
    )
    .unwrap();
    let out = dir.ok(&["inspect", "gaussians.parquet", "--head", "1"]);
    assert!(out.contains("table: gaussians"), "{out}");
    assert!(out.contains("stage: synth"), "{out}");
    assert!(out.contains(r#"params: {"seed":3}"#), "{out}");
    assert!(out.contains("rows: 2  row groups: 1"), "{out}");
    let opacity = out.lines().find(|l| l.starts_with("opacity")).unwrap();
    assert_eq!(
        opacity.split_whitespace().collect::<Vec<_>>(),
        ["opacity", "f32", "0", "0.250000", "0.750000"]
    );
    assert!(out.contains("first 1 rows:"), "{out}");
}

#[test]
fn inspect_rejects_non_parquet_with_file_name() {
    let dir = Dir::new();
    std::fs::write(dir.join("x.parquet"), b"not parquet").unwrap();
    std::fs::write(dir.join("params.json"), br#"{"seed": 1, "frames": [1, 2, 3]}"#).unwrap();
    for file in ["x.parquet", "params.json"] {
        let err = dir.fails(&["inspect", file], 2);
        assert_eq!(
            err.trim_end(),
            format!("error: {file}: not a Parquet file (it does not start with the bytes PAR1)")
        );
    }
}
