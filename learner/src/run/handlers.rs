//! The run's handlers for what arrives and what is due, as the loop calls them: a message
//! ([`Run::receive`]: episodes, evaluation trials, a stop, a worker's failure), everything
//! else already waiting ([`Run::drain`]), the update once its episodes are in
//! ([`Run::update_if_ready`], recorded in `metrics.jsonl` and the run's logs) and the stop
//! check ([`Run::should_stop`]). Evaluations have theirs in `evaluation.rs`; the grants in
//! `publish.rs`.

use super::buffer::Admitted;
use super::link::Inbound;
use super::spec::RunFailure;
use super::state::{Run, episode_reward, mean, noted};
use super::stop::Standing;
use crate::record::IterationRecord;
use policy::Trajectory;
use policy::exchange::Experience;
use std::time::{Duration, Instant};

/// Messages taken in one turn of the loop at most (a flood cannot hold it).
const MAX_DRAIN: usize = 1000;

/// Where a stopping run stands with its last evaluation.
#[derive(Clone, Copy, Debug)]
struct Ending {
    /// A checkpoint held its verification.
    verified: bool,
    /// An evaluation is under way.
    pending: bool,
    /// This process made an update.
    updated: bool,
    /// The current version's evaluation is recorded.
    evaluated: bool,
    /// A worker is alive to evaluate it.
    workers: bool,
}

/// Why a stopping run is over.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Over {
    /// A verified checkpoint is the run's model: no later version is evaluated.
    Verified,
    /// This process made no update: there is nothing new to evaluate.
    NothingNew,
    /// The last version's evaluation is recorded.
    Evaluated,
    /// Nobody is left to run the final evaluation.
    NoWorker,
}

impl Ending {
    /// Whether a stopping run is over, and why (`None`: its final evaluation is still to come).
    fn over(self) -> Option<Over> {
        if self.verified && !self.pending {
            Some(Over::Verified)
        } else if !self.updated {
            Some(Over::NothingNew)
        } else if !self.pending && self.evaluated {
            Some(Over::Evaluated)
        } else if !self.workers {
            Some(Over::NoWorker)
        } else {
            None
        }
    }
}

