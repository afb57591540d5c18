//! End-to-end tests: one binary that runs the real `usplat4d` CLI (see `util`).

mod pipeline;
