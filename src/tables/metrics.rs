//! The `metrics` table (being written).
