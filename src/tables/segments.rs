//! The `segments` table (being written).
