//! The crate's dependency rule (stated in `src/lib.rs`), checked on the source: every
//! `crate::` path and every `super::` path of every file's non-test code is resolved to the
//! file that defines it, then
//! - each top-level module references only the modules its layer allows, and
//! - no two files reference each other (a folder's `mod.rs` and the files directly inside it
//!   may share items, e.g. the folder's `Error` type).
//!
//! Test code (`#[cfg(test)]` modules and files) may use anything.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Which top-level modules each top-level module may reference (besides itself and the
/// crate root's items such as `VERSION`).
fn allowed(top: &str) -> &'static [&'static str] {
    const BASE: &[&str] = &["util", "context"];
    match top {
        "util" | "context" => &["util"],
        "math" => BASE,
        "formats" => &["util", "context", "math"],
        "render" => &["util", "math"],
        "tables" => &["util", "math", "formats"],
        "model" | "scene" => &["util", "context", "math", "formats", "tables", "render", "scene"],
        // Test-only: round trips of the tables through model and scene directories.
        "table_tests" => {
            &["util", "context", "math", "formats", "tables", "render", "model", "scene"]
        }
        "metrics" => &["util", "context", "math", "formats", "tables", "render", "model", "scene"],
        "datasets" | "stages" | "import" => &[
            "util", "context", "math", "formats", "tables", "render", "model", "scene", "metrics",
            "datasets", "stages", "import",
        ],
        "tools" => &[
            "util", "context", "math", "formats", "tables", "render", "model", "scene", "metrics",
            "datasets", "stages", "import",
        ],
        "pipeline" => BASE,
        "cli" => &[
            "util", "context", "math", "formats", "tables", "render", "model", "scene", "metrics",
            "datasets", "stages", "import", "tools", "pipeline",
        ],
        other => panic!("top-level module `{other}` has no layer: add it to tests/layout.rs"),
    }
}

/// Module path of a source file (`src/a/b.rs` and `src/a/b/mod.rs` are `a::b`).
fn module_of(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> =
        rel.iter().map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string()).collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    parts
}

/// The non-test code of a file (up to its `#[cfg(test)] mod tests {`) without comments, and
/// the names of the child modules it declares as test-only files.
fn code_of(text: &str) -> (String, Vec<String>) {
    let mut code = String::new();
    let mut test_files = Vec::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            let next = lines.peek().map(|l| l.trim()).unwrap_or("");
            let decl = next.trim_start_matches("pub(crate) ").trim_start_matches("pub ");
            if let Some(name) = decl.strip_prefix("mod ").and_then(|n| n.strip_suffix(';')) {
                test_files.push(name.to_string());
                lines.next();
                continue;
            }
            if decl.starts_with("mod ") {
                break;
            }
        }
        if t.starts_with("//") {
            continue;
        }
        code.push_str(line.split(" //").next().unwrap_or(""));
        code.push('\n');
    }
    (code, test_files)
}

/// Every path that starts with `crate::` or `super::` (with `use` groups expanded one level:
/// `use crate::a::{b, c::d}` gives `crate::a::b` and `crate::a::c::d`).
fn paths_in(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    for start in ["crate::", "super::"] {
        let mut from = 0;
        while let Some(i) = code[from..].find(start).map(|i| i + from) {
            from = i + start.len();
            if i > 0 && (bytes[i - 1].is_ascii_alphanumeric() || bytes[i - 1] == b'_') {
                continue;
            }
            let mut end = i;
            while end < bytes.len()
                && (bytes[end].is_ascii_alphanumeric() || bytes[end] == b'_' || bytes[end] == b':')
            {
                end += 1;
            }
            let head = code[i..end].trim_end_matches(':').to_string();
            if end < bytes.len() && bytes[end] == b'{' && code[i..end].ends_with("::") {
                let close = code[end..].find('}').map(|c| c + end).unwrap_or(bytes.len());
                for item in code[end + 1..close].split(',') {
                    let item = item.trim().trim_start_matches('{');
                    let name: String = item
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_' || *c == ':')
                        .collect();
                    if !name.is_empty() && name != "self" {
                        out.push(format!("{head}::{}", name.trim_end_matches(':')));
                    }
                }
            }
            out.push(head);
        }
    }
    out
}

