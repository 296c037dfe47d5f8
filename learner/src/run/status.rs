//! The run's figures as the link reports them ([`RunStatus`], per world [`WorldFigures`]),
//! figured from windows over the last seconds of experience ([`Windows`]): reported every
//! second and after every update, and a last time, with `summary.json`, when the run
//! finishes.

use super::link::LinkError;
use super::spec::{RunFailure, Summary};
use super::state::{Run, mean, noted};
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::{Duration, Instant};

/// How far back the windows reach.
const WINDOW: Duration = Duration::from_secs(10);

/// Per-world figures over the last 10 s.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WorldFigures {
    /// The world.
    pub world: String,
    /// Workers that sent its episodes lately.
    pub workers: u32,
    /// Episodes trained on, in all.
    pub episodes: u64,
    /// Mean progress of its recent episodes.
    pub mean_progress: f64,
    /// Mean reward of its recent episodes.
    pub mean_reward: f64,
    /// Environment steps per second lately.
    pub steps_per_s: f64,
    /// Episodes trained on that ended crashed, in all.
    pub crashes: u64,
    /// The last evaluation on this world: mean progress (%) and mean lap time when every
    /// trial lapped (`None` before the first).
    pub eval: Option<(f64, Option<f64>)>,
}

/// A run's figures, as the link reports them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunStatus {
    /// Current policy version.
    pub policy_version: u64,
    /// Updates so far.
    pub iteration: u64,
    /// Episodes trained on.
    pub episodes: u64,
    /// Episodes received (simulated and delivered), trained on or not.
    pub episodes_received: u64,
    /// Environment steps received.
    pub env_steps: u64,
    /// Mean reward and progress over the window.
    pub window_reward: f64,
    /// Mean progress over the window.
    pub window_progress: f64,
    /// Largest policy lag trained on.
    pub max_lag: u64,
    /// Episodes dropped as stale.
    pub dropped_stale: u64,
    /// Batches dropped as duplicates.
    pub dropped_duplicate: u64,
    /// Episodes dropped as malformed (the link adds what it dropped itself).
    pub dropped_bad: u64,
    /// Mean progress of the last evaluation.
    pub eval_progress: f64,
    /// Laps of the last evaluation on its weakest world.
    pub eval_laps: u64,
    /// The final checkpoint and best model are written.
    pub finished: bool,
    /// Why the run stopped (once it has).
    pub stop_reason: Option<String>,
    /// The run folder.
    pub run_dir: String,
    /// Per world.
    pub worlds: Vec<WorldFigures>,
    /// Per worker: (id, environment steps per second lately).
    pub workers: Vec<(String, f64)>,
    /// Writes to the run folder that failed (checkpoints on a full disk, say).
    pub write_failures: u64,
    /// The last failed write's error (empty: none failed).
    pub write_error: String,
    /// How the evaluations are going (plateau, collapse), empty while improving.
    pub trend: String,
}

/// Recent episodes of one world, for the status.
#[derive(Default)]
pub(super) struct WorldWindow {
    /// (when, worker, progress, reward) of the episodes kept.
    pub(super) recent: VecDeque<(Instant, String, f64, f64)>,
    /// (when, env steps) delivered.
    pub(super) steps: VecDeque<(Instant, u64)>,
    /// Episodes trained on, in all.
    pub(super) episodes: u64,
    /// Episodes trained on that ended crashed, in all.
    pub(super) crashes: u64,
}

/// The windows the status is figured from: per world, and per worker's delivered env steps.
#[derive(Default)]
pub(super) struct Windows {
    /// Per world.
    pub(super) worlds: BTreeMap<String, WorldWindow>,
    /// Per worker: (when, env steps) delivered.
    pub(super) per_worker: BTreeMap<String, VecDeque<(Instant, u64)>>,
    /// When the status was last reported (`None`: at the loop's next turn).
    pub(super) last_status: Option<Instant>,
}

/// Drop the entries of `q` older than [`WINDOW`] at `now` (`when`: an entry's time).
fn trim<T>(q: &mut VecDeque<T>, now: Instant, when: impl Fn(&T) -> Instant) {
    while q.front().is_some_and(|r| now.duration_since(when(r)) > WINDOW) {
        q.pop_front();
    }
}

