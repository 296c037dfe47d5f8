//! The coordinator library: jobs and their database ([`jobs`]), the assignment of worlds to
//! agents ([`assign`]), job specs read from TOML ([`jobspec`]), and a model's policy as ONNX
//! ([`onnx`]). The `coordinator` binary
//! is the command line over it (and the role shell `serve`).

pub mod assign;
pub mod jobs;
pub mod jobspec;
pub mod onnx;