/// The module (one of `modules`) that path `p` of file module `me` names: the longest
/// prefix of its absolute form that is a module with a file.
fn resolve(p: &str, me: &[String], modules: &BTreeSet<Vec<String>>) -> Option<Vec<String>> {
    let mut segs: Vec<&str> = p.split("::").filter(|s| !s.is_empty()).collect();
    let mut abs: Vec<String> = if segs.first() == Some(&"crate") {
        segs.remove(0);
        Vec::new()
    } else {
        // `super` of module a::b (file `a/b.rs` or `a/b/mod.rs`) is `a`.
        let mut base = me.to_vec();
        while segs.first() == Some(&"super") {
            segs.remove(0);
            base.pop();
        }
        base
    };
    abs.extend(segs.iter().map(|s| s.to_string()));
    (1..=abs.len()).rev().map(|n| abs[..n].to_vec()).find(|m| modules.contains(m))
}

#[test]
fn modules_follow_the_dependency_rule_and_files_do_not_import_each_other() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    let mut stack = vec![src.clone()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                files.push(p);
            }
        }
    }
    files.sort();
    let mut code = BTreeMap::new();
    let mut test_only = BTreeSet::new();
    for f in &files {
        let rel = f.strip_prefix(&src).unwrap();
        if rel == Path::new("main.rs") || rel == Path::new("lib.rs") {
            continue;
        }
        let module = module_of(rel);
        let (c, tests) = code_of(&std::fs::read_to_string(f).unwrap());
        for t in tests {
            let mut m = module.clone();
            m.push(t);
            test_only.insert(m);
        }
        code.insert(module, c);
    }
    let modules: BTreeSet<Vec<String>> = code.keys().cloned().collect();
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    let mut problems = Vec::new();
    for (me, c) in &code {
        if test_only.contains(me) {
            continue;
        }
        for p in paths_in(c) {
            let Some(target) = resolve(&p, me, &modules) else { continue };
            if &target == me {
                continue;
            }
            let (from, to) = (me[0].as_str(), target[0].as_str());
            if from != to && !allowed(from).contains(&to) {
                problems.push(format!("{} uses {p}: `{from}` may not use `{to}`", me.join("::")));
            }
            edges.entry(me.clone()).or_default().insert(target);
        }
    }
    let parent_child = |a: &Vec<String>, b: &Vec<String>| {
        (a.len() + 1 == b.len() && b.starts_with(a)) || (b.len() + 1 == a.len() && a.starts_with(b))
    };
    for (a, targets) in &edges {
        for b in targets {
            if a < b && edges.get(b).is_some_and(|t| t.contains(a)) && !parent_child(a, b) {
                problems.push(format!("{} and {} use each other", a.join("::"), b.join("::")));
            }
        }
    }
    assert!(problems.is_empty(), "dependency rule broken:\n{}", problems.join("\n"));
    assert!(edges.len() > 50, "only {} files with imports: the scan is broken", edges.len());
}

#[test]
fn the_scan_sees_use_groups_and_super_paths() {
    let code = "use crate::a::{b, c::d};\nuse super::x::Y;\nfn f() { crate::e::f(); }\n";
    let p = paths_in(code);
    for want in ["crate::a::b", "crate::a::c::d", "super::x::Y", "crate::e::f"] {
        assert!(p.iter().any(|q| q == want), "{want} not in {p:?}");
    }
    let (c, tests) = code_of(
        "use crate::a;\n#[cfg(test)]\nmod t;\n#[cfg(test)]\nmod tests {\n use crate::cli;\n}\n",
    );
    assert_eq!(tests, ["t"]);
    assert!(!c.contains("cli"));
}
