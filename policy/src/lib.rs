//! What sim-agent, learner and deploy share about a model.
//!
//! Today: DeepRacer's `model_metadata.json` ([`ModelMetadata`]) and the action spaces it
//! defines ([`ActionSpace`]). The networks, their forward/backward passes and the model
//! folder format arrive with the learner issue.
//!
//! Architecture invariant: no physics, no transport, no Python here.

mod metadata;
pub mod nn;

pub use metadata::{
    Action, ActionSpace, MAX_SPEED, MAX_STEERING_DEG, MIN_SPEED, MetadataError, ModelMetadata, NeuralNetwork, Sensor,
    TrainingAlgorithm,
};
