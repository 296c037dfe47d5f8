//! Evaluation and the best model: a checkpoint when one is due, its evaluation on the workers
//! (asked, repeated and moved to another worker as `pending.rs` does it), and once every
//! world's trials are in, the evaluation closed: recorded in the checkpoint index, the model
//! kept and announced when it is the best, the lap streak and the trend followed, and the
//! checkpoint that met the lap target verified. The decisions are pure functions, tested on
//! tables below.

use super::link::LinkError;
use super::pending::{EVAL_REPEAT, EVAL_TIMEOUT, EvalTurns, PendingEval};
use super::state::{Run, noted};
use super::stop::{StopRules, TargetLaps};
use crate::checkpoints::{CheckpointRecord, RunDir};
use crate::record::EvalRecord;
use crate::trend::{Trend, TrendRules, Verdict};
use policy::exchange::{EvalReport, Trial, summarise};
use policy::folder::{self, Manifest};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// One world's evaluation: the world, mean progress, mean lap time (when every trial
/// lapped), laps, trials.
pub(super) type WorldEval = (String, f64, Option<f64>, usize, usize);

/// The run's checkpoints, their evaluations and its best model.
pub(super) struct Evaluations {
    /// The best checkpoint (the verified one when a verification held).
    pub(super) best: Option<CheckpointRecord>,
    /// When the last checkpoint was due.
    pub(super) last: Option<Instant>,
    /// The last checkpoint due was not evaluated (another evaluation was under way).
    pub(super) owed: bool,
    /// The iteration of the last checkpoint written.
    pub(super) saved_iteration: Option<u64>,
    /// The version of the last evaluation closed.
    pub(super) evaluated_version: Option<u64>,
    /// Mean progress and weakest world's laps of the last evaluation.
    pub(super) figures: (f64, u64),
    /// Per world, the last evaluation's mean progress and lap time.
    pub(super) worlds: BTreeMap<String, (f64, Option<f64>)>,
    /// Consecutive evaluations that met the lap target.
    pub(super) lap_streak: usize,
    /// The checkpoint that held its verification, and what it did.
    pub(super) verified: Option<String>,
    /// The evaluation under way.
    pub(super) pending: Option<PendingEval>,
    /// Who is asked next.
    pub(super) turns: EvalTurns,
    /// When the evaluation under way was last asked for.
    pub(super) last_ask: Instant,
    /// Evaluation progress over time.
    pub(super) trend: Trend,
    /// Its verdict after the last evaluation.
    pub(super) verdict: Verdict,
}

impl Evaluations {
    /// None yet; `best`: the run folder's best checkpoint (a resumed run's).
    pub(super) fn new(best: Option<CheckpointRecord>, stop: &StopRules) -> Evaluations {
        let trend = Trend::new(TrendRules {
            plateau_evals: stop.plateau_evals.unwrap_or(TrendRules::default().plateau_evals),
            ..TrendRules::default()
        });
        Evaluations {
            best,
            last: None,
            owed: false,
            saved_iteration: None,
            evaluated_version: None,
            figures: (0.0, 0),
            worlds: BTreeMap::new(),
            lap_streak: 0,
            verified: None,
            pending: None,
            turns: EvalTurns::default(),
            last_ask: Instant::now(),
            trend,
            verdict: Verdict::Improving,
        }
    }
}

/// What decides whether a checkpoint is due.
#[derive(Clone, Copy, Debug)]
struct CheckpointClock {
    /// This process made an update.
    updated: bool,
    /// The run is stopping.
    stopping: bool,
    /// The current iteration's checkpoint is written.
    saved: bool,
    /// `eval_seconds` have passed since the last checkpoint, or there was none.
    elapsed: bool,
    /// The current version's evaluation is closed.
    evaluated: bool,
    /// An evaluation is under way.
    pending: bool,
    /// A worker is alive.
    workers: bool,
    /// The clock fell while an evaluation was under way: the checkpoint was written, and its
    /// evaluation is owed.
    owed: bool,
    /// The run stops at a lap target, and the last evaluation lapped at least one trial on
    /// every world: the target is in sight.
    in_sight: bool,
}

