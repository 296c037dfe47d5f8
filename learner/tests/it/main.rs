//! The learner's integration tests, one test binary: PPO's and SAC's maths, the training run
//! against a scripted worker, its stop rules, learner teams and the `learner` binary.

mod support;

mod bench_cli;
mod data_parallel;
mod on_gpu;
mod ppo;
mod run_scripted;
mod sac;
mod stop_rules;
mod team;
mod threads;
