//! A run under way: the state every handler shares ([`Run`]), what it has counted so far
//! ([`Tally`]), and how it starts: the run folder opened, the run's inputs written into it,
//! the algorithm made, and the first policy published.

use super::buffer::Buffer;
use super::evaluation::Evaluations;
use super::grants::Grants;
use super::link::{Link, Observer};
use super::open;
use super::spec::{RunFailure, RunSpec, Start};
use super::status::Windows;
use crate::algorithm::Algorithm;
use crate::checkpoints::RunDir;
use crate::record::Recorder;
use policy::folder::Parent;
use policy::signature::Signer;
use policy::{ModelMetadata, Trajectory};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A run under way: everything [`super::run`]'s handlers share.
pub(super) struct Run<'a> {
    pub(super) spec: &'a RunSpec,
    pub(super) link: &'a mut dyn Link,
    pub(super) observer: &'a mut dyn Observer,
    pub(super) dir: RunDir,
    pub(super) signer: Signer,
    /// The run's logs (sim-trace, metrics JSON, MCAP); `None` when they could not be opened.
    pub(super) recorder: Option<Recorder>,
    pub(super) metadata: Arc<ModelMetadata>,
    pub(super) parent: Option<Parent>,
    /// The algorithm: PPO or SAC.
    pub(super) algo: Box<dyn Algorithm>,
    /// The run's start (moved back by the training time of a job's earlier learner).
    pub(super) start: Instant,
    /// Episodes an update takes (DeepRacer's `num_episodes_between_training`).
    pub(super) want: u64,
    pub(super) buffer: Buffer,
    pub(super) grants: Grants,
    pub(super) tally: Tally,
    /// The status's windows over the last seconds.
    pub(super) windows: Windows,
    /// Checkpoints, their evaluations and the best model.
    pub(super) evals: Evaluations,
    pub(super) stop_reason: Option<String>,
}

/// What the run has counted so far.
pub(super) struct Tally {
    /// (progress, reward) of the last `window` episodes trained on.
    pub(super) recent: VecDeque<(f64, f64)>,
    /// Episodes trained on.
    pub(super) episodes: u64,
    /// Environment steps received.
    pub(super) env_steps: u64,
    /// Updates so far (a resumed run goes on from its checkpoint's).
    pub(super) iteration: u64,
    /// Updates made by this process (a resumed run counts from 0).
    pub(super) iterations_here: u64,
    /// Largest policy lag trained on.
    pub(super) max_lag: u64,
    /// Since the last update: the learner's wait for experience.
    pub(super) wait_since: Instant,
}

impl Tally {
    /// An update made on `trajs`: counted, and their (progress, reward) kept among the last
    /// `window` (at least one).
    pub(super) fn count(&mut self, trajs: &[Trajectory], window: u64) {
        self.iteration += 1;
        self.iterations_here += 1;
        self.episodes += trajs.len() as u64;
        for t in trajs {
            self.recent.push_back((t.progress, episode_reward(t)));
        }
        while self.recent.len() as u64 > window.max(1) {
            self.recent.pop_front();
        }
    }
}

