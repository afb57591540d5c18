//! The pipeline file: its YAML schema, `${param}` interpolation and `foreach` expansion.
//!
//! [`Pipeline::load`] parses the file (unknown keys are errors, with line and column), applies
//! `--set` overrides, expands every `foreach` stage into one stage per item named `name@item`,
//! interpolates `${param}`, `${item}` and `${item.key}` in `cmd`, `deps` and `outs`, splits
//! `cmd` into argv with shell-like quoting and normalises paths relative to the file's
//! directory. The result is a flat list of [`Stage`]s in declaration order; the graph between
//! them is built by [`super::dag`].

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Component, Path, PathBuf};

use serde::Deserialize;
use serde::de::{self, MapAccess, SeqAccess, Visitor};
use serde_saphyr::Spanned;

use super::Error;

/// One executable stage after expansion and interpolation.
#[derive(Debug, Clone, PartialEq)]
pub struct Stage {
    /// Unique name (`name` or `name@item`).
    pub name: String,
    /// The command after interpolation (a usplat4d subcommand line).
    pub cmd: String,
    /// `cmd` split into arguments, without a leading `usplat4d`.
    pub argv: Vec<String>,
    /// Input paths, normalised, relative to the pipeline directory (absolute ones kept).
    pub deps: Vec<String>,
    /// Output paths (files or directories), normalised like `deps`.
    pub outs: Vec<String>,
    /// The parameters the stage uses (referenced in cmd, deps or outs) and their values.
    pub params: BTreeMap<String, String>,
}

/// A loaded pipeline file.
#[derive(Debug, Clone)]
pub struct Pipeline {
    /// The YAML file.
    pub file: PathBuf,
    /// Its directory: the base of every relative path and the working directory of stages.
    pub base: PathBuf,
    /// The stages in declaration order (foreach items in list order).
    pub stages: Vec<Stage>,
}

/// A foreach item or list-parameter element: a scalar (kept as its canonical text) or a
/// flat map of scalars.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Scalar(String),
    Map(BTreeMap<String, String>),
}

/// A parameter: a scalar, interpolated as text, or a list of items that a stage iterates
/// with `foreach: ${name}` (a list of sequence directories, say).
#[derive(Debug, Clone, PartialEq)]
enum Param {
    Scalar(String),
    List(Vec<Value>),
}

/// What a `foreach` iterates: its own list, or a list parameter named as `${name}`.
#[derive(Debug)]
enum Foreach {
    Items(Vec<Value>),
    Param(String),
}

/// A YAML node as parsed, with its location. The schema is checked by hand on this tree
/// (not by serde), so that every error names its key (`stage `a`: `deps``), what was
/// expected and what was found, with the line and column.
#[derive(Debug)]
enum Node {
    Null,
    /// A scalar as its canonical text (`0.50` → `0.5`).
    Scalar(String),
    Seq(Vec<Spanned<Node>>),
    /// Keys in declaration order (duplicate keys are rejected by the parser).
    Map(Vec<(String, Spanned<Node>)>),
}

impl<'de> Deserialize<'de> for Node {
    fn deserialize<D: de::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Node;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a YAML value")
            }
            fn visit_bool<E: de::Error>(self, v: bool) -> Result<Node, E> {
                Ok(Node::Scalar(v.to_string()))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Node, E> {
                Ok(Node::Scalar(v.to_string()))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Node, E> {
                Ok(Node::Scalar(v.to_string()))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Node, E> {
                Ok(Node::Scalar(v.to_string()))
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Node, E> {
                Ok(Node::Scalar(v.to_string()))
            }
            fn visit_unit<E: de::Error>(self) -> Result<Node, E> {
                Ok(Node::Null)
            }
            fn visit_none<E: de::Error>(self) -> Result<Node, E> {
                Ok(Node::Null)
            }
            fn visit_some<D: de::Deserializer<'de>>(self, d: D) -> Result<Node, D::Error> {
                Node::deserialize(d)
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut s: A) -> Result<Node, A::Error> {
                let mut out = Vec::new();
                while let Some(v) = s.next_element()? {
                    out.push(v);
                }
                Ok(Node::Seq(out))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<Node, A::Error> {
                let mut out = Vec::new();
                while let Some((k, v)) = m.next_entry::<String, Spanned<Node>>()? {
                    out.push((k, v));
                }
                Ok(Node::Map(out))
            }
        }
        d.deserialize_any(V)
    }
}

/// User text echoed in a message, cut to its first 60 characters (a pasted value may be
/// megabytes long).
pub fn shown(s: &str) -> std::borrow::Cow<'_, str> {
    const MAX: usize = 60;
    match s.char_indices().nth(MAX) {
        None => s.into(),
        Some((end, _)) => format!("{}... ({} characters)", &s[..end], s.chars().count()).into(),
    }
}

