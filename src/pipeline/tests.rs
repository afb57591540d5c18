//! Runner behaviour tests with [`FileOps`], a real executor over a tiny command language that
//! reads and writes files (no usplat4d stages involved).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::*;
use crate::context::Context;

/// Test executor: `cat OUT IN...` writes the concatenation of the IN files (a directory IN
/// contributes its files in sorted order) plus nothing else; `echo OUT WORD...` writes the
/// words; `split DIR IN` writes each line of IN as `DIR/<n>.txt`; `fail MSG` errors;
/// `crash OUT` writes half an output and errors (a kill between writing and recording).
/// Counts executions per stage.
#[derive(Default)]
struct FileOps {
    runs: BTreeMap<String, usize>,
}

impl FileOps {
    fn total(&self) -> usize {
        self.runs.values().sum()
    }
}

fn read_input(p: &Path) -> anyhow::Result<String> {
    if p.is_dir() {
        let mut names: Vec<PathBuf> =
            std::fs::read_dir(p)?.map(|e| e.map(|e| e.path())).collect::<Result<_, _>>()?;
        names.sort();
        names.iter().map(|n| read_input(n)).collect()
    } else {
        Ok(std::fs::read_to_string(p)?)
    }
}

impl Executor for FileOps {
    fn execute(&mut self, stage: &Stage, base: &Path) -> anyhow::Result<()> {
        *self.runs.entry(stage.name.clone()).or_default() += 1;
        let a = &stage.argv;
        let path = |i: usize| base.join(&a[i]);
        match a[0].as_str() {
            "cat" => {
                let text: String =
                    (2..a.len()).map(|i| read_input(&path(i))).collect::<anyhow::Result<_>>()?;
                std::fs::write(path(1), text)?;
            }
            "echo" => std::fs::write(path(1), a[2..].join(" "))?,
            "split" => {
                std::fs::create_dir_all(path(1))?;
                for (n, line) in std::fs::read_to_string(path(2))?.lines().enumerate() {
                    std::fs::write(path(1).join(format!("{n}.txt")), line)?;
                }
            }
            "fail" => anyhow::bail!("{}", a[1..].join(" ")),
            "crash" => {
                std::fs::write(path(1), "half")?;
                anyhow::bail!("killed");
            }
            other => anyhow::bail!("unknown test command {other}"),
        }
        Ok(())
    }

    fn device(&mut self) -> anyhow::Result<String> {
        Ok("cpu".into())
    }
}

/// A pipeline directory in a tempdir.
struct Fixture {
    dir: tempfile::TempDir,
    exec: FileOps,
    cache_max_bytes: u64,
}

const PIPE: &str = "\
params:
  greeting: hello
  suffix: '!'
stages:
  hello:
    cmd: echo hello.txt ${greeting}
    outs: [hello.txt]
  both:
    cmd: cat both.txt hello.txt input.txt
    deps: [hello.txt, input.txt]
    outs: [both.txt]
  lines:
    cmd: split lines both.txt
    deps: [both.txt]
    outs: [lines]
  tail:
    cmd: echo tail.txt ${suffix}
    outs: [tail.txt]
  per:
    foreach: [a, b]
    do:
      cmd: cat per-${item}.txt lines tail.txt
      deps: [lines, tail.txt]
      outs: ['per-${item}.txt']
";

impl Fixture {
    fn new(yaml: &str) -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("p.yaml"), yaml).unwrap();
        std::fs::write(dir.path().join("input.txt"), "\nworld\n").unwrap();
        Fixture { dir, exec: FileOps::default(), cache_max_bytes: 1 << 30 }
    }

    fn file(&self) -> PathBuf {
        self.dir.path().join("p.yaml")
    }

    fn read(&self, name: &str) -> String {
        std::fs::read_to_string(self.dir.path().join(name)).unwrap()
    }

    /// Run with options; returns the printed lines and the number of executions.
    fn run_with(&mut self, sets: &[&str], opts: RunOptions) -> Result<(Vec<String>, usize), Error> {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let p = Pipeline::load(&self.file(), &sets)?;
        let before = self.exec.total();
        let mut out = Vec::new();
        let mut runner = Runner::open(&p, self.cache_max_bytes, opts.only.is_empty())?;
        runner.run(&opts, &mut self.exec, &Context::quiet(), &mut out)?;
        let lines = String::from_utf8(out).unwrap().lines().map(String::from).collect();
        Ok((lines, self.exec.total() - before))
    }

    fn run(&mut self, sets: &[&str]) -> (Vec<String>, usize) {
        self.run_with(sets, RunOptions::default()).unwrap()
    }

    fn status(&self, sets: &[&str]) -> Vec<String> {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let p = Pipeline::load(&self.file(), &sets).unwrap();
        let mut out = Vec::new();
        Runner::open(&p, u64::MAX, true).unwrap().status(&mut out).unwrap();
        String::from_utf8(out).unwrap().lines().map(String::from).collect()
    }
}

