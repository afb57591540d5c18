//! The `edges` table (being written).
