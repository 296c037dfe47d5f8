//! The wire: Zenoh key expressions, message schemas and their encoding.
//!
//! Empty on purpose until the cluster issue: nothing crosses a process boundary yet, and
//! this crate will be the only one that knows how anything does. It has no dependencies on
//! the simulator or learner crates, and they will have none on the transport.
