//! The on-car agent: subscribes to a job's published models, verifies them, swaps them in
//! between two camera frames, and drives the car through its own ROS 2 nodes.
//!
//! - [`frame`]: camera frames (JPEG or raw) to the network's input, as DeepRacer's inference
//!   node prepares them.
//! - [`infer`]: the policy tower as the car runs it (the big dense layer in half precision,
//!   as DeepRacer's car runs FP16).
//! - [`verify`]: the checks a model passes before it drives (signature, checksum, fit).
//! - [`driver`]: frames in, commands out; the model slot, the watchdog and the e-stop.
//!
//! The binary (`main.rs`) is the Zenoh shell around these. This package depends on `policy`
//! and `protocol` only: no simulator, no learner.

pub mod driver;
pub mod frame;
pub mod infer;
pub mod verify;

pub use driver::{CarState, Command, Driver, Follow, ModelSlot, Offer};
pub use verify::VerifiedModel;
