//! The coordinator's integration tests, one test binary (one link): each module is a file of
//! tests that run the real binaries, in temporary directories, as a user would.

mod support;

mod car_in_the_loop;
mod cli;
mod cluster;
mod docs;
mod fidelity;
mod identity;
mod join;
mod logs;
mod model_formats;
mod netns;
mod train_cli;
mod virtual_model;
