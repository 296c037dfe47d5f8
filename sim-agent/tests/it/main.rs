//! The simulator's integration tests, one test binary: the camera, the car's physics, the
//! configuration, DeepRacer's episode rules, Python reward files and their checker, races, the vectorised
//! environments and the worker.

mod acting_on_gpu;
mod camera;
mod car_physics;
mod config;
mod env_rules;
mod python_reward;
mod races;
mod reward_check;
mod vec_env;
mod worker;
