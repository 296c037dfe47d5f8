//! One set of features for every dependency, whichever of the workspace's packages a build
//! selects: `cargo build -p deploy` after `cargo build -p coordinator -p sim-agent -p learner`
//! (or after the test build) compiles only `deploy` itself. Written by cargo-hakari from
//! `.config/hakari.toml`; after changing a dependency run `cargo hakari generate` and
//! `cargo hakari manage-deps` (a test checks that every member depends on this crate).
