//! End-to-end tests: one test binary that runs the real `usplat4d` CLI (STYLE.md 14; the
//! harness is in `util`).

mod util;

mod bad_inputs;
mod benchmark_pipelines;
mod dycheck;
mod evaluate;
mod gpu;
mod graph;
mod graph_fox;
mod graph_scope;
mod ground_truth;
mod import;
mod init;
mod inspect;
mod interop;
mod layout;
mod model_cameras;
mod optimize;
mod pipeline;
mod render;
mod report;
mod synth;