impl CheckpointClock {
    /// A checkpoint every `eval_seconds` while training, and the evaluation owed as soon as
    /// the one under way is closed; while the lap target is in sight, every new version as
    /// soon as no evaluation is under way, whatever the clock says (the first version that
    /// would hold is not skipped); when stopping, the last version's, unless it is evaluated,
    /// an evaluation is under way or nobody is left to evaluate it.
    fn due(self) -> bool {
        let on_the_clock = self.updated && !self.stopping && !self.saved && self.elapsed;
        let owed = self.owed && self.updated && !self.stopping && !self.pending && self.workers;
        let in_sight = self.in_sight && self.updated && !self.stopping && !self.saved && !self.pending && self.workers;
        let last = self.stopping && self.updated && !self.evaluated && !self.pending && self.workers;
        on_the_clock || owed || in_sight || last
    }
}

/// Per world, in the run's order, the summary of its trials (`done`); a world without
/// trials has none.
fn per_world(worlds: &[String], done: &BTreeMap<String, Vec<Trial>>) -> Vec<WorldEval> {
    worlds
        .iter()
        .map(|w| {
            let t = done.get(w).map(Vec::as_slice).unwrap_or(&[]);
            let (pr, lap, laps) = summarise(t);
            (w.clone(), pr, lap, laps, t.len())
        })
        .collect()
}

/// Laps on the world that lapped fewest (0 without worlds).
fn min_laps(per_world: &[WorldEval]) -> usize {
    per_world.iter().map(|w| w.3).min().unwrap_or(0)
}

/// The lap streak after a checkpoint's evaluation that lapped `min_laps` on its weakest
/// world (of `eval_trials` trials), and the trials of the verification it calls for: one
/// once the streak reaches the target's evaluations, unless the target verifies nothing or
/// the run is stopping.
fn lap_streak(
    streak: usize,
    target: &TargetLaps,
    min_laps: usize,
    eval_trials: usize,
    stopping: bool,
) -> (usize, Option<u32>) {
    let met = min_laps >= target.needed(eval_trials, eval_trials);
    let streak = if met { streak + 1 } else { 0 };
    let verify = met && target.verify_trials > 0 && streak >= target.evaluations.max(1) && !stopping;
    (streak, verify.then_some(target.verify_trials as u32))
}

/// Whether a verification of `trials` trials per world holds: every world lapped `needed`
/// of them, and every world's trials are all in.
fn verification_holds(per_world: &[WorldEval], needed: usize, trials: usize) -> bool {
    per_world.iter().all(|w| w.3 >= needed && w.4 == trials)
}

/// Whether a verification can no longer hold, whatever the worlds still out bring: a world
/// whose trials are in (`done`) lapped fewer than `needed` of them.
fn verification_lost(done: &BTreeMap<String, Vec<Trial>>, needed: usize) -> bool {
    done.values().any(|t| summarise(t).2 < needed)
}

/// The checkpoint's manifest with its evaluation's figures (and a verification's trials).
fn evaluated_manifest(p: &PendingEval, progress: f64, lap_time: Option<f64>, per_world: &[WorldEval]) -> Manifest {
    let mut manifest = p.manifest.clone();
    if let Some(obj) = manifest.training.as_object_mut() {
        obj.insert("eval_progress".into(), progress.into());
        obj.insert("eval_lap_time".into(), serde_json::json!(lap_time));
        obj.insert("eval_worlds".into(), serde_json::to_value(per_world).expect("JSON"));
        if p.verifying {
            obj.insert("verified_trials".into(), p.trials.into());
        }
    }
    manifest
}

