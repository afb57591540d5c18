//! Integration tests: one test binary that runs the real `usplat4d` CLI.
mod evaluate;
