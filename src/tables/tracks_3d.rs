//! The `tracks_3d` table (being written).
