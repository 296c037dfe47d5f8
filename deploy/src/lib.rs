//! The on-car agent: subscribes to published models, verifies, hot-swaps, drives.
//!
//! Empty on purpose until its issue; it will depend on `policy` and `protocol` only.