/// Schema checks on the parsed tree; errors carry the node's line and column.
struct Schema<'a> {
    file: &'a Path,
}

type Entries = [(String, Spanned<Node>)];

impl Schema<'_> {
    fn error(&self, at: &Spanned<Node>, message: String) -> Error {
        let (line, column) = (at.referenced.line(), at.referenced.column());
        Error::Yaml {
            file: self.file.into(),
            message: format!("line {line} column {column}: {message}"),
        }
    }

    /// `key: expected <what>, found <the node>`.
    fn expected(&self, at: &Spanned<Node>, key: &str, what: &str) -> Error {
        let found = match &at.value {
            Node::Null => "nothing".to_string(),
            Node::Scalar(s) => format!("`{}`", shown(s)),
            Node::Seq(_) => "a list".into(),
            Node::Map(_) => "a map".into(),
        };
        self.error(at, format!("{key}: expected {what}, found {found}"))
    }

    fn map<'n>(&self, at: &'n Spanned<Node>, key: &str, what: &str) -> Result<&'n Entries, Error> {
        match &at.value {
            Node::Map(m) => Ok(m),
            _ => Err(self.expected(at, key, what)),
        }
    }

    /// A key's value, `None` when absent or null.
    fn string(
        &self,
        at: Option<&Spanned<Node>>,
        key: &str,
        what: &str,
    ) -> Result<Option<String>, Error> {
        match at.map(|n| (n, &n.value)) {
            None | Some((_, Node::Null)) => Ok(None),
            Some((_, Node::Scalar(s))) => Ok(Some(s.clone())),
            Some((n, _)) => Err(self.expected(n, key, what)),
        }
    }

    fn strings(&self, at: Option<&Spanned<Node>>, key: &str) -> Result<Option<Vec<String>>, Error> {
        let what = "a list of paths";
        match at.map(|n| (n, &n.value)) {
            None | Some((_, Node::Null)) => Ok(None),
            Some((_, Node::Seq(items))) => items
                .iter()
                .map(|i| match &i.value {
                    Node::Scalar(s) => Ok(s.clone()),
                    _ => Err(self.expected(i, &format!("{key} item"), "a path")),
                })
                .collect::<Result<_, _>>()
                .map(Some),
            Some((n, _)) => Err(self.expected(n, key, what)),
        }
    }

    /// A scalar or a flat map of scalars.
    fn value(&self, at: &Spanned<Node>, key: &str) -> Result<Value, Error> {
        let what = "a string, number, boolean or a map of them";
        match &at.value {
            Node::Scalar(s) => Ok(Value::Scalar(s.clone())),
            Node::Map(m) => m
                .iter()
                .map(|(k, v)| match &v.value {
                    Node::Scalar(s) => Ok((k.clone(), s.clone())),
                    _ => Err(self.expected(
                        v,
                        &format!("{key}: `{k}`"),
                        "a scalar (nested values are not supported)",
                    )),
                })
                .collect::<Result<_, _>>()
                .map(Value::Map),
            _ => Err(self.expected(at, key, what)),
        }
    }

    /// The items of a foreach list or list parameter: scalars or flat maps of scalars.
    fn items(&self, items: &[Spanned<Node>], key: &str) -> Result<Vec<Value>, Error> {
        items.iter().enumerate().map(|(i, item)| self.value(item, &format!("{key} {i}"))).collect()
    }

    /// Reject keys outside `allowed`; return the value of each allowed key.
    fn keys<'n, const K: usize>(
        &self,
        entries: &'n Entries,
        context: &str,
        allowed: [&str; K],
    ) -> Result<[Option<&'n Spanned<Node>>; K], Error> {
        let mut out = [None; K];
        for (k, v) in entries {
            match allowed.iter().position(|a| a == k) {
                Some(i) => out[i] = Some(v),
                None => {
                    let list: Vec<String> = allowed.iter().map(|a| format!("`{a}`")).collect();
                    return Err(self.error(
                        v,
                        format!(
                            "{context}unknown key `{}` (expected {})",
                            shown(k),
                            list.join(", ")
                        ),
                    ));
                }
            }
        }
        Ok(out)
    }

    fn pipeline(&self, root: &Spanned<Node>) -> Result<RawPipeline, Error> {
        let top = "a map with `stages` and optionally `params`";
        let entries = self.map(root, "the file", top)?;
        let [params, stages] = self.keys(entries, "", ["params", "stages"])?;
        let mut out = RawPipeline { params: Vec::new(), stages: Vec::new() };
        if let Some(params) = params.filter(|p| !matches!(p.value, Node::Null)) {
            for (name, v) in self.map(params, "`params`", "a map of parameter names to values")? {
                let key = format!("parameter `{}`", shown(name));
                let param = match &v.value {
                    Node::Seq(items) => Param::List(self.items(items, &format!("{key} item"))?),
                    Node::Scalar(s) => Param::Scalar(s.clone()),
                    _ => {
                        return Err(self.expected(
                            v,
                            &key,
                            "a string, number, boolean or a list of items",
                        ));
                    }
                };
                out.params.push((name.clone(), param));
            }
        }
        let Some(stages) = stages else {
            return Err(self.error(root, format!("missing `stages`: expected {top}")));
        };
        for (name, st) in self.map(stages, "`stages`", "a map of stage names to stages")? {
            let ctx = format!("stage `{}`: ", shown(name));
            let what = "a map with `cmd` (or `foreach` and `do`)";
            let entries = self.map(st, &format!("stage `{}`", shown(name)), what)?;
            let [cmd, deps, outs, foreach, body] =
                self.keys(entries, &ctx, ["cmd", "deps", "outs", "foreach", "do"])?;
            let key = |k: &str| format!("{ctx}`{k}`");
            let foreach = match foreach.filter(|f| !matches!(f.value, Node::Null)) {
                None => None,
                Some(f) => match (&f.value, scalar_list_reference(&f.value)) {
                    (Node::Seq(items), _) => {
                        Some(Foreach::Items(self.items(items, &format!("{ctx}`foreach` item"))?))
                    }
                    (_, Some(name)) => Some(Foreach::Param(name.to_string())),
                    _ => {
                        return Err(self.expected(
                            f,
                            &key("foreach"),
                            "a list of items or `${name}` of a list parameter",
                        ));
                    }
                },
            };
            let body = match body.filter(|b| !matches!(b.value, Node::Null)) {
                None => None,
                Some(b) => {
                    let entries = self.map(b, &key("do"), "a map with `cmd`, `deps` and `outs`")?;
                    let [cmd, deps, outs] =
                        self.keys(entries, &format!("{ctx}`do`: "), ["cmd", "deps", "outs"])?;
                    let cmd = self.string(cmd, &key("do.cmd"), "a string (the command line)")?;
                    Some(RawBody {
                        cmd: cmd
                            .ok_or_else(|| self.error(b, format!("{ctx}`do` needs a `cmd`")))?,
                        deps: self.strings(deps, &key("do.deps"))?.unwrap_or_default(),
                        outs: self.strings(outs, &key("do.outs"))?.unwrap_or_default(),
                    })
                }
            };
            out.stages.push((
                name.clone(),
                RawStage {
                    cmd: self.string(cmd, &key("cmd"), "a string (the command line)")?,
                    deps: self.strings(deps, &key("deps"))?,
                    outs: self.strings(outs, &key("outs"))?,
                    foreach,
                    body,
                },
            ));
        }
        Ok(out)
    }
}

