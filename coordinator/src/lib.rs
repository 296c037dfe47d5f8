//! The coordinator library: jobs and their database ([`jobs`]), the assignment of worlds to
//! agents ([`assign`]), and job specs read from TOML ([`jobspec`]). The `coordinator` binary
//! is the command line over it (and the role shell `serve`).

pub mod assign;
pub mod jobs;
pub mod jobspec;