/// Env steps per second over `q` at `now`: their sum over the time since the oldest, taken
/// as at least 1 s and at most 10 s.
fn rate(q: &VecDeque<(Instant, u64)>, now: Instant) -> f64 {
    let span = q.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
    q.iter().map(|r| r.1).sum::<u64>() as f64 / span
}

impl WorldWindow {
    /// This world's figures at `now`, once what is older than the window is dropped (`eval`:
    /// its last evaluation).
    fn figures(&mut self, world: &str, now: Instant, eval: Option<(f64, Option<f64>)>) -> WorldFigures {
        trim(&mut self.recent, now, |r| r.0);
        trim(&mut self.steps, now, |r| r.0);
        let workers: BTreeSet<&String> = self.recent.iter().map(|r| &r.1).collect();
        WorldFigures {
            world: world.to_string(),
            workers: workers.len() as u32,
            episodes: self.episodes,
            mean_progress: mean(self.recent.iter().map(|r| r.2)),
            mean_reward: mean(self.recent.iter().map(|r| r.3)),
            steps_per_s: rate(&self.steps, now),
            crashes: self.crashes,
            eval,
        }
    }
}

impl Windows {
    /// Per world, its figures at `now` (`evals`: each world's last evaluation).
    fn worlds(&mut self, now: Instant, evals: &BTreeMap<String, (f64, Option<f64>)>) -> Vec<WorldFigures> {
        self.worlds.iter_mut().map(|(name, w)| w.figures(name, now, evals.get(name).copied())).collect()
    }

    /// Per worker that delivered within the window, its env steps per second at `now`.
    fn workers(&mut self, now: Instant) -> Vec<(String, f64)> {
        self.per_worker
            .iter_mut()
            .filter_map(|(id, q)| {
                trim(q, now, |r| r.0);
                (!q.is_empty()).then(|| (id.clone(), rate(q, now)))
            })
            .collect()
    }
}