/// The file as written.
#[derive(Debug)]
struct RawPipeline {
    params: Vec<(String, Param)>,
    stages: Vec<(String, RawStage)>,
}

/// A stage as written: either `cmd`/`deps`/`outs`, or `foreach` + `do`.
#[derive(Debug)]
struct RawStage {
    cmd: Option<String>,
    deps: Option<Vec<String>>,
    outs: Option<Vec<String>>,
    foreach: Option<Foreach>,
    body: Option<RawBody>,
}

/// The body of a `foreach` stage.
#[derive(Debug)]
struct RawBody {
    cmd: String,
    deps: Vec<String>,
    outs: Vec<String>,
}

impl Pipeline {
    /// Read and expand `file`, with `sets` (`name=value`) overriding parameters. The base
    /// directory is made absolute, so hashes cached per path do not depend on the directory
    /// `usplat4d` was started from.
    pub fn load(file: &Path, sets: &[String]) -> Result<Pipeline, Error> {
        let text = std::fs::read_to_string(file).map_err(Error::io(file))?;
        let mut p = Pipeline::parse(file, &text, sets)?;
        p.base = std::path::absolute(&p.base).map_err(Error::io(&p.base))?;
        Ok(p)
    }

    /// Parse `text` as the content of `file` (which gives the base directory).
    pub fn parse(file: &Path, text: &str, sets: &[String]) -> Result<Pipeline, Error> {
        let empty = |message: &str| Error::Yaml {
            file: file.into(),
            message: format!("{message}: expected a map with `stages` and optionally `params`"),
        };
        if text.lines().all(|l| {
            let l = l.trim();
            l.is_empty() || l.starts_with('#') || l == "---" || l == "..."
        }) {
            return Err(empty("the file is empty"));
        }
        let root: Spanned<Node> = serde_saphyr::from_str_with_options(text, yaml_options())
            .map_err(|e| {
                // the parser echoes the offending scalar, which may be megabytes long
                let text = e.without_snippet().to_string();
                let words: Vec<_> = text.split(' ').map(shown).collect();
                Error::Yaml { file: file.into(), message: words.join(" ") }
            })?;
        if matches!(root.value, Node::Null) {
            return Err(empty("the file holds no value"));
        }
        let raw = Schema { file }.pipeline(&root)?;
        let invalid = |message: String| Error::Invalid { file: file.into(), message };
        let mut params: BTreeMap<String, Param> = raw.params.into_iter().collect();
        for set in sets {
            let (name, value) = parse_set(set).ok_or_else(|| Error::BadArgument {
                file: file.into(),
                message: format!("--set `{}`: expected NAME=VALUE", shown(set)),
            })?;
            let bad = |message: String| Error::BadArgument {
                file: file.into(),
                message: format!("--set `{}`: {message}", shown(set)),
            };
            let value = match params.get(&name) {
                None => {
                    return Err(bad(format!("no parameter `{}` in the pipeline", shown(&name))));
                }
                Some(Param::Scalar(_)) => Param::Scalar(value),
                Some(Param::List(_)) => Param::List(parse_list(&value).ok_or_else(|| {
                    bad(format!(
                        "`{name}` is a list parameter: expected a YAML list such as [a, b]"
                    ))
                })?),
            };
            params.insert(name, value);
        }
        let base = match file.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut stages: Vec<Stage> = Vec::new();
        for (name, rs) in raw.stages {
            if name.is_empty() || name.contains(['@', '/', ' ']) {
                return Err(invalid(format!(
                    "stage name `{}` must be non-empty without `@`, `/` or spaces",
                    shown(&name)
                )));
            }
            match (rs.foreach, rs.body) {
                (Some(foreach), Some(body)) => {
                    if rs.cmd.is_some() || rs.deps.is_some() || rs.outs.is_some() {
                        return Err(invalid(format!(
                            "stage `{name}`: a foreach stage puts cmd, deps and outs under `do`"
                        )));
                    }
                    let items = match &foreach {
                        Foreach::Items(items) => items,
                        Foreach::Param(p) => match params.get(p) {
                            Some(Param::List(items)) => items,
                            Some(Param::Scalar(_)) => {
                                return Err(invalid(format!(
                                    "stage `{name}`: `foreach: ${{{p}}}` names a scalar parameter, not a list"
                                )));
                            }
                            None => {
                                return Err(Error::UnknownParam {
                                    file: file.into(),
                                    stage: name.clone(),
                                    name: shown(p).into_owned(),
                                });
                            }
                        },
                    };
                    for (i, item) in items.iter().enumerate() {
                        // `${param}` inside an item's values (`dir: ${out}/seq`)
                        let outer = Interp { file, stage: &name, params: &params, item: None };
                        let text = |v: &String| outer.interpolate(v, &mut BTreeMap::new());
                        let item = &match item {
                            Value::Scalar(s) => Value::Scalar(text(s)?),
                            Value::Map(m) => Value::Map(
                                m.iter()
                                    .map(|(k, v)| Ok((k.clone(), text(v)?)))
                                    .collect::<Result<_, Error>>()?,
                            ),
                        };
                        let stage_name = match item {
                            Value::Scalar(s) => format!("{name}@{s}"),
                            Value::Map(_) => format!("{name}@{i}"),
                        };
                        let ctx =
                            Interp { file, stage: &stage_name, params: &params, item: Some(item) };
                        stages.push(ctx.stage(&body.cmd, &body.deps, &body.outs)?);
                    }
                }
                (None, None) => {
                    let cmd =
                        rs.cmd.ok_or_else(|| invalid(format!("stage `{name}`: missing `cmd`")))?;
                    let ctx = Interp { file, stage: &name, params: &params, item: None };
                    stages.push(ctx.stage(
                        &cmd,
                        &rs.deps.unwrap_or_default(),
                        &rs.outs.unwrap_or_default(),
                    )?);
                }
                (Some(_), None) => {
                    return Err(invalid(format!("stage `{name}`: `foreach` needs a `do`")));
                }
                (None, Some(_)) => {
                    return Err(invalid(format!("stage `{name}`: `do` needs a `foreach`")));
                }
            }
        }
        let mut seen = std::collections::HashSet::new();
        for s in &stages {
            if !seen.insert(s.name.as_str()) {
                return Err(invalid(format!("two stages are named `{}`", shown(&s.name))));
            }
        }
        Ok(Pipeline { file: file.into(), base, stages })
    }

