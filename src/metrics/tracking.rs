//! Tracking metrics.