#[test]
fn first_run_runs_everything_second_run_nothing() {
    let mut f = Fixture::new(PIPE);
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 6);
    assert_eq!(lines[0], "run  hello (never run)");
    assert_eq!(lines.last().unwrap(), "6 stages: 6 run, 0 restored from run cache, 0 up to date");
    assert_eq!(f.read("per-a.txt"), "helloworld!");
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 0);
    assert_eq!(lines[..2], ["skip hello (up to date)", "skip both (up to date)"]);
    assert_eq!(lines.last().unwrap(), "all 6 stages up to date");
    assert!(f.status(&[]).iter().all(|l| l.ends_with(": up to date")));
}

#[test]
fn a_param_change_reruns_that_stage_and_downstream_only() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    assert_eq!(
        f.status(&["suffix=?"]),
        [
            "hello: up to date",
            "both: up to date",
            "lines: up to date",
            "tail: param suffix changed ! -> ?",
            "per@a: upstream tail out of date",
            "per@b: upstream tail out of date",
        ]
    );
    let (lines, n) = f.run(&["suffix=?"]);
    assert_eq!(n, 3);
    assert_eq!(
        lines,
        [
            "skip hello (up to date)",
            "skip both (up to date)",
            "skip lines (up to date)",
            "run  tail (param suffix changed ! -> ?)",
            "run  per@a (dep tail.txt changed)",
            "run  per@b (dep tail.txt changed)",
            "6 stages: 3 run, 0 restored from run cache, 3 up to date",
        ]
    );
    assert_eq!(f.exec.runs["tail"], 2);
    assert_eq!(f.exec.runs["hello"], 1);
    assert_eq!(f.read("per-b.txt"), "helloworld?");
}

#[test]
fn an_unchanged_output_after_an_upstream_rerun_stops_propagation() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    let (lines, n) =
        f.run_with(&[], RunOptions { force: vec!["hello".into()], ..Default::default() }).unwrap();
    assert_eq!(n, 1);
    assert_eq!(lines[0], "run  hello (forced)");
    assert_eq!(lines[1], "skip both (up to date)");
}

#[test]
fn a_deleted_or_edited_output_reruns_its_stage() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    std::fs::remove_file(f.dir.path().join("both.txt")).unwrap();
    assert_eq!(f.status(&[])[1], "both: out both.txt missing");
    let (lines, n) = f.run(&[]);
    assert_eq!((lines[1].as_str(), n), ("run  both (out both.txt missing)", 1));
    std::fs::write(f.dir.path().join("lines/1.txt"), "edited, longer").unwrap();
    assert_eq!(f.status(&[])[2], "lines: out lines modified");
    let (lines, n) = f.run(&[]);
    assert_eq!((lines[2].as_str(), n), ("run  lines (out lines modified)", 1));
    assert_eq!(f.read("lines/1.txt"), "world");
    assert_eq!(f.exec.runs["lines"], 2);
}

#[test]
fn setting_a_param_back_restores_from_the_run_cache() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    f.run(&["greeting=bye"]);
    assert_eq!(f.read("per-a.txt"), "byeworld!");
    assert_eq!(
        f.status(&[])[0],
        "hello: param greeting changed bye -> hello (restorable from run cache)"
    );
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 0, "{lines:?}");
    assert_eq!(
        lines,
        [
            "restore hello (from run cache)",
            "restore both (from run cache)",
            "restore lines (from run cache)",
            "skip tail (up to date)",
            "restore per@a (from run cache)",
            "restore per@b (from run cache)",
            "6 stages: 0 run, 5 restored from run cache, 1 up to date",
        ]
    );
    assert_eq!(f.read("per-a.txt"), "helloworld!");
    assert_eq!(f.read("lines/0.txt"), "hello");
    assert_eq!(f.run(&[]).1, 0);
}