    /// The absolute-or-base-relative filesystem path of a pipeline path.
    pub fn path(&self, p: &str) -> PathBuf {
        self.base.join(p)
    }

    /// The lock file next to the pipeline file: `FILE.lock`.
    pub fn lock_path(&self) -> PathBuf {
        self.file.with_extension("lock")
    }

    /// The runner's state directory next to the pipeline file.
    pub fn state_dir(&self) -> PathBuf {
        self.base.join(".usplat4d")
    }
}

/// Parser options: one-line errors with line and column, YAML 1.2 booleans only (a scene
/// named `y` or `no` stays a string) and numbers with leading zeros kept as strings (`007`).
fn yaml_options() -> serde_saphyr::Options {
    serde_saphyr::options! { with_snippet: false, strict_booleans: true, leading_zero_numbers_as_strings: true }
}

/// The list parameter a scalar node names as `${name}`, if it is one.
fn scalar_list_reference(node: &Node) -> Option<&str> {
    match node {
        Node::Scalar(s) => list_reference(s),
        _ => None,
    }
}

/// `${name}` alone: a foreach naming a list parameter.
fn list_reference(s: &str) -> Option<&str> {
    let name = s.trim().strip_prefix("${")?.strip_suffix('}')?.trim();
    (!name.is_empty() && !name.contains(['$', '{', '}'])).then_some(name)
}

