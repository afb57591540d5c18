//! Why a stage is out of date: the comparison of a stage's current state (params, cmd, dep
//! and output hashes) with its lock entry, as a list of human-readable [`Reason`]s.

use std::collections::BTreeMap;
use std::fmt;

use super::Error;
use super::hash::{Hasher, Tree};
use super::lock::LockEntry;
use super::spec::{Pipeline, Stage};

/// One reason for (re)running a stage.
#[derive(Debug, Clone, PartialEq)]
pub enum Reason {
    /// No lock entry.
    NeverRun,
    /// `--force`.
    Forced,
    /// The tool (version or executable, see [`Hasher::tool_id`]) differs from the one
    /// that ran it.
    ToolVersion {
        /// Recorded tool id.
        from: String,
        /// The running tool's id.
        to: String,
    },
    /// A parameter value changed.
    ParamChanged {
        /// Parameter.
        name: String,
        /// Recorded value.
        from: String,
        /// Current value.
        to: String,
    },
    /// The stage uses a parameter it did not use before.
    ParamAdded {
        /// Parameter.
        name: String,
    },
    /// The stage no longer uses a parameter.
    ParamRemoved {
        /// Parameter.
        name: String,
    },
    /// The command changed (other than through parameters).
    CmdChanged,
    /// The list of outputs changed.
    OutsChanged,
    /// A dep's content changed.
    DepChanged {
        /// Dep.
        path: String,
    },
    /// A dep not recorded before.
    DepAdded {
        /// Dep.
        path: String,
    },
    /// A recorded dep is no longer declared.
    DepRemoved {
        /// Dep.
        path: String,
    },
    /// A dep does not exist (yet).
    DepMissing {
        /// Dep.
        path: String,
    },
    /// An output is missing.
    OutMissing {
        /// Output.
        path: String,
    },
    /// An output differs from what the stage produced.
    OutModified {
        /// Output.
        path: String,
    },
    /// An upstream stage will change this stage's deps.
    Upstream {
        /// The upstream stage.
        stage: String,
    },
    /// The key differs but nothing above explains it (e.g. a hand-edited lock).
    DefinitionChanged,
}

impl fmt::Display for Reason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Reason::NeverRun => write!(f, "never run"),
            Reason::Forced => write!(f, "forced"),
            Reason::ToolVersion { from, to } => write!(f, "tool changed {from} -> {to}"),
            Reason::ParamChanged { name, from, to } => {
                write!(f, "param {name} changed {from} -> {to}")
            }
            Reason::ParamAdded { name } => write!(f, "new param {name}"),
            Reason::ParamRemoved { name } => write!(f, "param {name} no longer used"),
            Reason::CmdChanged => write!(f, "command changed"),
            Reason::OutsChanged => write!(f, "outs changed"),
            Reason::DepChanged { path } => write!(f, "dep {path} changed"),
            Reason::DepAdded { path } => write!(f, "new dep {path}"),
            Reason::DepRemoved { path } => write!(f, "dep {path} removed"),
            Reason::DepMissing { path } => write!(f, "dep {path} missing"),
            Reason::OutMissing { path } => write!(f, "out {path} missing"),
            Reason::OutModified { path } => write!(f, "out {path} modified"),
            Reason::Upstream { stage } => write!(f, "upstream {stage} out of date"),
            Reason::DefinitionChanged => write!(f, "stage definition changed"),
        }
    }
}

/// Join reasons for one output line.
pub fn join(reasons: &[Reason]) -> String {
    reasons.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
}

/// The current state of a stage on disk.
#[derive(Debug, Clone)]
pub struct Current {
    /// The stage key, `None` while a dep is missing.
    pub key: Option<String>,
    /// Dep path → hash (`None` when missing).
    pub deps: BTreeMap<String, Option<String>>,
    /// Out path → tree (`None` when missing).
    pub outs: BTreeMap<String, Option<Tree>>,
    /// [`Hasher::tool_id`] of the running tool.
    pub tool: String,
}

