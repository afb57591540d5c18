//! Integration tests: one binary running the real CLI, one module per area.

mod synth;
