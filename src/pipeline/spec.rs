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

/// A YAML map that keeps declaration order (duplicate keys are rejected by the parser).
#[derive(Debug)]
struct Ordered<T>(Vec<(String, T)>);

impl<T> Default for Ordered<T> {
    fn default() -> Self {
        Ordered(Vec::new())
    }
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for Ordered<T> {
    fn deserialize<D: de::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V<T>(std::marker::PhantomData<T>);
        impl<'de, T: Deserialize<'de>> Visitor<'de> for V<T> {
            type Value = Ordered<T>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a map")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<Self::Value, A::Error> {
                let mut out = Vec::new();
                while let Some((k, v)) = m.next_entry::<String, T>()? {
                    out.push((k, v));
                }
                Ok(Ordered(out))
            }
        }
        d.deserialize_map(V(std::marker::PhantomData))
    }
}

/// A parameter or foreach value: a scalar (kept as its canonical text) or a flat map of
/// scalars (foreach items only).
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Scalar(String),
    Map(BTreeMap<String, String>),
}

impl<'de> Deserialize<'de> for Value {
    fn deserialize<D: de::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Value;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a string, number, boolean or a map of them")
            }
            fn visit_bool<E: de::Error>(self, v: bool) -> Result<Value, E> {
                Ok(Value::Scalar(v.to_string()))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Value, E> {
                Ok(Value::Scalar(v.to_string()))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Value, E> {
                Ok(Value::Scalar(v.to_string()))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Value, E> {
                Ok(Value::Scalar(v.to_string()))
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Value, E> {
                Ok(Value::Scalar(v.to_string()))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<Value, A::Error> {
                let mut out = BTreeMap::new();
                while let Some((k, v)) = m.next_entry::<String, Value>()? {
                    match v {
                        Value::Scalar(s) => out.insert(k, s),
                        Value::Map(_) => {
                            return Err(de::Error::custom(format!(
                                "`{k}`: nested maps are not supported, use scalars"
                            )));
                        }
                    };
                }
                Ok(Value::Map(out))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, _s: A) -> Result<Value, A::Error> {
                Err(de::Error::invalid_type(de::Unexpected::Seq, &self))
            }
        }
        d.deserialize_any(V)
    }
}

/// The file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPipeline {
    #[serde(default)]
    params: Ordered<Value>,
    stages: Ordered<RawStage>,
}

/// A stage as written: either `cmd`/`deps`/`outs`, or `foreach` + `do`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStage {
    cmd: Option<String>,
    #[serde(default)]
    deps: Option<Vec<String>>,
    #[serde(default)]
    outs: Option<Vec<String>>,
    foreach: Option<Vec<Value>>,
    #[serde(rename = "do")]
    body: Option<RawBody>,
}

/// The body of a `foreach` stage.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBody {
    cmd: String,
    #[serde(default)]
    deps: Vec<String>,
    #[serde(default)]
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
        let raw: RawPipeline =
            serde_saphyr::from_str_with_options(text, yaml_options()).map_err(|e| Error::Yaml {
                file: file.into(),
                message: e.without_snippet().to_string(),
            })?;
        let invalid = |message: String| Error::Invalid { file: file.into(), message };
        let mut params = BTreeMap::new();
        for (name, v) in raw.params.0 {
            match v {
                Value::Scalar(s) => params.insert(name, s),
                Value::Map(_) => {
                    return Err(invalid(format!("parameter `{name}` must be a scalar, not a map")));
                }
            };
        }
        for set in sets {
            let (name, value) = parse_set(set).ok_or_else(|| Error::BadArgument {
                file: file.into(),
                message: format!("--set `{set}`: expected NAME=VALUE"),
            })?;
            if !params.contains_key(&name) {
                return Err(Error::BadArgument {
                    file: file.into(),
                    message: format!("--set `{set}`: no parameter `{name}` in the pipeline"),
                });
            }
            params.insert(name, value);
        }
        let base = match file.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut stages: Vec<Stage> = Vec::new();
        for (name, rs) in raw.stages.0 {
            if name.is_empty() || name.contains(['@', '/', ' ']) {
                return Err(invalid(format!(
                    "stage name `{name}` must be non-empty without `@`, `/` or spaces"
                )));
            }
            match (rs.foreach, rs.body) {
                (Some(items), Some(body)) => {
                    if rs.cmd.is_some() || rs.deps.is_some() || rs.outs.is_some() {
                        return Err(invalid(format!(
                            "stage `{name}`: a foreach stage puts cmd, deps and outs under `do`"
                        )));
                    }
                    for (i, item) in items.iter().enumerate() {
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
                return Err(invalid(format!("two stages are named `{}`", s.name)));
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

/// Split `NAME=VALUE`; the value is canonicalised like a YAML scalar (`0.50` → `0.5`) so
/// that setting a parameter to the value written in the file gives the same stage key.
fn parse_set(set: &str) -> Option<(String, String)> {
    let (name, value) = set.split_once('=')?;
    let name = name.trim();
    if name.is_empty() {
        return None;
    }
    let canonical = match serde_saphyr::from_str_with_options::<Value>(value, yaml_options()) {
        Ok(Value::Scalar(s)) if !value.trim().is_empty() => s,
        _ => value.to_string(),
    };
    Some((name.to_string(), canonical))
}

/// Interpolation context of one (expanded) stage.
struct Interp<'a> {
    file: &'a Path,
    stage: &'a str,
    params: &'a BTreeMap<String, String>,
    item: Option<&'a Value>,
}

impl Interp<'_> {
    fn stage(&self, cmd: &str, deps: &[String], outs: &[String]) -> Result<Stage, Error> {
        let mut used = BTreeMap::new();
        let cmd = self.interpolate(cmd, &mut used)?;
        let mut argv = shlex::split(&cmd).ok_or_else(|| Error::Invalid {
            file: self.file.into(),
            message: format!("stage `{}`: unbalanced quotes in cmd `{cmd}`", self.stage),
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
            stage: self.stage.to_string(),
            name: name.to_string(),
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
        let value = self.params.get(name).ok_or_else(unknown)?;
        used.insert(name.to_string(), value.clone());
        Ok(value.clone())
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
