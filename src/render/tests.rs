//! End-to-end tests of the CPU renderer.
