//! The coordinator library: jobs and their database ([`jobs`]), the assignment of worlds to
//! agents ([`assign`]), job specs read from TOML ([`jobspec`]), the job-control client
//! ([`control`]), a model's evaluation ([`evaluation`]), roles supervised as child processes ([`supervise`]), and a model's policy as
//! ONNX ([`onnx`]), and DeepRacer's whole models (DRoA's and deepracer-for-cloud's folders) both ways
//! ([`virtual_model`]). The `coordinator` binary is the command line over it (and the role shell
//! `serve`); the `console` crate is the web shell over it.

pub mod assign;
pub mod certs;
pub mod control;
pub mod evaluation;
pub mod jobs;
pub mod jobspec;
pub mod join;
pub mod onnx;
pub mod supervise;
pub mod virtual_model;