impl Run<'_> {
    /// A checkpoint when due (every `eval_seconds`, every version while the lap target is in
    /// sight, and the last version when stopping), each evaluated on the workers unless an
    /// evaluation is still under way.
    pub(super) fn checkpoint_if_due(&mut self, workers: &[String]) -> Result<(), LinkError> {
        let spec = self.spec;
        let every = Duration::from_secs_f64(spec.eval_seconds.max(0.0));
        let clock = CheckpointClock {
            updated: self.tally.iterations_here > 0,
            stopping: self.stop_reason.is_some(),
            saved: self.evals.saved_iteration == Some(self.tally.iteration),
            elapsed: self.evals.last.is_none_or(|t| t.elapsed() >= every),
            evaluated: self.evals.evaluated_version == Some(self.algo.version()),
            pending: self.evals.pending.is_some(),
            workers: !workers.is_empty(),
            owed: self.evals.owed,
            in_sight: spec.stop.target_laps.is_some_and(|t| t.laps > 0) && self.evals.figures.1 >= 1,
        };
        if !clock.due() {
            return Ok(());
        }
        let iteration = self.tally.iteration;
        let name = RunDir::checkpoint_name(iteration);
        let manifest = self.manifest(serde_json::json!({"run": spec.name, "worlds": spec.worlds,
            "iteration": iteration, "episodes": self.tally.episodes, "env_steps": self.tally.env_steps,
            "seconds": self.start.elapsed().as_secs_f64(), "hyperparameters": spec.hyper}));
        if self.evals.saved_iteration != Some(iteration) {
            self.save_checkpoint(&name, &manifest);
            noted(&self.dir, "the replay memory's part not kept", self.algo.save_memory_part(self.dir.root()));
            self.evals.saved_iteration = Some(iteration);
        }
        self.evals.last = Some(Instant::now());
        self.evals.owed = self.evals.pending.is_some() && self.stop_reason.is_none();
        if self.evals.pending.is_none() && !workers.is_empty() {
            let mut p =
                PendingEval::new(spec, iteration, self.algo.version(), self.algo.model().clone(), manifest, name);
            if let Some((trials, laps)) = self.chained_verification() {
                p.chain_verification(&mut self.evals.turns, &spec.worlds, trials, laps);
            }
            for world in &spec.worlds {
                self.evals.turns.ask(&mut p, &mut *self.link, workers, world.clone(), 1)?;
            }
            self.evals.pending = Some(p);
        }
        Ok(())
    }

    /// The verification (trials, and laps each world's evaluation must make for it) that a
    /// checkpoint's evaluation meeting the lap target would call for now, to be chained to it.
    fn chained_verification(&self) -> Option<(u32, u32)> {
        let t = self.spec.stop.target_laps.filter(|t| t.laps > 0)?;
        let eval_trials = self.spec.eval_trials as usize;
        let needed = t.needed(eval_trials, eval_trials);
        let stopping = self.stop_reason.is_some();
        let (_, verify) = lap_streak(self.evals.lap_streak, &t, needed, eval_trials, stopping);
        verify.map(|trials| (trials, needed as u32))
    }

    /// Write checkpoint `name`. One that cannot be written (a full disk) is reported and
    /// training goes on: the previous checkpoint stays the one a restart resumes from.
    fn save_checkpoint(&self, name: &str, manifest: &Manifest) {
        let written = folder::save_signed(
            &self.dir.checkpoint_dir(name),
            &self.spec.metadata,
            self.algo.model(),
            manifest,
            Some(&self.signer),
        )
        .map_err(|e| e.to_string())
        .and_then(|_| self.algo.save_state(&self.dir.checkpoint_dir(name)).map_err(|e| e.to_string()))
        .and_then(|_| {
            self.dir
                .record_last(CheckpointRecord {
                    name: name.to_string(),
                    iteration: self.tally.iteration,
                    policy_version: self.algo.version(),
                    avg_eval_metric: 0.0,
                    avg_lap_time: None,
                    time_stamp: self.start.elapsed().as_secs_f64(),
                })
                .map_err(|e| e.to_string())
        });
        if let Err(e) = written {
            let kept =
                self.dir.index().ok().and_then(|i| i.last_checkpoint).map(|l| l.name).unwrap_or_else(|| "none".into());
            self.dir.note_failure(format!("checkpoint {name} not written ({e}); the last checkpoint is still {kept}"));
        }
    }

    /// Trials for the evaluation under way (a failed request is asked of another worker).
    pub(super) fn evaluated(&mut self, r: EvalReport) -> Result<(), LinkError> {
        if let Some(p) = self.evals.pending.as_mut().filter(|p| p.is_chained(&r)) {
            p.early.push(r);
            return Ok(());
        }
        let Some(p) =
            self.evals.pending.as_mut().filter(|p| {
                p.version == r.version && p.asked.get(&r.id).is_some_and(|(world, _, _, _)| *world == r.world)
            })
        else {
            return Ok(());
        };
        let (world, worker, _, attempts) = p.asked.remove(&r.id).expect("checked");
        match r.trials {
            Ok(trials) => {
                p.by.insert(world.clone(), worker);
                p.done.insert(world, trials);
            }
            Err(why) => {
                tracing::warn!(run = %self.spec.name, worker = %worker, world = %world, "evaluation failed: {why}");
                let workers = self.link.workers();
                self.evals.turns.retry(p, &mut *self.link, &workers, world, attempts)?;
            }
        }
        Ok(())
    }

    /// Keep the evaluation under way going: ask again every few seconds (a request can be lost
    /// while the worker's subscription is on its way; the worker answers a repeat from its
    /// cache), and ask another worker when this one went away or never answered.
    pub(super) fn chase_evaluation(&mut self, workers: &[String]) -> Result<(), LinkError> {
        let Some(p) = self.evals.pending.as_mut() else { return Ok(()) };
        if self.evals.last_ask.elapsed() >= EVAL_REPEAT {
            self.evals.last_ask = Instant::now();
            for (id, (world, w, _, _)) in &p.asked {
                self.link.request_eval(&p.request(*id, w, world))?;
            }
        }
        let lost: Vec<u64> = p
            .asked
            .iter()
            .filter(|(_, (_, w, t, _))| !workers.contains(w) || t.elapsed() > EVAL_TIMEOUT)
            .map(|(id, _)| *id)
            .collect();
        for id in lost {
            let (world, _, _, attempts) = p.asked.remove(&id).expect("listed");
            self.evals.turns.retry(p, &mut *self.link, workers, world, attempts)?;
        }
        Ok(())
    }

    /// Once every world's trials are in, or a verification can no longer hold: record the
    /// evaluation, keep the model if it is the best, follow the lap streak and the trend, and
    /// verify a checkpoint that met the lap target. True when this was the final evaluation of
    /// a stopping run (the run is over). A verification lost on one world closes at once: the
    /// worlds still out count as run none, the next grant tells their workers the checks are
    /// closed (they drop the trials), and training goes on without waiting for them.
    pub(super) fn close_evaluation(&mut self) -> Result<bool, LinkError> {
        let lost = |p: &PendingEval| {
            let needed = self
                .spec
                .stop
                .target_laps
                .filter(|t| t.laps > 0)
                .map(|t| t.needed(self.spec.eval_trials as usize, p.trials as usize));
            p.verifying && needed.is_some_and(|n| verification_lost(&p.done, n))
        };
        if !self.evals.pending.as_ref().is_some_and(|p| p.asked.is_empty() || lost(p)) {
            return Ok(false);
        }
        let mut p = self.evals.pending.take().expect("checked");
        p.asked.clear();
        let all: Vec<Trial> = p.done.values().flatten().cloned().collect();
        let (progress, lap_time, _) = summarise(&all);
        let per_world = per_world(&self.spec.worlds, &p.done);
        let min_laps = min_laps(&per_world);
        let rec = CheckpointRecord {
            name: p.name.clone(),
            iteration: p.iteration,
            policy_version: p.version,
            avg_eval_metric: progress,
            avg_lap_time: lap_time,
            time_stamp: self.start.elapsed().as_secs_f64(),
        };
        let manifest = evaluated_manifest(&p, progress, lap_time, &per_world);
        let is_best = self.keep_if_best(&p, rec, &manifest, &per_world)?;
        let mut verify = None;
        if !p.verifying {
            verify = self.follow_streak(min_laps);
            self.follow_trend(p.iteration, progress, min_laps, &per_world);
        }
        let e = EvalRecord {
            iteration: p.iteration,
            policy_version: p.version,
            worlds: per_world,
            progress,
            reward: super::state::mean(all.iter().map(|t| t.reward)),
            lap_time,
            min_laps,
            trials: p.trials as usize,
            best: is_best,
            simtrace: Vec::new(),
            trend: self.evals.verdict.describe(),
            crashes: all.iter().map(|t| t.crashes).sum(),
            overtakes: all.iter().filter_map(|t| t.overtakes).reduce(|a, b| a + b),
            verification: p.verifying,
        };
        self.record_evaluation(e, &p.done);
        let workers = self.link.workers();
        // Chained verifications all in need no worker.
        let covered = self.spec.worlds.iter().all(|w| p.chained_report(w).is_some());
        if let (Some(trials), true) = (verify, covered || !workers.is_empty()) {
            self.verify(p, trials, &workers)?;
            // Chained verifications may all be in already.
            return self.close_evaluation();
        }
        // The final evaluation (of the last version) closes a stopping run.
        Ok(self.stop_reason.is_some() && p.version == self.algo.version())
    }

    /// Record the evaluation `rec` of `p` in the checkpoint index and keep its model (with
    /// `manifest`) when it is the best; the first evaluated model is kept whatever its
    /// figures. A verification that holds makes its checkpoint the run's model, whatever an
    /// earlier evaluation's figures were; one that does not hold changes nothing. True when it
    /// is the best.
    fn keep_if_best(
        &mut self,
        p: &PendingEval,
        rec: CheckpointRecord,
        manifest: &Manifest,
        per_world: &[WorldEval],
    ) -> Result<bool, LinkError> {
        let target = self.spec.stop.target_laps.filter(|t| t.laps > 0);
        let is_best = if p.verifying {
            let held = target.is_some_and(|t| self.verification_held(p, &t, per_world));
            if held {
                noted(&self.dir, "the checkpoint index not written", self.dir.record_best(rec.clone()));
            }
            held
        } else {
            noted(&self.dir, "the checkpoint index not written", self.dir.record(rec.clone())).unwrap_or(false)
        };
        self.evals.evaluated_version = Some(p.version);
        if is_best || !self.dir.model_dir().join("manifest.json").exists() {
            noted(
                &self.dir,
                &format!("the best model (v{}) not written; model/ holds the previous best", p.version),
                folder::save_signed(&self.dir.model_dir(), &self.spec.metadata, &p.model, manifest, Some(&self.signer)),
            );
        }
        if is_best {
            self.publish_best(p, manifest)?;
            self.evals.best = Some(rec);
        }
        Ok(is_best)
    }

    /// Whether a verification's trials lap the target's share on every world; one that holds
    /// becomes the run's verified checkpoint, one that does not ends the lap streak.
    fn verification_held(&mut self, p: &PendingEval, t: &TargetLaps, per_world: &[WorldEval]) -> bool {
        let needed = t.needed(self.spec.eval_trials as usize, p.trials as usize);
        let held = verification_holds(per_world, needed, p.trials as usize);
        let mut what = format!(
            "{} (v{}) lapped {} of {} trials on every world in its verification ({needed} needed)",
            p.name,
            p.version,
            min_laps(per_world),
            p.trials
        );
        // A worker stops a verification's trials once it can no longer hold, and drops the
        // checkpoint's other verifications it had queued.
        for (world, .., laps, ran) in per_world.iter().filter(|w| w.4 < p.trials as usize) {
            what += &if *ran == 0 {
                format!("; on {world} it ran none of its {} trials (another world's could no longer hold)", p.trials)
            } else {
                format!("; on {world} it ran {ran} of its {} trials, lapped {laps}, and could no longer hold", p.trials)
            };
        }
        if held {
            tracing::info!(run = %self.spec.name, "verified: {what}");
            self.evals.verified = Some(what);
        } else {
            tracing::warn!(run = %self.spec.name, "not verified, training goes on: {what}");
            self.evals.lap_streak = 0;
        }
        held
    }

    /// The lap streak after a checkpoint's evaluation (see [`lap_streak`]); the trials of the
    /// verification it calls for, if any.
    fn follow_streak(&mut self, min_laps: usize) -> Option<u32> {
        let t = self.spec.stop.target_laps.filter(|t| t.laps > 0)?;
        let eval_trials = self.spec.eval_trials as usize;
        let (streak, verify) = lap_streak(self.evals.lap_streak, &t, min_laps, eval_trials, self.stop_reason.is_some());
        self.evals.lap_streak = streak;
        verify
    }

    /// A checkpoint's evaluation becomes the last one the status shows, and moves the trend
    /// on; a change of verdict is logged.
    fn follow_trend(&mut self, iteration: u64, progress: f64, min_laps: usize, per_world: &[WorldEval]) {
        self.evals.figures = (progress, min_laps as u64);
        self.evals.worlds = per_world.iter().map(|w| (w.0.clone(), (w.1, w.2))).collect();
        let now = self.evals.trend.push(iteration, progress);
        if std::mem::discriminant(&now) != std::mem::discriminant(&self.evals.verdict) {
            match &now {
                Verdict::Improving => tracing::info!(run = %self.spec.name, "evaluation progress improving again"),
                v => tracing::warn!(run = %self.spec.name, "{}", v.describe()),
            }
        }
        self.evals.verdict = now;
    }

    /// Write an evaluation's record (with the folders of its sim-traces) to
    /// `evaluations.jsonl` and the run's logs, and tell the observer.
    fn record_evaluation(&mut self, mut e: EvalRecord, done: &BTreeMap<String, Vec<Trial>>) {
        if let Some(r) = self.recorder.as_mut() {
            e.simtrace =
                noted(&self.dir, "an evaluation's sim-trace, metrics JSON or MCAP not written", r.evaluation(&e, done))
                    .unwrap_or_default();
        }
        noted(
            &self.dir,
            "evaluations.jsonl: an evaluation's line not written",
            self.dir.append_evaluation(&serde_json::to_value(&e).expect("JSON")),
        );
        self.observer.evaluation(&e);
    }

    /// Verify the checkpoint `p` that met the lap target at once, with `trials` trials per
    /// world, each world asked of the worker that evaluated it (it keeps that version) while
    /// it is alive, else of the next in turn. A world whose verification was chained to its
    /// evaluation is not asked again: its worker ran it or is running it (the request is
    /// repeated while unanswered), and a report already in is taken.
    fn verify(&mut self, mut p: PendingEval, trials: u32, workers: &[String]) -> Result<(), LinkError> {
        let spec = self.spec;
        // A chained report in hand counts whoever sent it and wherever they are now.
        let sent: BTreeMap<String, String> =
            spec.worlds.iter().filter_map(|w| Some((w.clone(), p.chained_report(w)?.worker.clone()))).collect();
        let by = std::mem::take(&mut p.by);
        let chain = std::mem::take(&mut p.chain);
        let early = std::mem::take(&mut p.early);
        let mut v = p.verification(trials);
        tracing::info!(run = %spec.name, checkpoint = %v.name, trials, "verifying the checkpoint that met the lap target");
        for world in &spec.worlds {
            match (chain.get(world), sent.get(world).or(by.get(world).filter(|w| workers.contains(w)))) {
                (Some(c), Some(w)) => {
                    v.asked.insert(c.id, (world.clone(), w.clone(), Instant::now(), 1));
                }
                (None, Some(w)) => self.evals.turns.ask_of(&mut v, &mut *self.link, w.clone(), world.clone(), 1)?,
                (_, None) => self.evals.turns.ask(&mut v, &mut *self.link, workers, world.clone(), 1)?,
            }
        }
        self.evals.last_ask = Instant::now();
        self.evals.pending = Some(v);
        for r in early {
            self.evaluated(r)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trial(progress: f64, lap_time: Option<f64>) -> Trial {
        Trial { progress, lap_time, ..Trial::default() }
    }

    /// Issue 50: a checkpoint is due every `eval_seconds` once this process has updated and
    /// the iteration is not saved yet; when stopping, the last version's is due unless it is
    /// evaluated, an evaluation is under way, or no worker is left. Issue 55: a checkpoint
    /// written while another evaluation was under way has its evaluation owed, due as soon as
    /// that one is closed, whatever the clock says.
    #[test]
    fn a_checkpoint_is_due_on_the_clock_and_once_more_when_stopping() {
        // (updated, stopping, saved, elapsed, evaluated, pending, workers, owed, due)
        for (updated, stopping, saved, elapsed, evaluated, pending, workers, owed, due) in [
            (true, false, false, true, false, false, true, false, true),
            (true, false, false, true, false, true, false, false, true),
            (false, false, false, true, false, false, true, false, false),
            (true, false, true, true, false, false, true, false, false),
            (true, false, false, false, false, false, true, false, false),
            (true, true, false, true, false, false, true, false, true),
            (true, true, true, false, false, false, true, false, true),
            (true, true, false, true, true, false, true, false, false),
            (true, true, false, true, false, true, true, false, false),
            (true, true, false, true, false, false, false, false, false),
            (false, true, false, true, false, false, true, false, false),
            (true, false, true, false, false, false, true, true, true),
            (true, false, false, false, false, false, true, true, true),
            (true, false, true, false, false, true, true, true, false),
            (true, false, true, false, false, false, false, true, false),
            (true, true, true, false, true, false, true, true, false),
            (false, false, false, false, false, false, true, true, false),
        ] {
            let c = CheckpointClock {
                updated,
                stopping,
                saved,
                elapsed,
                evaluated,
                pending,
                workers,
                owed,
                in_sight: false,
            };
            assert_eq!(c.due(), due, "{c:?}");
        }
    }

    /// Issue 55: while the lap target is in sight, every new version's checkpoint is due as
    /// soon as no evaluation is under way, before the clock falls; a version already saved, an
    /// evaluation under way, no worker or a stopping run (whose last version has its own rule)
    /// waits as before.
    #[test]
    fn every_version_is_due_while_the_lap_target_is_in_sight() {
        let base = CheckpointClock {
            updated: true,
            stopping: false,
            saved: false,
            elapsed: false,
            evaluated: false,
            pending: false,
            workers: true,
            owed: false,
            in_sight: true,
        };
        // (what differs from `base`, due)
        let table: [(&str, CheckpointClock, bool); 7] = [
            ("in sight, a new version", base, true),
            ("not in sight", CheckpointClock { in_sight: false, ..base }, false),
            ("this version saved", CheckpointClock { saved: true, ..base }, false),
            ("an evaluation under way", CheckpointClock { pending: true, ..base }, false),
            ("no worker", CheckpointClock { workers: false, ..base }, false),
            ("no update here yet", CheckpointClock { updated: false, ..base }, false),
            ("stopping, the version evaluated", CheckpointClock { stopping: true, evaluated: true, ..base }, false),
        ];
        for (what, c, due) in table {
            assert_eq!(c.due(), due, "{what}: {c:?}");
        }
    }

    /// Issue 50: each world is summarised from its own trials, in the run's order; a world
    /// without trials counts none, and the weakest world's laps are the evaluation's.
    #[test]
    fn each_world_is_summarised_from_its_trials() {
        let worlds: Vec<String> = ["a", "b"].map(String::from).to_vec();
        // (trials per world, per world (progress, lap time, laps, trials), fewest laps)
        for (done, want, fewest) in [
            (
                vec![("a", vec![trial(100.0, Some(10.0)), trial(100.0, Some(12.0))]), ("b", vec![trial(50.0, None)])],
                vec![(100.0, Some(11.0), 2, 2), (50.0, None, 0, 1)],
                0,
            ),
            (
                vec![("a", vec![trial(100.0, Some(10.0))]), ("b", vec![trial(100.0, Some(20.0))])],
                vec![(100.0, Some(10.0), 1, 1), (100.0, Some(20.0), 1, 1)],
                1,
            ),
            (vec![("b", vec![trial(100.0, Some(9.0))])], vec![(0.0, None, 0, 0), (100.0, Some(9.0), 1, 1)], 0),
        ] {
            let done: BTreeMap<String, Vec<Trial>> = done.into_iter().map(|(w, t)| (w.to_string(), t)).collect();
            let got = per_world(&worlds, &done);
            let figures: Vec<_> = got.iter().map(|w| (w.1, w.2, w.3, w.4)).collect();
            assert_eq!(figures, want, "{done:?}");
            assert_eq!(got.iter().map(|w| w.0.as_str()).collect::<Vec<_>>(), ["a", "b"]);
            assert_eq!(min_laps(&got), fewest);
        }
        assert_eq!(min_laps(&[]), 0);
    }

    /// Issue 50: an evaluation that laps the target's share on every world lengthens the
    /// streak (one that does not ends it), and a streak as long as the target's evaluations
    /// calls for a verification, unless the target verifies nothing or the run is stopping.
    #[test]
    fn the_lap_streak_calls_for_a_verification_once_long_enough() {
        let target = |laps, evaluations, verify_trials| TargetLaps { laps, evaluations, verify_trials };
        // (streak, target, fewest laps, eval trials, stopping, streak after, verification)
        for (streak, t, fewest, trials, stopping, after, verify) in [
            (0, target(3, 2, 10), 3, 3, false, 1, None),
            (1, target(3, 2, 10), 3, 3, false, 2, Some(10)),
            (1, target(3, 2, 10), 2, 3, false, 0, None),
            (5, target(2, 1, 10), 2, 3, false, 6, Some(10)),
            (0, target(1, 0, 4), 1, 3, false, 1, Some(4)),
            (1, target(3, 2, 0), 3, 3, false, 2, None),
            (1, target(3, 2, 10), 3, 3, true, 2, None),
            (0, target(5, 1, 10), 3, 3, false, 1, Some(10)),
        ] {
            assert_eq!(lap_streak(streak, &t, fewest, trials, stopping), (after, verify), "{streak} {t:?} {fewest}");
        }
    }

    /// Issue 50: a verification holds when every world lapped the laps needed and all its
    /// trials are in.
    #[test]
    fn a_verification_holds_when_every_world_laps_enough_of_all_its_trials() {
        let world = |laps, trials| ("w".to_string(), 100.0, None, laps, trials);
        // (per world (laps, trials), needed, trials, holds)
        for (worlds, needed, trials, holds) in [
            (vec![(10, 10), (7, 10)], 7, 10, true),
            (vec![(10, 10), (6, 10)], 7, 10, false),
            (vec![(10, 10), (0, 0)], 0, 10, false),
            (vec![(9, 9)], 7, 10, false),
            (vec![], 7, 10, true),
        ] {
            let per: Vec<WorldEval> = worlds.iter().map(|&(l, t)| world(l, t)).collect();
            assert_eq!(verification_holds(&per, needed, trials), holds, "{worlds:?}");
        }
    }

    /// A verification is lost as soon as one world whose trials are in lapped fewer than
    /// needed (a worker that gave up sends the trials it ran), whatever the worlds still out.
    #[test]
    fn a_verification_is_lost_once_one_world_in_lapped_too_few() {
        let trials = |laps: usize, ran: usize| -> Vec<Trial> {
            (0..ran).map(|i| if i < laps { trial(100.0, Some(12.0)) } else { trial(40.0, None) }).collect()
        };
        // (worlds in (laps, trials ran), needed, lost)
        for (worlds, needed, lost) in [
            (vec![], 10, false),
            (vec![(10, 10)], 10, false),
            (vec![(10, 10), (0, 1)], 10, true),
            (vec![(0, 1)], 10, true),
            (vec![(7, 10), (8, 10)], 7, false),
            (vec![(6, 10)], 7, true),
            (vec![(0, 0)], 1, true),
        ] {
            let done: BTreeMap<String, Vec<Trial>> =
                worlds.iter().enumerate().map(|(i, &(l, r))| (format!("w{i}"), trials(l, r))).collect();
            assert_eq!(verification_lost(&done, needed), lost, "{worlds:?}");
        }
    }
}
