//! What sim-agent, learner and deploy share about a model.
//!
//! - [`error`]: [`FileError`], a file that could not be read or written, or whose contents
//!   are wrong, naming the file.
//! - [`metadata`]: DeepRacer's `model_metadata.json` and action spaces.
//! - [`nn`]: layers on faer, forward and backward, Adam.
//! - `bf16`: matrix products with bf16 operands and f32 sums (x86-64 with AVX-512 BF16).
//! - [`model`]: the actor-critic (separate policy and value towers, DeepRacer's networks by
//!   name) and its heads.
//! - [`folder`]: the model folder (safetensors + `model_metadata.json` + manifest).
//! - [`tfgraph`]: DeepRacer's frozen TensorFlow graph (`model.pb`), written and read.
//! - [`tfckpt`]: TensorFlow's checkpoint (tensor bundle), written and read.
//! - [`coach`]: rl_coach's variable names and shapes for every network, and a model as them.
//! - [`carpkg`]: DeepRacer's model archive (`agent/model.pb` + `model_metadata.json`).
//! - [`car`]: `car.toml`, what a physical car can run and how actions become servo ratios.
//! - [`signature`]: ed25519 signatures over a model's files, and the keys a car trusts.
//! - [`experience`]: trajectories, tagged with the policy version that produced them.
//! - [`simtrace`]: DeepRacer's sim-trace CSV rows.
//! - [`exchange`]: what the learner and the sim workers say to each other (credits,
//!   experience, evaluation requests and reports), as plain values.
//!
//! Architecture invariant: no physics, no transport, no Python here.

#[cfg(target_arch = "x86_64")]
pub mod bf16;
pub mod car;
pub mod carpkg;
pub mod coach;
pub mod error;
pub mod exchange;
pub mod experience;
pub mod folder;
pub mod metadata;
pub mod model;
pub mod nn;
pub mod signature;
pub mod simtrace;
pub mod tfckpt;
pub mod tfgraph;

pub use error::FileError;
pub use experience::{EpisodeStatus, StepTrace, TrackLines, Trajectory};
pub use folder::{Manifest, ModelError, ModelFolder, ModelParts};
pub use metadata::{
    Action, ActionSpace, Incompatible, MAX_SPEED, MAX_STEERING_DEG, MIN_SPEED, MetadataError, ModelMetadata,
    NeuralNetwork, Sensor, TrainingAlgorithm,
};
pub use model::{ActOutput, ActorCritic, Choice, Head};
