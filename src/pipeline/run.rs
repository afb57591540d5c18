//! The runner: walks the stages in topological order and, for each, skips it (lock matches),
//! restores it (run cache holds its key) or runs it through an [`Executor`], then records it.
//!
//! Atomicity is per stage: before running, the stage's old outputs are removed; its lock entry
//! is written (atomically) only after it finished and its outputs were hashed and cached. A
//! run killed mid-stage therefore leaves outputs that no lock entry vouches for, and the next
//! run redoes that stage while skipping the ones that finished.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::path::{Path, PathBuf};

use super::Error;
use super::cache::{RunCache, remove_path, sweep_restores};
use super::dag::Dag;
use super::hash::{self, Hasher};
use super::lock::{Lock, LockEntry};
use super::spec::{Pipeline, Stage};
use super::status::{self, Reason};
use crate::context::Context;

/// Runs one stage's command. The real one is `cli::InProcess` (the pipeline does not know
/// the stages); tests use a double that writes files, so the runner logic is tested without
/// the stage implementations.
pub trait Executor {
    /// Run `stage.argv`, resolving relative paths against `base` (the pipeline directory).
    fn execute(&mut self, stage: &Stage, base: &Path) -> anyhow::Result<()>;

    /// What the stages render on (`cpu`, `gpu:<adapter>`): part of every stage's cache key,
    /// so that an output of one device is never restored as another's.
    fn device(&mut self) -> anyhow::Result<String>;
}

/// Options of `pipeline run` (already parsed).
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Stages (or foreach groups `name` for every `name@item`) to run even if up to date.
    pub force: Vec<String>,
    /// When non-empty, only these stages are considered; their deps must exist.
    pub only: Vec<String>,
    /// Print the plan without running anything.
    pub dry_run: bool,
}

/// What happened (or would happen) to one stage.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Up to date.
    Skipped,
    /// Outputs restored from the run cache.
    Restored,
    /// Executed, for these reasons.
    Ran(Vec<Reason>),
}

impl Outcome {
    fn line(&self, stage: &str) -> String {
        match self {
            Outcome::Skipped => format!("skip {stage} (up to date)"),
            Outcome::Restored => format!("restore {stage} (from run cache)"),
            Outcome::Ran(r) => format!("run  {stage} ({})", status::join(r)),
        }
    }
}

/// Resolve `--force`/`--only` names (a stage, or a foreach group) to stage indices.
pub fn select(p: &Pipeline, names: &[String], flag: &str) -> Result<BTreeSet<usize>, Error> {
    let mut out = BTreeSet::new();
    for n in names {
        let hits: Vec<usize> = (0..p.stages.len())
            .filter(|&i| {
                let s = &p.stages[i].name;
                s == n || s.strip_prefix(n.as_str()).is_some_and(|r| r.starts_with('@'))
            })
            .collect();
        if hits.is_empty() {
            return Err(Error::BadArgument {
                file: p.file.clone(),
                message: format!("{flag} `{n}`: no such stage"),
            });
        }
        out.extend(hits);
    }
    Ok(out)
}

/// The runner's state for one pipeline: lock, hasher and run cache.
pub struct Runner<'a> {
    p: &'a Pipeline,
    dag: Dag,
    lock: Lock,
    hasher: Hasher,
    cache: RunCache,
}

