//! The `tracks_2d` table (being written).
