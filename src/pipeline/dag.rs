//! The stage graph: an edge `P -> S` for every dep of `S` that is an output of `P`, lies
//! inside an output directory of `P`, or is a directory containing an output of `P`.
//!
//! [`Dag::build`] rejects overlapping outputs, cycles (naming the stages of one cycle) and
//! dangling deps (neither produced by a stage nor existing on disk), and fixes one
//! topological order: among ready stages, declaration order wins, so the order is stable.

use super::Error;
use super::spec::Pipeline;

/// An upstream stage and the dep path that links it to a stage.
#[derive(Debug, Clone, PartialEq)]
pub struct Edge {
    /// Index of the producing stage in `Pipeline::stages`.
    pub from: usize,
    /// The dep of the consuming stage.
    pub path: String,
}

/// The graph of a pipeline.
#[derive(Debug, Clone)]
pub struct Dag {
    /// Stage indices in execution order.
    pub order: Vec<usize>,
    /// Per stage (by index): its upstream edges, in dep order.
    pub upstream: Vec<Vec<Edge>>,
}

/// Whether `inner` equals `outer` or lies inside it (`/`-separated normalised paths).
pub fn contains(outer: &str, inner: &str) -> bool {
    outer == "."
        || inner == outer
        || (inner.len() > outer.len()
            && inner.starts_with(outer)
            && inner.as_bytes()[outer.len()] == b'/')
}

impl Dag {
    /// Build and validate the graph; `check_files` also rejects deps missing on disk.
    pub fn build(p: &Pipeline, check_files: bool) -> Result<Dag, Error> {
        let n = p.stages.len();
        for (i, a) in p.stages.iter().enumerate() {
            for b in &p.stages[i + 1..] {
                for oa in &a.outs {
                    for ob in &b.outs {
                        if contains(oa, ob) || contains(ob, oa) {
                            return Err(Error::OverlappingOuts {
                                file: p.file.clone(),
                                a: a.name.clone(),
                                b: b.name.clone(),
                                path: if contains(oa, ob) { ob.clone() } else { oa.clone() },
                            });
                        }
                    }
                }
            }
        }
        let mut upstream = vec![Vec::new(); n];
        for (i, s) in p.stages.iter().enumerate() {
            for dep in &s.deps {
                let producers: Vec<usize> = (0..n)
                    .filter(|&j| {
                        p.stages[j].outs.iter().any(|o| contains(o, dep) || contains(dep, o))
                    })
                    .collect();
                if producers.is_empty() && check_files && !p.path(dep).exists() {
                    return Err(Error::MissingDep {
                        file: p.file.clone(),
                        stage: s.name.clone(),
                        path: dep.clone(),
                    });
                }
                for from in producers {
                    upstream[i].push(Edge { from, path: dep.clone() });
                }
            }
        }
        let mut indegree: Vec<usize> = vec![0; n];
        let mut downstream = vec![Vec::new(); n];
        for (i, ups) in upstream.iter().enumerate() {
            let mut froms: Vec<usize> = ups.iter().map(|e| e.from).collect();
            froms.sort_unstable();
            froms.dedup();
            indegree[i] = froms.len();
            for f in froms {
                downstream[f].push(i);
            }
        }
        let mut order = Vec::with_capacity(n);
        let mut done = vec![false; n];
        while order.len() < n {
            let Some(next) = (0..n).find(|&i| !done[i] && indegree[i] == 0) else {
                return Err(Error::Cycle {
                    file: p.file.clone(),
                    cycle: find_cycle(p, &upstream, &done),
                });
            };
            done[next] = true;
            order.push(next);
            for &d in &downstream[next] {
                indegree[d] -= 1;
            }
        }
        Ok(Dag { order, upstream })
    }
}