impl<'a> Runner<'a> {
    /// Validate the graph and open the lock, stat cache and run cache of `p`.
    pub fn open(
        p: &'a Pipeline,
        cache_max_bytes: u64,
        check_files: bool,
    ) -> Result<Runner<'a>, Error> {
        let dag = Dag::build(p, check_files)?;
        let lock = Lock::load(&p.lock_path())?;
        let state = p.state_dir();
        let hasher = Hasher::with_cache(state.join("stat-cache.json"));
        let cache = RunCache::new(state.join("cache"), cache_max_bytes);
        Ok(Runner { p, dag, lock, hasher, cache })
    }

    /// Key every stage by the renderer that runs it (`cpu` or `gpu:<adapter>`), so that a
    /// GPU output is never restored as a CPU one or the reverse.
    pub fn set_device(&mut self, tag: &str) {
        self.hasher.set_device(tag);
    }

    /// Decide every stage without running anything: `(stage index, outcome)` in order.
    /// Stages downstream of a changing stage are reported with [`Reason::Upstream`].
    pub fn plan(&mut self, opts: &RunOptions) -> Result<Vec<(usize, Outcome)>, Error> {
        let force = select(self.p, &opts.force, "--force")?;
        let only = select(self.p, &opts.only, "--only")?;
        let mut changing = vec![false; self.p.stages.len()];
        let mut plan = Vec::new();
        for &i in &self.dag.order {
            if !only.is_empty() && !only.contains(&i) {
                continue;
            }
            let stage = &self.p.stages[i];
            let cur = status::current(self.p, stage, &mut self.hasher)?;
            let entry = self.lock.stages.get(&stage.name);
            let mut reasons = status::explain(stage, entry, &cur);
            let mut ups: Vec<String> = self.dag.upstream[i]
                .iter()
                .filter(|e| changing[e.from])
                .map(|e| self.p.stages[e.from].name.clone())
                .collect();
            ups.dedup();
            if !ups.is_empty() {
                // Deps an upstream stage is about to (re)create are not worth reporting.
                reasons.retain(|r| !matches!(r, Reason::DepMissing { .. }));
            }
            reasons.extend(ups.into_iter().map(|stage| Reason::Upstream { stage }));
            if force.contains(&i) {
                reasons.insert(0, Reason::Forced);
            }
            let outcome = if reasons.is_empty() {
                Outcome::Skipped
            } else if self.restorable(&force, i, &cur.key) {
                Outcome::Restored
            } else {
                Outcome::Ran(reasons)
            };
            changing[i] = outcome != Outcome::Skipped;
            plan.push((i, outcome));
        }
        Ok(plan)
    }

    /// A stage is restored (not run) when it is not forced, its key differs from the lock's
    /// (inputs changed, not outputs tampered with) and the run cache holds that key.
    fn restorable(&self, force: &BTreeSet<usize>, i: usize, key: &Option<String>) -> bool {
        let Some(key) = key else { return false };
        let lock_key = self.lock.stages.get(&self.p.stages[i].name).map(|e| &e.key);
        !force.contains(&i) && lock_key != Some(key) && self.cache.contains(key)
    }

    /// Run the pipeline, printing one line per stage and a summary to `out`.
    pub fn run(
        &mut self,
        opts: &RunOptions,
        exec: &mut dyn Executor,
        ctx: &Context,
        out: &mut dyn Write,
    ) -> Result<Vec<(usize, Outcome)>, Error> {
        let io = Error::io("<stdout>");
        if opts.dry_run {
            let plan = self.plan(opts)?;
            for (i, o) in &plan {
                writeln!(out, "{}", o.line(&self.p.stages[*i].name)).map_err(io)?;
            }
            writeln!(out, "dry run: {}", summary(&plan)).map_err(io)?;
            return Ok(plan);
        }
        let force = select(self.p, &opts.force, "--force")?;
        let only = select(self.p, &opts.only, "--only")?;
        let names: Vec<&str> = self.p.stages.iter().map(|s| s.name.as_str()).collect();
        self.lock.retain(&names);
        let parents: BTreeSet<PathBuf> = self
            .p
            .stages
            .iter()
            .flat_map(|s| &s.outs)
            .filter_map(|o| self.p.path(o).parent().map(Path::to_path_buf))
            .collect();
        for dir in &parents {
            sweep_restores(dir)?;
        }
        let mut done = Vec::new();
        let order = self.dag.order.clone();
        for i in order {
            if !only.is_empty() && !only.contains(&i) {
                continue;
            }
            let result = self.run_stage(i, &force, exec, ctx, out);
            self.hasher.save()?;
            done.push((i, result?));
        }
        writeln!(out, "{}", summary(&done)).map_err(io)?;
        Ok(done)
    }

    fn run_stage(
        &mut self,
        i: usize,
        force: &BTreeSet<usize>,
        exec: &mut dyn Executor,
        ctx: &Context,
        out: &mut dyn Write,
    ) -> Result<Outcome, Error> {
        let io = Error::io("<stdout>");
        let p = self.p;
        let stage = &p.stages[i];
        let cur = status::current(p, stage, &mut self.hasher)?;
        let Some(key) = cur.key.clone() else {
            let path = cur
                .deps
                .iter()
                .find(|(_, h)| h.is_none())
                .map(|(d, _)| d.clone())
                .unwrap_or_default();
            return Err(Error::MissingDep {
                file: p.file.clone(),
                stage: stage.name.clone(),
                path,
            });
        };
        let mut reasons = status::explain(stage, self.lock.stages.get(&stage.name), &cur);
        if force.contains(&i) {
            reasons.insert(0, Reason::Forced);
        }
        let deps: BTreeMap<String, String> =
            cur.deps.into_iter().filter_map(|(k, v)| Some((k, v?))).collect();
        let mut entry = LockEntry {
            key: key.clone(),
            cmd: stage.cmd.clone(),
            tool_version: cur.tool.clone(),
            params: stage.params.clone(),
            deps,
            outs: BTreeMap::new(),
        };
        let outcome = if reasons.is_empty() {
            Outcome::Skipped
        } else if self.restorable(force, i, &cur.key)
            && let Some(outs) = self.restore(&key, &cur.outs)?
        {
            entry.outs = outs;
            Outcome::Restored
        } else {
            writeln!(out, "{}", Outcome::Ran(reasons.clone()).line(&stage.name)).map_err(io)?;
            out.flush().map_err(io)?;
            for o in &stage.outs {
                let path = p.path(o);
                remove_path(&path)?;
                if let Some(parent) = path.parent() {
                    std::fs::create_dir_all(parent).map_err(Error::io(parent))?;
                }
            }
            let span = tracing::info_span!("stage", name = %stage.name);
            let _guard = span.enter();
            exec.execute(stage, &p.base).map_err(|e| Error::StageFailed {
                stage: stage.name.clone(),
                message: format!("{e:#}"),
            })?;
            let mut trees = BTreeMap::new();
            for o in &stage.outs {
                let tree = self.hasher.hash(&p.path(o))?.ok_or_else(|| {
                    Error::OutputNotProduced { stage: stage.name.clone(), path: o.clone() }
                })?;
                trees.insert(o.clone(), tree);
            }
            if self.cache_enabled() {
                match self.cache.store(&key, &p.base, &trees) {
                    Ok(_) => {}
                    Err(e) => ctx
                        .warn(format!("stage `{}`: not stored in the run cache: {e}", stage.name)),
                }
            }
            entry.outs = trees.into_iter().map(|(k, t)| (k, t.hash)).collect();
            Outcome::Ran(reasons)
        };
        if outcome != Outcome::Skipped {
            self.lock.record(&stage.name, entry)?;
        }
        if !matches!(outcome, Outcome::Ran(_)) {
            writeln!(out, "{}", outcome.line(&stage.name)).map_err(io)?;
        }
        Ok(outcome)
    }

    /// Restore the outputs cached under `key`, or adopt the current ones without copying when
    /// they already are those outputs (e.g. after the lock file was lost). Returns the output
    /// hashes, `None` when the cache cannot provide them.
    fn restore(
        &self,
        key: &str,
        current: &BTreeMap<String, Option<hash::Tree>>,
    ) -> Result<Option<BTreeMap<String, String>>, Error> {
        let now: Option<BTreeMap<String, String>> =
            current.iter().map(|(k, t)| t.as_ref().map(|t| (k.clone(), t.hash.clone()))).collect();
        if now.is_some() && self.cache.out_hashes(key) == now {
            return Ok(now);
        }
        let restored = self.cache.restore(key, &self.p.base)?;
        Ok(restored.map(|trees| trees.into_iter().map(|(k, t)| (k, t.hash)).collect()))
    }

    fn cache_enabled(&self) -> bool {
        self.cache.max_bytes() > 0
    }

    /// `pipeline status`: one line per stage, `name: up to date` or `name: <reasons>`.
    pub fn status(&mut self, out: &mut dyn Write) -> Result<(), Error> {
        let io = Error::io("<stdout>");
        let plan = self.plan(&RunOptions::default())?;
        for (i, o) in &plan {
            let name = &self.p.stages[*i].name;
            match o {
                Outcome::Skipped => writeln!(out, "{name}: up to date"),
                Outcome::Restored => {
                    let cur = status::current(self.p, &self.p.stages[*i], &mut self.hasher)?;
                    let r = status::explain(&self.p.stages[*i], self.lock.stages.get(name), &cur);
                    writeln!(out, "{name}: {} (restorable from run cache)", status::join(&r))
                }
                Outcome::Ran(r) => writeln!(out, "{name}: {}", status::join(r)),
            }
            .map_err(io)?;
        }
        self.hasher.save()
    }

    /// `pipeline dag`: stages in topological order with their upstream edges, as text or
    /// Graphviz dot.
    pub fn dag(&self, dot: bool, out: &mut dyn Write) -> Result<(), Error> {
        let io = Error::io("<stdout>");
        let name = |i: usize| &self.p.stages[i].name;
        if dot {
            writeln!(out, "digraph pipeline {{").map_err(io)?;
            for &i in &self.dag.order {
                writeln!(out, "  \"{}\";", name(i)).map_err(io)?;
            }
            for &i in &self.dag.order {
                for e in &self.dag.upstream[i] {
                    writeln!(
                        out,
                        "  \"{}\" -> \"{}\" [label=\"{}\"];",
                        name(e.from),
                        name(i),
                        e.path
                    )
                    .map_err(io)?;
                }
            }
            writeln!(out, "}}").map_err(io)?;
            return Ok(());
        }
        for &i in &self.dag.order {
            let ups: Vec<String> = self.dag.upstream[i]
                .iter()
                .map(|e| format!("{} ({})", name(e.from), e.path))
                .collect();
            if ups.is_empty() {
                writeln!(out, "{}", name(i)).map_err(io)?;
            } else {
                writeln!(out, "{} <- {}", name(i), ups.join(", ")).map_err(io)?;
            }
        }
        Ok(())
    }
}

/// The final line of a run.
fn summary(done: &[(usize, Outcome)]) -> String {
    let count = |f: fn(&Outcome) -> bool| done.iter().filter(|(_, o)| f(o)).count();
    let (ran, restored, skipped) = (
        count(|o| matches!(o, Outcome::Ran(_))),
        count(|o| *o == Outcome::Restored),
        count(|o| *o == Outcome::Skipped),
    );
    if skipped == done.len() {
        return format!("all {} stages up to date", done.len());
    }
    format!(
        "{} stages: {ran} run, {restored} restored from run cache, {skipped} up to date",
        done.len()
    )
}
