//! Cross-crate tests, one test binary: the foundation (tracks, simulator and reward host
//! together), PPO on a track, the fuzz targets and their kept corpus, and the repository's own rules (tidy).

mod foundation;
mod fuzz_corpus;
mod fuzz_targets;
mod ppo_on_track;
mod tidy;
