//! What the in-process and the cluster tests share: the stop conditions, each with the words
//! of the reason it must give. The same table runs through `coordinator train` (channels) and
//! through a job on `coordinator serve` + `learner serve` + `sim-agent serve` (Zenoh).

/// (train flags, job spec `[stop]` lines, hyperparameters.json or "", the reason's words)
pub const STOP_TABLE: &[(&[&str], &str, &str, &str)] = &[
    (&["--max-episodes", "60"], "max_episodes = 60\n", "", "60 episodes reached"),
    (&["--env-steps", "15000"], "env_steps_budget = 15000\n", "", "compute budget of 15000 env steps"),
    (&["--target-progress", "25"], "target_progress = 25\n", "", "reached the target 25"),
    (&["--target-reward", "15"], "target_reward = 15\n", "", "reached the target 15"),
    (&["--minutes", "0.1"], "minutes = 0.1\n", "", "time limit of 0.1 min"),
    (&[], "", r#"{"term_cond_max_episodes": 40}"#, "term_cond_max_episodes (40)"),
    (&[], "", r#"{"term_cond_avg_score": 12}"#, "term_cond_avg_score (12)"),
];
