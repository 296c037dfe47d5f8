//! The policy crate's integration tests, one test binary: the model folder, DeepRacer's
//! networks by name, and every layer's gradients.

mod folder;
mod networks;
mod nn_gradients;