impl Run<'_> {
    /// The episodes for an update are in, and the run is not stopping.
    pub(super) fn update_ready(&self) -> bool {
        self.buffer.len() as u64 >= self.want && self.stop_reason.is_none() && !self.check_goes_first()
    }

    /// An update, and the grant of its episodes, wait for the evaluation under way when the
    /// workers share these cores and it may stop the run ([`crate::run::RunSpec::checks_first`]).
    pub(super) fn check_goes_first(&self) -> bool {
        self.spec.checks_first && self.evals.pending.as_ref().is_some_and(|p| p.verifying || !p.chain.is_empty())
    }

    /// A message from the workers (or whoever may stop the run).
    pub(super) fn receive(&mut self, m: Inbound) -> Result<(), RunFailure> {
        match m {
            Inbound::Experience(e) => self.experience(e),
            Inbound::Eval(r) => self.evaluated(r)?,
            Inbound::Stop(why) => {
                self.stop_reason.get_or_insert(why);
            }
            Inbound::Failed { worker, error } => return Err(RunFailure::Worker { worker, error }),
        }
        Ok(())
    }

    /// Take every message already waiting (at most [`MAX_DRAIN`]).
    pub(super) fn drain(&mut self) -> Result<(), RunFailure> {
        for _ in 0..MAX_DRAIN {
            match self.link.next(Duration::ZERO)? {
                Some(m) => self.receive(m)?,
                None => break,
            }
        }
        Ok(())
    }

    /// Episodes: counted, and kept for training unless duplicate, bad or stale.
    fn experience(&mut self, e: Experience) {
        if !self.buffer.first_sight(&e.worker, e.seq) {
            return;
        }
        self.tally.env_steps += e.env_steps;
        let now = Instant::now();
        self.windows.per_worker.entry(e.worker.clone()).or_default().push_back((now, e.env_steps));
        self.grants.delivered(e.credit, &e.worker, e.trajectories.len() as u64, now);
        let share = e.env_steps / e.trajectories.len().max(1) as u64;
        // Off-policy experience is never stale.
        let lag = if self.algo.off_policy() { u64::MAX } else { self.spec.max_policy_lag };
        let (version, obs) = (self.algo.version(), self.spec.obs_size);
        for t in e.trajectories {
            let w = self.windows.worlds.entry(t.world.clone()).or_default();
            w.steps.push_back((now, share));
            let (progress, reward) = (t.progress, episode_reward(&t));
            let crashed = t.done && t.trace.last().is_some_and(|s| s.status == policy::EpisodeStatus::Crashed);
            if self.buffer.admit(&e.worker, t, version, lag, obs) == Admitted::Kept {
                w.recent.push_back((now, e.worker.clone(), progress, reward));
                w.episodes += 1;
                w.crashes += u64::from(crashed);
            }
        }
    }

    /// Update once the episodes are in: exactly the episodes an iteration takes, the first to
    /// arrive (the rest wait for the next update; off-policy, every episode buffered); publish
    /// the new version and record it. True when an update was made (or refused).
    pub(super) fn update_if_ready(&mut self) -> Result<bool, RunFailure> {
        if !self.update_ready() {
            return Ok(false);
        }
        // The figures before the update holds the loop: the delivery that completed the round
        // is shown (the per-worker window is 10 s, and an update can outlast it).
        self.windows.last_status = None;
        self.report()?;
        let spec = self.spec;
        let off_policy = self.algo.off_policy();
        let n = if off_policy { self.buffer.len() } else { self.want as usize };
        let (trajs, from) = self.buffer.take(n);
        if off_policy {
            // The next round is simulated while this update runs.
            let workers = self.link.workers();
            self.grants.clear();
            self.grant(&workers)?;
        }
        let lag = trajs.iter().map(|t| self.algo.version() - t.policy_version).max().unwrap_or(0);
        self.tally.max_lag = self.tally.max_lag.max(lag);
        let wait_s = self.tally.wait_since.elapsed().as_secs_f64();
        let t = &self.tally;
        let lr = spec.stop.lr(&spec.hyper, self.start.elapsed().as_secs_f64(), t.episodes, t.env_steps);
        self.algo.set_lr(lr);
        let t1 = Instant::now();
        let result = self.algo.update(&trajs, self.link.team());
        let update_s = t1.elapsed().as_secs_f64();
        self.tally.wait_since = Instant::now();
        self.tally.count(&trajs, spec.stop.window);
        // A refused update changed nothing; it is recorded, and the next one goes on.
        let refused = result.as_ref().err().map(|why| why.to_string());
        if let Some(why) = &refused {
            tracing::warn!(run = %spec.name, iteration = self.tally.iteration, "{why}");
        }
        self.publish()?;
        if !off_policy {
            self.buffer.drop_stale(self.algo.version(), spec.max_policy_lag);
            self.grants.clear();
        }
        let mut rec = self.iteration_record(&trajs, lag, (wait_s, update_s), lr);
        rec.refused = refused;
        if let Ok(stats) = &result {
            rec.take_figures(stats);
        }
        self.record_iteration(rec, trajs, &from);
        Ok(true)
    }

    /// The record of the update just made on `trajs` (`lag`: their largest policy lag;
    /// `seconds`: the wait for them and the update's), but its figures.
    fn iteration_record(&self, trajs: &[Trajectory], lag: u64, seconds: (f64, f64), lr: f64) -> IterationRecord {
        let (wait_s, update_s) = seconds;
        let steps: usize = trajs.iter().map(|t| t.len()).sum();
        IterationRecord {
            iteration: self.tally.iteration,
            policy_version: self.algo.version(),
            time_s: self.start.elapsed().as_secs_f64(),
            episodes: trajs.len(),
            total_episodes: self.tally.episodes,
            steps,
            env_steps: self.tally.env_steps,
            mean_reward: mean(trajs.iter().map(episode_reward)),
            mean_progress: mean(trajs.iter().map(|t| t.progress)),
            wait_s,
            update_s,
            samples_per_s: steps as f64 / update_s.max(1e-9),
            policy_lag: lag,
            episodes_received: self.buffer.received,
            dropped_stale: self.buffer.stale,
            dropped_duplicate: self.buffer.dup,
            dropped_bad: self.buffer.bad,
            lr,
            ..IterationRecord::default()
        }
    }

    /// Write an update's record (the run's logs, then, its episodes freed, `metrics.jsonl`
    /// with the memory the learner keeps), tell the observer, and have the status reported at
    /// the loop's next turn.
    fn record_iteration(&mut self, mut rec: IterationRecord, trajs: Vec<Trajectory>, from: &[String]) {
        if let Some(r) = self.recorder.as_mut() {
            noted(&self.dir, "an update's sim-trace, metrics JSON or MCAP not written", r.episodes(&rec, &trajs, from));
        }
        drop(trajs);
        rec.resident_mb = resident_mb();
        rec.live_mb = crate::record::live_mb();
        rec.waiting_mb = rec.live_mb.map(|_| self.buffer.bytes() as f64 / (1024.0 * 1024.0));
        if let Some(r) = self.recorder.as_mut() {
            noted(&self.dir, "an update's MCAP figures not written", r.figures(&rec));
        }
        noted(
            &self.dir,
            "metrics.jsonl: an update's line not written",
            self.dir.append_metrics(&serde_json::to_value(&rec).expect("JSON")),
        );
        self.observer.iteration(&rec);
        self.windows.last_status = None;
    }

    /// The figures the stop rules look at.
    fn standing(&self) -> Standing {
        let recent = &self.tally.recent;
        let full = recent.len() as u64 >= self.spec.stop.window.max(1);
        Standing {
            seconds: self.start.elapsed().as_secs_f64(),
            episodes: self.tally.episodes,
            env_steps: self.tally.env_steps,
            window: full.then(|| (mean(recent.iter().map(|r| r.0)), mean(recent.iter().map(|r| r.1)))),
            lap_streak: self.evals.lap_streak,
            verified: self.evals.verified.clone(),
            verdict: self.evals.verdict.clone(),
        }
    }

    /// Check the stop rules; true when the run is over: stopping, and the last version's
    /// evaluation is recorded (or there is nothing to evaluate, or nobody left to evaluate it).
    pub(super) fn should_stop(&mut self, workers: &[String]) -> bool {
        if self.stop_reason.is_none()
            && let Some(why) = self.spec.stop.check(&self.spec.hyper, &self.standing())
        {
            tracing::info!(run = %self.spec.name, "stopping: {why}");
            self.stop_reason = Some(why);
            self.grants.clear();
        }
        if self.stop_reason.is_none() {
            return false;
        }
        let ending = Ending {
            verified: self.evals.verified.is_some(),
            pending: self.evals.pending.is_some(),
            updated: self.tally.iterations_here > 0,
            evaluated: self.evals.evaluated_version == Some(self.algo.version()),
            workers: !workers.is_empty(),
        };
        match ending.over() {
            Some(Over::NoWorker) => {
                tracing::warn!(run = %self.spec.name, "no worker left to run the final evaluation");
                true
            }
            Some(_) => true,
            None => false,
        }
    }
}

/// This process's resident memory in MiB (`VmRSS` in `/proc/self/status`), where the system
/// tells it.
fn resident_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: f64 =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kb / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 50: a stopping run is over once a verified checkpoint has no evaluation under
    /// way, when this process made no update, once the last version's evaluation is recorded,
    /// or when no worker is left to run it; otherwise it waits for its final evaluation.
    #[test]
    fn a_stopping_run_is_over_when_its_last_evaluation_is_settled() {
        // (verified, pending, updated, evaluated, workers, over)
        for (verified, pending, updated, evaluated, workers, over) in [
            (true, false, true, false, true, Some(Over::Verified)),
            (true, true, true, false, true, None),
            (false, false, false, false, true, Some(Over::NothingNew)),
            (false, true, false, false, false, Some(Over::NothingNew)),
            (false, false, true, true, true, Some(Over::Evaluated)),
            (false, true, true, true, true, None),
            (false, true, true, true, false, Some(Over::NoWorker)),
            (false, false, true, false, false, Some(Over::NoWorker)),
            (false, false, true, false, true, None),
        ] {
            let e = Ending { verified, pending, updated, evaluated, workers };
            assert_eq!(e.over(), over, "{e:?}");
        }
    }
}
