//! End-to-end tests: one test binary that runs the real `usplat4d` CLI (STYLE.md 14).

mod dycheck;