/// The value of `--set LIST=[a, b]`: a YAML list of scalars or flat maps of scalars.
fn parse_list(value: &str) -> Option<Vec<Value>> {
    match serde_saphyr::from_str_with_options::<Node>(value, yaml_options()).ok()? {
        Node::Seq(items) => items
            .into_iter()
            .map(|i| match i.value {
                Node::Scalar(s) => Some(Value::Scalar(s)),
                Node::Map(m) => m
                    .into_iter()
                    .map(|(k, v)| match v.value {
                        Node::Scalar(s) => Some((k, s)),
                        _ => None,
                    })
                    .collect::<Option<_>>()
                    .map(Value::Map),
                _ => None,
            })
            .collect(),
        _ => None,
    }
}

/// Split `NAME=VALUE`; the value is canonicalised like a YAML scalar (`0.50` → `0.5`) so
/// that setting a parameter to the value written in the file gives the same stage key.
fn parse_set(set: &str) -> Option<(String, String)> {
    let (name, value) = set.split_once('=')?;
    let name = name.trim();
    if name.is_empty() {
        return None;
    }
    let canonical = match serde_saphyr::from_str_with_options::<Node>(value, yaml_options()) {
        Ok(Node::Scalar(s)) if !value.trim().is_empty() => s,
        _ => value.to_string(),
    };
    Some((name.to_string(), canonical))
}

/// Interpolation context of one (expanded) stage.
struct Interp<'a> {
    file: &'a Path,
    stage: &'a str,
    params: &'a BTreeMap<String, Param>,
    item: Option<&'a Value>,
}

