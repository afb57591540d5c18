//! The `key_nodes` table (being written).
