//! The GPU path against faer, on whatever adapter `--device gpu` finds (lavapipe in CI, so
//! no test needs a GPU): the product in every orientation and split, every layer's forward
//! and backward pass in whole networks, and Adam.

mod against_faer;