impl Interp<'_> {
    fn stage(&self, cmd: &str, deps: &[String], outs: &[String]) -> Result<Stage, Error> {
        let mut used = BTreeMap::new();
        let cmd = self.interpolate(cmd, &mut used)?;
        let mut argv = shlex::split(&cmd).ok_or_else(|| Error::Invalid {
            file: self.file.into(),
            message: format!(
                "stage `{}`: unbalanced quotes in cmd `{}`",
                shown(self.stage),
                shown(&cmd)
            ),
        })?;
        if argv.first().is_some_and(|a| a == "usplat4d") {
            argv.remove(0);
        }
        if argv.is_empty() {
            return Err(Error::Invalid {
                file: self.file.into(),
                message: format!("stage `{}`: empty cmd", self.stage),
            });
        }
        let paths = |list: &[String], used: &mut BTreeMap<String, String>| {
            list.iter()
                .map(|p| Ok(normalize(&self.interpolate(p, used)?)))
                .collect::<Result<Vec<_>, Error>>()
        };
        let deps = paths(deps, &mut used)?;
        let outs = paths(outs, &mut used)?;
        Ok(Stage { name: self.stage.to_string(), cmd, argv, deps, outs, params: used })
    }

    /// Replace every `${name}`, recording the parameters used.
    fn interpolate(&self, s: &str, used: &mut BTreeMap<String, String>) -> Result<String, Error> {
        let mut out = String::with_capacity(s.len());
        let mut rest = s;
        while let Some(start) = rest.find("${") {
            out.push_str(&rest[..start]);
            let after = &rest[start + 2..];
            let end = after.find('}').ok_or_else(|| Error::Invalid {
                file: self.file.into(),
                message: format!("stage `{}`: unclosed `${{` in `{s}`", self.stage),
            })?;
            let name = after[..end].trim();
            out.push_str(&self.lookup(name, used)?);
            rest = &after[end + 1..];
        }
        out.push_str(rest);
        Ok(out)
    }

    fn lookup(&self, name: &str, used: &mut BTreeMap<String, String>) -> Result<String, Error> {
        let unknown = || Error::UnknownParam {
            file: self.file.into(),
            stage: shown(self.stage).into_owned(),
            name: shown(name).into_owned(),
        };
        if let Some(item) = self.item {
            match (name.split_once('.'), item) {
                (None, Value::Scalar(s)) if name == "item" => return Ok(s.clone()),
                (Some(("item", key)), Value::Map(m)) => {
                    return m.get(key).cloned().ok_or_else(unknown);
                }
                _ if name == "item" || name.starts_with("item.") => return Err(unknown()),
                _ => {}
            }
        }
        match self.params.get(name).ok_or_else(unknown)? {
            Param::Scalar(value) => {
                used.insert(name.to_string(), value.clone());
                Ok(value.clone())
            }
            Param::List(_) => Err(Error::Invalid {
                file: self.file.into(),
                message: format!(
                    "stage `{}`: parameter `{name}` is a list: iterate it with `foreach: ${{{name}}}`",
                    shown(self.stage)
                ),
            }),
        }
    }
}