/// Walk upstream edges from the first unfinished stage until a stage repeats.
fn find_cycle(p: &Pipeline, upstream: &[Vec<Edge>], done: &[bool]) -> Vec<String> {
    let start = done.iter().position(|d| !d).unwrap_or(0);
    let mut path = vec![start];
    loop {
        let cur = *path.last().unwrap_or(&start);
        let Some(next) = upstream[cur].iter().map(|e| e.from).find(|&f| !done[f]) else {
            return path.iter().map(|&i| p.stages[i].name.clone()).collect();
        };
        if let Some(pos) = path.iter().position(|&i| i == next) {
            // `path` follows edges upstream; reverse it so the cycle reads producer -> consumer,
            // then start it at the stage declared first.
            let mut cycle: Vec<usize> = path[pos..].iter().rev().copied().collect();
            let first = (0..cycle.len()).min_by_key(|&k| cycle[k]).unwrap_or(0);
            cycle.rotate_left(first);
            cycle.push(cycle[0]);
            return cycle.iter().map(|&i| p.stages[i].name.clone()).collect();
        }
        path.push(next);
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    fn dag(text: &str) -> Result<(Pipeline, Dag), Error> {
        let p = Pipeline::parse(Path::new("p.yaml"), text, &[])?;
        let d = Dag::build(&p, false)?;
        Ok((p, d))
    }

    #[test]
    fn orders_by_edges_then_declaration() {
        let (p, d) = dag(
            "stages:\n  c: {cmd: x, deps: [b/f, a.txt], outs: [c]}\n  a: {cmd: x, outs: [a.txt]}\n  b: {cmd: x, deps: [a.txt], outs: [b]}\n  z: {cmd: x, deps: [c/..//c], outs: [z]}\n",
        )
        .unwrap();
        let names: Vec<_> = d.order.iter().map(|&i| p.stages[i].name.as_str()).collect();
        assert_eq!(names, ["a", "b", "c", "z"]);
        assert_eq!(
            d.upstream[0],
            [Edge { from: 2, path: "b/f".into() }, Edge { from: 1, path: "a.txt".into() }]
        );
        assert_eq!(d.upstream[3], [Edge { from: 0, path: "c".into() }]);
    }

    #[test]
    fn a_directory_dep_depends_on_the_outs_inside_it() {
        let (_, d) = dag("stages:\n  s: {foreach: [a, b], do: {cmd: x, outs: ['sc/${item}']}}\n  t: {cmd: y, deps: [sc]}\n").unwrap();
        assert_eq!(d.upstream[2].iter().map(|e| e.from).collect::<Vec<_>>(), [0, 1]);
    }

    #[test]
    fn rejects_cycles_overlaps_and_missing_deps() {
        let e = dag("stages:\n  a: {cmd: x, deps: [c], outs: [a]}\n  b: {cmd: x, deps: [a], outs: [b]}\n  c: {cmd: x, deps: [b], outs: [c]}\n").unwrap_err();
        assert_eq!(e.to_string(), "p.yaml: dependency cycle: a -> b -> c -> a");
        let e = dag("stages:\n  a: {cmd: x, deps: [a/in], outs: [a]}\n").unwrap_err();
        assert_eq!(e.to_string(), "p.yaml: dependency cycle: a -> a");
        let e = dag("stages:\n  a: {cmd: x, outs: [d]}\n  b: {cmd: x, outs: [d/e]}\n").unwrap_err();
        assert_eq!(e.to_string(), "p.yaml: stages `a` and `b` both output `d/e`");
        let p = Pipeline::parse(
            Path::new("/nonexistent/p.yaml"),
            "stages:\n  a: {cmd: x, deps: [in.txt]}\n",
            &[],
        )
        .unwrap();
        let e = Dag::build(&p, true).unwrap_err();
        assert_eq!(
            e.to_string(),
            "/nonexistent/p.yaml: stage `a`: dependency `in.txt` does not exist and no stage outputs it"
        );
    }

    #[test]
    fn containment_is_by_component() {
        assert!(contains("a/b", "a/b/c"));
        assert!(!contains("a/b", "a/bc"));
        assert!(contains(".", "x"));
    }
}
