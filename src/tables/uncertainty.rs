//! The `uncertainty` table (being written).
