//! The track crate's integration tests, one test binary: the catalog, `.npy` files and the
//! geometry's queries.

mod common;

mod catalog;
mod npy;
mod queries;