impl<'a> Run<'a> {
    /// Open the run folder (new, resumed or cloned), write the run's inputs into it and
    /// publish the first policy.
    pub(super) fn open(
        spec: &'a RunSpec,
        link: &'a mut dyn Link,
        observer: &'a mut dyn Observer,
    ) -> Result<Run<'a>, RunFailure> {
        let start = Instant::now();
        if spec.worlds.is_empty() {
            return Err(RunFailure::Inputs("the run names no world".into()));
        }
        let (dir, model, version, parent, first_iteration) = open::open(spec)?;
        // A learner restarted mid-job goes on from the run's records: the training time,
        // episodes and env steps so far count towards the job's stop rules (it does not start
        // over). A person's `train --resume` asks for a new stretch of training instead.
        let mid_job = matches!(spec.start, Start::ResumeOrNew { .. });
        let resumed = if first_iteration > 0 && mid_job { dir.last_metrics() } else { None };
        let so_far = |k: &str| resumed.as_ref().and_then(|m| m[k].as_f64()).unwrap_or(0.0);
        let start = start.checked_sub(Duration::from_secs_f64(so_far("time_s"))).unwrap_or(start);
        let signer = open::signer_for(spec, &dir)?;
        open::write_inputs(spec, &dir)?;
        let recorder = noted(
            &dir,
            "the run's logs (sim-trace, metrics JSON, MCAP) not opened",
            Recorder::open(&spec.out, &spec.metadata.action_space, &spec.tracks, first_iteration),
        );
        let algo = open::algorithm(spec, &dir, model, version, first_iteration)?;
        let best = dir.index()?.best_checkpoint;
        let mut r = Run {
            spec,
            link,
            observer,
            dir,
            signer,
            recorder,
            metadata: Arc::new(spec.metadata.clone()),
            parent,
            algo,
            start,
            want: spec.hyper.num_episodes_between_training.max(1) as u64,
            buffer: Buffer::new(so_far("total_episodes") as u64),
            grants: Grants::from_clock(),
            tally: Tally {
                recent: VecDeque::new(),
                episodes: so_far("total_episodes") as u64,
                env_steps: so_far("env_steps") as u64,
                iteration: first_iteration,
                iterations_here: 0,
                max_lag: 0,
                wait_since: Instant::now(),
            },
            windows: Windows::default(),
            evals: Evaluations::new(best, &spec.stop),
            stop_reason: None,
        };
        r.publish()?;
        tracing::info!(run = %spec.name, version = r.algo.version(), folder = %spec.out.display(), "training");
        Ok(r)
    }
}

/// A write to the run folder that training does not stop for: a failure is noted (logged, and
/// reported in the run's status) and `None`.
pub(super) fn noted<T, E: std::fmt::Display>(run: &RunDir, what: &str, r: Result<T, E>) -> Option<T> {
    match r {
        Ok(v) => Some(v),
        Err(e) => {
            run.note_failure(format!("{what}: {e}"));
            None
        }
    }
}

/// The mean of `xs`; 0 when there are none.
pub(super) fn mean(xs: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

/// An episode's reward: the sum of its steps'.
pub(super) fn episode_reward(t: &Trajectory) -> f64 {
    t.rewards.iter().map(|r| *r as f64).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 50: an update counts its episodes and keeps the (progress, reward) of the last
    /// `window` episodes trained on (at least one), the oldest let go first.
    #[test]
    fn an_update_is_counted_and_the_window_keeps_the_last_episodes() {
        let episode = |progress: f64, reward: f32| Trajectory {
            progress,
            rewards: vec![reward, reward],
            ..Trajectory::default()
        };
        // (episodes already in the window, this update's, window, kept afterwards)
        for (before, update, window, kept) in [
            (vec![], vec![(10.0, 1.0)], 3, vec![(10.0, 2.0)]),
            (
                vec![(1.0, 1.0), (2.0, 2.0)],
                vec![(30.0, 0.5), (40.0, 1.5)],
                3,
                vec![(2.0, 2.0), (30.0, 1.0), (40.0, 3.0)],
            ),
            (vec![(1.0, 1.0)], vec![(50.0, 2.0)], 0, vec![(50.0, 4.0)]),
            (vec![], vec![], 5, vec![]),
        ] {
            let mut t = Tally {
                recent: before.iter().copied().collect(),
                episodes: 4,
                env_steps: 0,
                iteration: 9,
                iterations_here: 2,
                max_lag: 0,
                wait_since: Instant::now(),
            };
            let trajs: Vec<Trajectory> = update.iter().map(|&(p, r)| episode(p, r)).collect();
            t.count(&trajs, window);
            assert_eq!(t.recent.iter().copied().collect::<Vec<_>>(), kept, "{before:?} + {update:?}");
            assert_eq!((t.iteration, t.iterations_here, t.episodes), (10, 3, 4 + update.len() as u64));
        }
        assert_eq!(mean([1.0, 2.0, 6.0].into_iter()), 3.0);
        assert_eq!(mean(std::iter::empty()), 0.0);
    }
}
