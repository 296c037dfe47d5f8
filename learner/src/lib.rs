//! PPO on faer: the learner library (networks live in `policy`).
//!
//! Empty on purpose until the learner issue. Until then `coordinator drive` runs the
//! scripted pure-pursuit driver instead of a trained policy; nothing here pretends to train.
