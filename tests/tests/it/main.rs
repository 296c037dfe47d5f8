//! Cross-crate tests, one test binary: the foundation (tracks, simulator and reward host
//! together), PPO on a track, the fuzz targets and their kept corpus, and the repository's own rules (tidy).

mod issue_10_fuzz;
mod issue_2_foundation;
mod issue_35_fuzz_corpus;
mod issue_3_ppo_on_track;
mod tidy;