/// Lexically normalise a path: drop `.`, fold `a/..`, use `/`; absolute paths stay absolute.
pub fn normalize(p: &str) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut prefix = String::new();
    for c in Path::new(p).components() {
        match c {
            Component::Prefix(x) => prefix = x.as_os_str().to_string_lossy().into_owned(),
            Component::RootDir => prefix.push('/'),
            Component::CurDir => {}
            Component::ParentDir => {
                if parts.last().is_some_and(|l| l != "..") {
                    parts.pop();
                } else if prefix.is_empty() {
                    parts.push("..".into());
                }
            }
            Component::Normal(s) => parts.push(s.to_string_lossy().into_owned()),
        }
    }
    let joined = parts.join("/");
    if prefix.is_empty() && joined.is_empty() { ".".into() } else { format!("{prefix}{joined}") }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Pipeline, Error> {
        Pipeline::parse(Path::new("dir/p.yaml"), text, &[])
    }

    #[test]
    fn foreach_iterates_a_list_parameter_that_set_replaces() {
        let text = "params:\n  seqs: [a, b]\n  n: 2\n  out: o\n  dirs: ['${out}/d']\nstages:\n  imp:\n    foreach: ${seqs}\n    do:\n      cmd: synth --frames ${n} --out 'out/${item}'\n      outs: ['out/${item}']\n  use:\n    foreach: ${dirs}\n    do: {cmd: 'x ${item}'}\n";
        let names = |p: Pipeline| p.stages.iter().map(|s| s.name.clone()).collect::<Vec<_>>();
        assert_eq!(names(parse(text).unwrap()), ["imp@a", "imp@b", "use@o/d"]);
        assert_eq!(parse(text).unwrap().stages[2].argv, ["x", "o/d"]);
        let set = |v: &str| Pipeline::parse(Path::new("dir/p.yaml"), text, &[v.to_string()]);
        assert_eq!(names(set("seqs=[x, y, z]").unwrap()), ["imp@x", "imp@y", "imp@z", "use@o/d"]);
        let e = set("seqs=x").unwrap_err().to_string();
        assert!(e.contains("`seqs` is a list parameter"), "{e}");
        let e = parse("params:\n  seqs: [a]\nstages:\n  s: {cmd: 'x ${seqs}'}\n").unwrap_err();
        assert!(e.to_string().contains("parameter `seqs` is a list"), "{e}");
        let e = parse("params:\n  n: 1\nstages:\n  s:\n    foreach: ${n}\n    do: {cmd: x}\n")
            .unwrap_err();
        assert!(e.to_string().contains("names a scalar parameter"), "{e}");
        let e = parse("stages:\n  s:\n    foreach: ${nope}\n    do: {cmd: x}\n").unwrap_err();
        assert!(e.to_string().contains("nope"), "{e}");
        let e = parse("stages:\n  s:\n    foreach: abc\n    do: {cmd: x}\n").unwrap_err();
        assert!(e.to_string().contains("a list of items or `${name}`"), "{e}");
    }

    #[test]
    fn interpolates_params_and_foreach_items() {
        let p = parse(
            "params:\n  n: 3\n  t: 0.50\n  name: a b\nstages:\n  gen:\n    foreach: [x, y, 007]\n    do:\n      cmd: synth --frames ${n} --out 'out/${item}' --label '${name}'\n      outs: ['out/${item}']\n  use:\n    foreach:\n      - {scene: x, k: 1}\n    do:\n      cmd: inspect out/${item.scene}/../${item.scene}/f --t ${t}\n      deps: ['./out/${item.scene}/f']\n",
        )
        .unwrap();
        let names: Vec<_> = p.stages.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["gen@x", "gen@y", "gen@007", "use@0"]);
        let g = &p.stages[1];
        assert_eq!(g.argv, ["synth", "--frames", "3", "--out", "out/y", "--label", "a b"]);
        assert_eq!(g.outs, ["out/y"]);
        assert_eq!(g.params.keys().collect::<Vec<_>>(), ["n", "name"]);
        let u = &p.stages[3];
        assert_eq!(u.cmd, "inspect out/x/../x/f --t 0.5");
        assert_eq!(u.deps, ["out/x/f"]);
        assert_eq!(p.base, Path::new("dir"));
        assert_eq!(p.lock_path(), Path::new("dir/p.lock"));
    }

    #[test]
    fn set_overrides_a_param_canonically() {
        let text = "params: {t: 0.5}\nstages:\n  a: {cmd: 'x --t ${t}'}\n";
        let p = Pipeline::parse(Path::new("p.yaml"), text, &["t=0.50".into()]).unwrap();
        assert_eq!(p.stages[0].cmd, "x --t 0.5");
        let p = Pipeline::parse(Path::new("p.yaml"), text, &["t=abc".into()]).unwrap();
        assert_eq!(p.stages[0].params["t"], "abc");
        let e = Pipeline::parse(Path::new("p.yaml"), text, &["u=1".into()]).unwrap_err();
        assert_eq!(e.to_string(), "p.yaml: --set `u=1`: no parameter `u` in the pipeline");
    }

    #[test]
    fn errors_name_the_file_and_key() {
        let e = parse("stages:\n  a:\n    cmd: x\n    dep: [y]\n").unwrap_err();
        assert!(matches!(e, Error::Yaml { .. }));
        let msg = e.to_string();
        assert!(
            msg.starts_with("dir/p.yaml: ") && msg.contains("dep") && msg.contains("line 4"),
            "{msg}"
        );
        let e = parse("stages:\n  a: {cmd: 'x ${nope}'}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: stage `a`: unknown parameter `${nope}`");
        let e = parse("stages:\n  a: {foreach: [1], do: {cmd: 'x ${item.k}'}}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: stage `a@1`: unknown parameter `${item.k}`");
        let e = parse("stages:\n  a: {cmd: \"x 'y\"}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: stage `a`: unbalanced quotes in cmd `x 'y`");
        let e = parse("stages:\n  a: {foreach: [1]}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: stage `a`: `foreach` needs a `do`");
        let e = parse("stages:\n  a: {cmd: x, foreach: [1], do: {cmd: y}}\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "dir/p.yaml: stage `a`: a foreach stage puts cmd, deps and outs under `do`"
        );
        let e = parse("stages:\n  a: {deps: [x]}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: stage `a`: missing `cmd`");
        let e = parse("stages:\n  a: {foreach: [1, 1], do: {cmd: y}}\n").unwrap_err();
        assert_eq!(e.to_string(), "dir/p.yaml: two stages are named `a@1`");
        let e = parse("stages:\n  a: {cmd: x: y}\n").unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
    }

    /// Type errors name the key, what was expected and what was found, with the location.
    #[test]
    fn type_errors_name_the_key_and_what_was_expected() {
        let cases = [
            (
                "params:\n  seed: {a: 1}\nstages:\n  a: {cmd: x}\n",
                "dir/p.yaml: line 2 column 9: parameter `seed`: expected a string, number, boolean or a list of items, found a map",
            ),
            (
                "stages:\n  a:\n    cmd: [x, y]\n",
                "dir/p.yaml: line 3 column 10: stage `a`: `cmd`: expected a string (the command line), found a list",
            ),
            (
                "stages:\n  - a\n",
                "dir/p.yaml: line 2 column 3: `stages`: expected a map of stage names to stages, found a list",
            ),
            (
                "stages:\n  a:\n    cmd: x\n    deps: y\n",
                "dir/p.yaml: line 4 column 11: stage `a`: `deps`: expected a list of paths, found `y`",
            ),
            (
                "stages:\n  a:\n    cmd: x\n    dep: [y]\n",
                "dir/p.yaml: line 4 column 10: stage `a`: unknown key `dep` (expected `cmd`, `deps`, `outs`, `foreach`, `do`)",
            ),
            (
                "",
                "dir/p.yaml: the file is empty: expected a map with `stages` and optionally `params`",
            ),
            (
                "# nothing yet\n\n",
                "dir/p.yaml: the file is empty: expected a map with `stages` and optionally `params`",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(parse(text).unwrap_err().to_string(), want, "{text:?}");
        }
    }

    /// A huge value is cut when echoed: the message stays short and says how long it was.
    #[test]
    fn echoed_values_are_truncated() {
        let huge = "7".repeat(2_000_000);
        for text in [
            format!("stages: {huge}\n"),
            format!("stages:\n  a: {{cmd: x, deps: {huge}}}\n"),
            format!("params: {{n: '{huge}'}}\nstages:\n  a: {{cmd: \"x ${{n}} '\"}}\n"),
            format!("stages:\n  a: {{foreach: ['{huge}', '{huge}'], do: {{cmd: x}}}}\n"),
        ] {
            let msg = parse(&text).unwrap_err().to_string();
            assert!(msg.len() < 300, "{} characters: {}", msg.len(), &msg[..300]);
            assert!(msg.contains("7777777777... (200000"), "{msg}");
        }
    }

    #[test]
    fn the_readme_example_parses() {
        let readme = include_str!("../../pipelines/README.md");
        let start = readme.find("```yaml\n").unwrap() + 8;
        let text = &readme[start..start + readme[start..].find("```").unwrap()];
        let p = Pipeline::parse(Path::new("pipelines/example.yaml"), text, &[]).unwrap();
        let names: Vec<_> = p.stages.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["synth@fox", "synth@man", "check"]);
        assert_eq!(p.stages[1].outs, ["scenes/man"]);
        assert_eq!(p.stages[1].argv[..3], ["synth", "--gltf", "data/man.glb"]);
    }

    #[test]
    fn normalizes_paths() {
        assert_eq!(normalize("./a/b/../c/"), "a/c");
        assert_eq!(normalize("../x/./y"), "../x/y");
        assert_eq!(normalize("/abs/./p"), "/abs/p");
        assert_eq!(normalize("a/.."), ".");
    }
}
