//! The on-car agent's integration tests, one test binary: its loop without a network, and the
//! real `deploy` binary against a car written in Python.

mod driver;
mod python_car;
