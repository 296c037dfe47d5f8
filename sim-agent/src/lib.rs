//! The simulator.
pub mod car;
