//! When a run stops: the rules (time, episodes, targets, budgets, laps, plateaus), the
//! figures they look at, and the learning rate over the job's budget. Pure functions of a
//! [`Standing`], tested on tables (learner/tests/it/stop_rules.rs) and through whole runs
//! (learner/tests/it/run_scripted.rs).

use crate::hyperparams::Hyperparameters;
use crate::trend::Verdict;
use serde::{Deserialize, Serialize};

/// The lap target: consecutive evaluations that must complete laps, then (unless
/// `verify_trials` is 0) a verification of the last one's checkpoint before the run stops.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetLaps {
    /// Laps (of the evaluation's trials, on every world).
    pub laps: usize,
    /// Consecutive evaluations.
    pub evaluations: usize,
    /// Trials per world of the verification: the checkpoint that met the target is evaluated
    /// again with this many trials (fresh noise) and the run stops, with that checkpoint as
    /// its model, if the same share of them lap on every world. 0: no verification, the run
    /// stops at the streak of `evaluations`.
    #[serde(default)]
    pub verify_trials: usize,
}

/// Trials per world that verify a checkpoint by default.
pub const VERIFY_TRIALS: usize = 10;

impl TargetLaps {
    /// Laps an evaluation of `trials` trials needs on every world: the target's share of
    /// them (3 of 3 trials → every trial; 2 of 3 → 7 of 10), and never more than there are.
    pub fn needed(&self, eval_trials: usize, trials: usize) -> usize {
        policy::exchange::laps_needed(self.laps, eval_trials, trials)
    }
}

/// When a run stops (whichever comes first). DeepRacer's `term_cond_max_episodes` and
/// `term_cond_avg_score` come from the hyperparameters and are checked beside these.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StopRules {
    /// Wall-clock minutes from the start.
    pub minutes: f64,
    /// Episodes trained on.
    pub max_episodes: Option<u64>,
    /// Mean progress (%) over the last `window` episodes trained on.
    pub target_progress: Option<f64>,
    /// Mean episode reward over the last `window` episodes.
    pub target_reward: Option<f64>,
    /// Episodes in the window.
    pub window: u64,
    /// Environment steps simulated (received), across all workers.
    pub env_steps_budget: Option<u64>,
    /// Laps in consecutive evaluations.
    pub target_laps: Option<TargetLaps>,
    /// Stop at a plateau: this many evaluations in a row without improving on the best mean
    /// progress by a point (`None`: report plateaus after 5, do not stop).
    #[serde(default)]
    pub plateau_evals: Option<usize>,
    /// Stop when evaluation progress collapses after a peak (the best model is kept).
    #[serde(default)]
    pub stop_on_collapse: bool,
}

impl Default for StopRules {
    fn default() -> Self {
        StopRules {
            minutes: 10.0,
            max_episodes: None,
            target_progress: None,
            target_reward: None,
            window: 20,
            env_steps_budget: None,
            target_laps: None,
            plateau_evals: None,
            stop_on_collapse: false,
        }
    }
}

/// The figures the stop rules look at.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Standing {
    /// Seconds since the start.
    pub seconds: f64,
    /// Episodes trained on.
    pub episodes: u64,
    /// Environment steps received.
    pub env_steps: u64,
    /// Mean progress and reward over the window, once it is full.
    pub window: Option<(f64, f64)>,
    /// Consecutive evaluations that met the lap target.
    pub lap_streak: usize,
    /// A checkpoint that met the lap target and held it in its verification: what it did.
    pub verified: Option<String>,
    /// How the evaluations are going.
    pub verdict: Verdict,
}

impl StopRules {
    /// How much of the job's budget is spent (0–1): the nearest to its limit of the time,
    /// the episodes (`max_episodes`, `term_cond_max_episodes`) and the env-step budget.
    /// Target stops (progress, reward, laps) end a job early and are no budget.
    pub fn spent(&self, h: &Hyperparameters, seconds: f64, episodes: u64, env_steps: u64) -> f64 {
        let of = |used: f64, limit: f64| if limit > 0.0 { used / limit } else { 1.0 };
        [
            of(seconds, self.minutes * 60.0),
            self.max_episodes.map_or(0.0, |m| of(episodes as f64, m as f64)),
            of(episodes as f64, h.term_cond_max_episodes as f64),
            self.env_steps_budget.map_or(0.0, |b| of(env_steps as f64, b as f64)),
        ]
        .into_iter()
        .fold(0.0, f64::max)
        .min(1.0)
    }

    /// The learning rate of an update that begins now: `lr` on the job's `lr_schedule`. A job
    /// that stops at a target (progress, reward or laps) keeps the whole rate: its budget is
    /// then a cap, not the length of the job.
    pub fn lr(&self, h: &Hyperparameters, seconds: f64, episodes: u64, env_steps: u64) -> f64 {
        let aims_at_target = self.target_progress.is_some()
            || self.target_reward.is_some()
            || self.target_laps.is_some_and(|t| t.laps > 0);
        let spent = if aims_at_target { 0.0 } else { self.spent(h, seconds, episodes, env_steps) };
        h.lr * h.lr_schedule.factor(spent)
    }

    /// Why to stop now, if at all.
    pub fn check(&self, h: &Hyperparameters, s: &Standing) -> Option<String> {
        if s.seconds >= self.minutes * 60.0 {
            return Some(format!("time limit of {} min reached", self.minutes));
        }
        if let Some(m) = self.max_episodes.filter(|m| s.episodes >= *m) {
            return Some(format!("{m} episodes reached"));
        }
        if s.episodes >= h.term_cond_max_episodes {
            return Some(format!("term_cond_max_episodes ({}) reached", h.term_cond_max_episodes));
        }
        if let Some((p, r)) = s.window {
            if let Some(t) = self.target_progress.filter(|t| p >= *t) {
                return Some(format!(
                    "mean progress {p:.1} % over the last {} episodes reached the target {t}",
                    self.window
                ));
            }
            if let Some(t) = self.target_reward.filter(|t| r >= *t) {
                return Some(format!(
                    "mean reward {r:.1} over the last {} episodes reached the target {t}",
                    self.window
                ));
            }
            if r >= h.term_cond_avg_score {
                return Some(format!(
                    "mean reward {r:.1} over the last {} episodes reached term_cond_avg_score ({})",
                    self.window, h.term_cond_avg_score
                ));
            }
        }
        if let Some(b) = self.env_steps_budget.filter(|b| s.env_steps >= *b) {
            return Some(format!("compute budget of {b} env steps spent"));
        }
        if let Some(t) = self.target_laps.filter(|t| t.laps > 0) {
            if t.verify_trials > 0 {
                if let Some(v) = &s.verified {
                    return Some(format!("target laps reached and verified: {v}"));
                }
            } else if s.lap_streak >= t.evaluations.max(1) {
                return Some(format!(
                    "target laps reached: {} laps in {} consecutive evaluations",
                    t.laps,
                    t.evaluations.max(1)
                ));
            }
        }
        match &s.verdict {
            Verdict::Plateau { .. } if self.plateau_evals.is_some() => return Some(s.verdict.describe()),
            Verdict::Collapse { .. } if self.stop_on_collapse => return Some(s.verdict.describe()),
            _ => {}
        }
        None
    }
}