#[test]
fn a_lost_lock_is_rebuilt_from_the_run_cache_without_copying() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    let mtime = |f: &Fixture| {
        std::fs::metadata(f.dir.path().join("lines/0.txt")).unwrap().modified().unwrap()
    };
    let before = mtime(&f);
    std::fs::remove_file(f.dir.path().join("p.lock")).unwrap();
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 0);
    assert_eq!(lines.last().unwrap(), "6 stages: 0 run, 6 restored from run cache, 0 up to date");
    assert_eq!(mtime(&f), before);
    assert_eq!(f.run(&[]).0.last().unwrap(), "all 6 stages up to date");
}

#[test]
fn without_a_run_cache_setting_a_param_back_reruns() {
    let mut f = Fixture::new(PIPE);
    f.cache_max_bytes = 0;
    f.run(&[]);
    f.run(&["suffix=?"]);
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 3);
    assert_eq!(lines[3], "run  tail (param suffix changed ? -> !)");
    assert!(!f.dir.path().join(".usplat4d/cache").exists());
}

#[test]
fn a_stage_killed_midway_is_redone_and_finished_stages_are_kept() {
    let yaml = PIPE
        .replace("cmd: split lines both.txt", "cmd: ${split} lines both.txt")
        .replace("params:\n", "params:\n  split: split\n");
    let mut f = Fixture::new(&yaml);
    let e = f.run_with(&["split=crash"], RunOptions::default()).unwrap_err();
    assert_eq!(e.to_string(), "stage `lines` failed: killed");
    assert_eq!(f.read("lines"), "half");
    let lock = lock::Lock::load(&f.dir.path().join("p.lock")).unwrap();
    assert_eq!(lock.stages.keys().collect::<Vec<_>>(), ["both", "hello"]);
    let (lines, n) = f.run(&[]);
    assert_eq!(n, 4);
    assert_eq!(
        lines[..3],
        ["skip hello (up to date)", "skip both (up to date)", "run  lines (never run)"]
    );
    assert_eq!(f.read("lines/0.txt"), "hello");
    // Killed again while re-running a stage that has an entry: the entry no longer matches.
    f.run_with(&["split=crash"], RunOptions { force: vec!["lines".into()], ..Default::default() })
        .unwrap_err();
    assert_eq!(f.status(&[])[2], "lines: out lines modified");
    assert_eq!(f.run(&[]).1, 1);
}

#[test]
fn only_runs_one_stage_on_existing_deps_and_dry_run_runs_nothing() {
    let mut f = Fixture::new(PIPE);
    let e = f
        .run_with(&[], RunOptions { only: vec!["both".into()], ..Default::default() })
        .unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "{}: stage `both`: dependency `hello.txt` does not exist and no stage outputs it",
            f.file().display()
        )
    );
    let (lines, n) = f.run_with(&[], RunOptions { dry_run: true, ..Default::default() }).unwrap();
    assert_eq!(n, 0);
    assert_eq!(lines[1], "run  both (never run; upstream hello out of date)");
    assert_eq!(
        lines.last().unwrap(),
        "dry run: 6 stages: 6 run, 0 restored from run cache, 0 up to date"
    );
    f.run(&[]);
    let (lines, n) = f
        .run_with(
            &["greeting=hi"],
            RunOptions { only: vec!["per".into(), "hello".into()], ..Default::default() },
        )
        .unwrap();
    assert_eq!(n, 1);
    assert_eq!(
        lines,
        [
            "run  hello (param greeting changed hello -> hi)",
            "skip per@a (up to date)",
            "skip per@b (up to date)",
            "3 stages: 1 run, 0 restored from run cache, 2 up to date"
        ]
    );
    let e = f
        .run_with(&[], RunOptions { force: vec!["nope".into()], ..Default::default() })
        .unwrap_err();
    assert_eq!(e.to_string(), format!("{}: --force `nope`: no such stage", f.file().display()));
}