/// blake3 over everything that determines a stage's result: its command after interpolation,
/// the tool version, its parameters, its output paths and the content hashes of its deps.
/// The stage name is not part of it, so a renamed stage can still restore from the run cache.
pub fn stage_key(stage: &Stage, tool: &str, deps: &BTreeMap<String, String>) -> String {
    let mut h = blake3::Hasher::new();
    let mut field = |tag: &str, parts: &[&str]| {
        h.update(tag.as_bytes());
        for p in parts {
            h.update(b"\0");
            h.update(p.as_bytes());
        }
        h.update(b"\n");
    };
    field("usplat4d-stage-key", &["1"]);
    field("cmd", &[&stage.cmd]);
    field("version", &[tool]);
    for (k, v) in &stage.params {
        field("param", &[k, v]);
    }
    let mut outs = stage.outs.clone();
    outs.sort();
    for o in &outs {
        field("out", &[o]);
    }
    for (p, hash) in deps {
        field("dep", &[p, hash]);
    }
    h.finalize().to_hex().to_string()
}

/// Hash the deps and outputs of `stage` as they are now.
pub fn current(p: &Pipeline, stage: &Stage, hasher: &mut Hasher) -> Result<Current, Error> {
    let mut deps = BTreeMap::new();
    for d in &stage.deps {
        deps.insert(d.clone(), hasher.hash(&p.path(d))?.map(|t| t.hash));
    }
    let mut outs = BTreeMap::new();
    for o in &stage.outs {
        outs.insert(o.clone(), hasher.hash(&p.path(o))?);
    }
    let complete: Option<BTreeMap<String, String>> =
        deps.iter().map(|(k, v)| v.clone().map(|v| (k.clone(), v))).collect();
    let tool = hasher.tool_id()?;
    let key = complete.map(|d| stage_key(stage, &tool, &d));
    Ok(Current { key, deps, outs, tool })
}

/// Why `stage` in state `cur` does not match its lock `entry`; empty when up to date.
pub fn explain(stage: &Stage, entry: Option<&LockEntry>, cur: &Current) -> Vec<Reason> {
    let mut r = Vec::new();
    let missing: Vec<Reason> = cur
        .deps
        .iter()
        .filter(|(_, h)| h.is_none())
        .map(|(p, _)| Reason::DepMissing { path: p.clone() })
        .collect();
    let Some(e) = entry else {
        r.push(Reason::NeverRun);
        r.extend(missing);
        return r;
    };
    if e.tool_version != cur.tool {
        r.push(Reason::ToolVersion { from: e.tool_version.clone(), to: cur.tool.clone() });
    }
    for (name, value) in &stage.params {
        match e.params.get(name) {
            None => r.push(Reason::ParamAdded { name: name.clone() }),
            Some(old) if old != value => r.push(Reason::ParamChanged {
                name: name.clone(),
                from: old.clone(),
                to: value.clone(),
            }),
            Some(_) => {}
        }
    }
    for name in e.params.keys().filter(|n| !stage.params.contains_key(*n)) {
        r.push(Reason::ParamRemoved { name: name.clone() });
    }
    if e.cmd != stage.cmd && r.iter().all(|x| !matches!(x, Reason::ParamChanged { .. })) {
        r.push(Reason::CmdChanged);
    }
    if !e.outs.keys().eq(cur.outs.keys()) {
        r.push(Reason::OutsChanged);
    }
    r.extend(missing);
    for (path, hash) in &cur.deps {
        match (hash, e.deps.get(path)) {
            (Some(_), None) => r.push(Reason::DepAdded { path: path.clone() }),
            (Some(h), Some(old)) if h != old => r.push(Reason::DepChanged { path: path.clone() }),
            _ => {}
        }
    }
    for path in e.deps.keys().filter(|p| !cur.deps.contains_key(*p)) {
        r.push(Reason::DepRemoved { path: path.clone() });
    }
    for (path, tree) in &cur.outs {
        match (tree, e.outs.get(path)) {
            (None, Some(_)) => r.push(Reason::OutMissing { path: path.clone() }),
            (Some(t), Some(old)) if &t.hash != old => {
                r.push(Reason::OutModified { path: path.clone() })
            }
            _ => {}
        }
    }
    if r.is_empty() && cur.key.as_deref() != Some(e.key.as_str()) {
        r.push(Reason::DefinitionChanged);
    }
    r
}