impl Run<'_> {
    /// The run's figures to the link, every second (and after every update).
    pub(super) fn report(&mut self) -> Result<(), LinkError> {
        if self.windows.last_status.is_some_and(|t| t.elapsed() < Duration::from_secs(1)) {
            return Ok(());
        }
        self.windows.last_status = Some(Instant::now());
        let s = self.status();
        self.link.status(&s)
    }

    /// The run's figures now (the windows are trimmed on the way).
    fn status(&mut self) -> RunStatus {
        let now = Instant::now();
        let worlds = self.windows.worlds(now, &self.evals.worlds);
        let workers = self.windows.workers(now);
        let (write_failures, write_error) = self.dir.failures();
        let t = &self.tally;
        RunStatus {
            policy_version: self.algo.version(),
            iteration: t.iteration,
            episodes: t.episodes,
            episodes_received: self.buffer.received,
            env_steps: t.env_steps,
            window_reward: mean(t.recent.iter().map(|r| r.1)),
            window_progress: mean(t.recent.iter().map(|r| r.0)),
            max_lag: t.max_lag,
            dropped_stale: self.buffer.stale,
            dropped_duplicate: self.buffer.dup,
            dropped_bad: self.buffer.bad,
            eval_progress: self.evals.figures.0,
            eval_laps: self.evals.figures.1,
            finished: false,
            stop_reason: self.stop_reason.clone(),
            run_dir: self.dir.root().display().to_string(),
            worlds,
            workers,
            write_failures,
            write_error,
            trend: self.evals.verdict.describe(),
        }
    }

    /// The run is over: the final status, the logs closed, `summary.json`.
    pub(super) fn finish(mut self) -> Result<Summary, RunFailure> {
        let seconds = self.start.elapsed().as_secs_f64();
        let reason = self.stop_reason.clone().unwrap_or_else(|| "stopped".into());
        let mut s = self.status();
        s.finished = true;
        s.stop_reason = Some(reason.clone());
        self.link.status(&s)?;
        if let Some(r) = self.recorder.as_mut() {
            noted(&self.dir, "the run's logs not closed", r.finish());
        }
        noted(&self.dir, "the replay memory not kept", self.algo.save_memory(self.dir.root()));
        let (write_failures, write_error) = self.dir.failures();
        let spec = self.spec;
        let (t, e) = (&self.tally, &self.evals);
        let summary = self.dir.write_file(
            "summary.json",
            serde_json::to_string_pretty(&serde_json::json!({
                "run": spec.name, "worlds": spec.worlds, "iterations": t.iteration, "episodes": t.episodes,
                "episodes_received": self.buffer.received, "dropped_stale": self.buffer.stale,
                "env_steps": t.env_steps, "seconds": seconds, "stop_reason": reason, "best": e.best,
                "policy_version": self.algo.version(), "write_failures": write_failures, "write_error": write_error,
                "trend": e.verdict.describe(), "verified": e.verified,
            }))
            .expect("JSON")
            .as_bytes(),
        );
        noted(&self.dir, "summary.json not written", summary);
        tracing::info!(run = %spec.name, version = self.algo.version(), "run finished: {reason}");
        Ok(Summary {
            stop_reason: reason,
            iterations: t.iteration,
            episodes: t.episodes,
            episodes_received: self.buffer.received,
            dropped_stale: self.buffer.stale,
            env_steps: t.env_steps,
            seconds,
            best: e.best.clone(),
            verified: e.verified.clone(),
            policy_version: self.algo.version(),
            run_dir: spec.out.clone(),
            write_failures: self.dir.failures(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 50: a window keeps what arrived within the last 10 s, and its rate is the steps
    /// kept over the time since the oldest, taken as at least 1 s and at most 10 s.
    #[test]
    fn a_window_keeps_the_last_ten_seconds_and_its_rate_spans_one_to_ten() {
        let now = Instant::now() + Duration::from_secs(60);
        let ago = |s: f64| now - Duration::from_secs_f64(s);
        // (ages in seconds with their steps, entries kept, steps per second)
        for (entries, kept, per_s) in [
            (vec![], 0, 0.0),
            (vec![(0.5, 100)], 1, 100.0),
            (vec![(4.0, 100), (2.0, 100)], 2, 50.0),
            (vec![(12.0, 500), (5.0, 100)], 1, 20.0),
            (vec![(9.9, 990), (0.0, 10)], 2, 1000.0 / 9.9),
            (vec![(30.0, 1), (11.0, 1)], 0, 0.0),
        ] {
            let mut q: VecDeque<(Instant, u64)> = entries.iter().map(|&(s, n)| (ago(s), n)).collect();
            trim(&mut q, now, |r| r.0);
            assert_eq!(q.len(), kept, "{entries:?}");
            assert!((rate(&q, now) - per_s).abs() < 1e-9, "{entries:?}: {}", rate(&q, now));
        }
    }

    /// Issue 50: a world's figures count its distinct workers and average its recent
    /// episodes; a worker that delivered nothing within the window is left out.
    #[test]
    fn world_and_worker_figures_come_from_the_window() {
        let now = Instant::now() + Duration::from_secs(60);
        let ago = |s: u64| now - Duration::from_secs(s);
        // (episodes, oldest first: age, worker, progress, reward), (workers, mean progress, mean reward)
        for (recent, want) in [
            (vec![], (0, 0.0, 0.0)),
            (vec![(2, "a", 100.0, 4.0), (1, "a", 50.0, 2.0)], (1, 75.0, 3.0)),
            (vec![(20, "c", 0.0, 0.0), (3, "b", 100.0, 4.0), (1, "a", 50.0, 2.0)], (2, 75.0, 3.0)),
            (vec![(30, "c", 0.0, 0.0), (11, "b", 10.0, 1.0)], (0, 0.0, 0.0)),
        ] {
            let mut w = WorldWindow {
                recent: recent.iter().map(|&(s, id, p, r)| (ago(s), id.to_string(), p, r)).collect(),
                episodes: 7,
                ..WorldWindow::default()
            };
            let f = w.figures("w", now, Some((80.0, None)));
            assert_eq!((f.workers, f.mean_progress, f.mean_reward), want, "{recent:?}");
            assert_eq!((f.episodes, f.eval), (7, Some((80.0, None))));
        }
        let mut windows = Windows::default();
        windows.per_worker.insert("old".into(), VecDeque::from([(ago(11), 10)]));
        windows.per_worker.insert("new".into(), VecDeque::from([(ago(2), 10)]));
        assert_eq!(windows.workers(now), vec![("new".to_string(), 5.0)]);
    }
}