#[test]
fn a_failing_stage_is_named_and_not_recorded() {
    let mut f = Fixture::new(
        "stages:\n  a: {cmd: echo a.txt x, outs: [a.txt]}\n  b: {cmd: fail disk on fire, deps: [a.txt], outs: [b.txt]}\n  c: {cmd: echo c.txt, outs: [c.txt]}\n",
    );
    let e = f.run_with(&[], RunOptions::default()).unwrap_err();
    assert_eq!(e.to_string(), "stage `b` failed: disk on fire");
    assert_eq!(f.status(&[]), ["a: up to date", "b: never run", "c: never run"]);
    let mut f = Fixture::new("stages:\n  a: {cmd: echo a.txt x, outs: [elsewhere.txt]}\n");
    let e = f.run_with(&[], RunOptions::default()).unwrap_err();
    assert_eq!(e.to_string(), "stage `a` did not produce its output `elsewhere.txt`");
}

#[test]
fn dag_prints_order_and_edges() {
    let f = Fixture::new(PIPE);
    let p = Pipeline::load(&f.file(), &[]).unwrap();
    let r = Runner::open(&p, 0, true).unwrap();
    let mut out = Vec::new();
    r.dag(false, &mut out).unwrap();
    assert_eq!(
        String::from_utf8(out).unwrap(),
        "hello\nboth <- hello (hello.txt)\nlines <- both (both.txt)\ntail\nper@a <- lines (lines), tail (tail.txt)\nper@b <- lines (lines), tail (tail.txt)\n"
    );
    let mut out = Vec::new();
    r.dag(true, &mut out).unwrap();
    let dot = String::from_utf8(out).unwrap();
    assert!(
        dot.starts_with("digraph pipeline {\n  \"hello\";\n")
            && dot.contains("  \"tail\" -> \"per@b\" [label=\"tail.txt\"];\n"),
        "{dot}"
    );
}

#[test]
fn the_lock_records_params_and_a_dep_edit_is_reported() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    let lock = lock::Lock::load(&f.dir.path().join("p.lock")).unwrap();
    assert_eq!(
        lock.stages["hello"].params,
        BTreeMap::from([("greeting".to_string(), "hello".to_string())])
    );
    let tool = &lock.stages["hello"].tool_version;
    assert!(tool.starts_with(&format!("{}+", crate::VERSION)) && tool.len() > 6, "{tool}");
    std::fs::write(f.dir.path().join("input.txt"), "\nthere\n").unwrap();
    assert_eq!(
        f.status(&[])[1..3],
        ["both: dep input.txt changed", "lines: upstream both out of date"]
    );
    let (_, n) = f.run(&[]);
    assert_eq!(n, 4);
}

#[test]
fn a_rebuilt_tool_reruns_its_stages() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    let path = f.dir.path().join("p.lock");
    let mut lock = lock::Lock::load(&path).unwrap();
    let now = lock.stages["hello"].tool_version.clone();
    let mut entry = lock.stages["hello"].clone();
    entry.tool_version = format!("{}+0000000000000000", crate::VERSION);
    lock.record("hello", entry).unwrap();
    let status = f.status(&[]).join("\n");
    let expected = format!("tool changed {}+0000000000000000 -> {now}", crate::VERSION);
    assert!(status.contains(&expected), "{status}");
    let (_, runs) = f.run(&[]);
    assert!(runs > 0, "the stage ran again");
}

/// A run killed while restoring from the run cache leaves its staging directory
/// (`.restore-*` beside the output, holding a partial copy); the next run removes it, whether
/// it restores, runs or skips the stage, and leaves the user's own hidden files alone.
#[test]
fn the_next_run_sweeps_the_staging_of_a_killed_restore() {
    let mut f = Fixture::new(PIPE);
    f.run(&[]);
    let base = f.dir.path().to_path_buf();
    let killed = |name: &str| {
        let staged = base.join(name).join("out");
        std::fs::create_dir_all(&staged).unwrap();
        std::fs::write(staged.join("0.txt"), "hel").unwrap();
    };
    killed(".restore-Ab12Cd");
    killed(".restore-Zz99yy");
    std::fs::write(base.join(".restore-notes"), "mine").unwrap();
    let (lines, n) = f.run(&[]);
    assert_eq!((lines.last().unwrap().as_str(), n), ("all 6 stages up to date", 0));
    let left: Vec<String> = std::fs::read_dir(&base)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".restore-"))
        .collect();
    assert_eq!(left, [".restore-notes"], "staging directories of a killed restore remain");
}
