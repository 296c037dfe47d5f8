//! The sim worker: the learner's peer. It drives a vector of environments with the policy
//! versions the learner publishes, starts only the episodes the learner granted
//! ([`Credit`]), delivers them as [`Experience`], and runs the evaluation trials the learner
//! asks for ([`EvalRequest`]) when it has no grant to spend, or before its next round of
//! episodes once an evaluation has waited through one.
//!
//! [`Worker::drive`] is the worker's one loop. It reads and writes through a
//! [`WorkerLink`]: `coordinator train` passes in-process channels, `sim-agent serve` passes
//! Zenoh. A worker may drive several worlds at once (environment `i` drives world
//! `i + offset mod k`), so an agent with fewer peers than worlds never has to hop between
//! worlds and lose the episodes it had running. The coordinator's adaptive schedule may
//! weigh the worlds ([`WorkerInbound::Weights`]): each world then gets its share of the
//! environments ([`shares`]), and the fewest environments move ([`replan`]), each when its
//! running episode ends.

use crate::config::SimConfig;
use crate::reward::{RewardError, RewardFn};
use crate::rollout::{Collector, EvalPlan, TrialResult, evaluate_groups};
use crate::vec_env::VecEnv;
use crate::{EnvError, EnvSpec, EvalRules};
use policy::exchange::{Credit, EvalReport, EvalRequest, Experience, PolicyVersion, Trial};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Why a worker stopped.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The reward function failed (its traceback is in the message).
    #[error(transparent)]
    Reward(#[from] RewardError),
    /// The environments could not be built.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// The link failed.
    #[error("link: {0}")]
    Link(String),
}

/// What reaches a worker.
#[derive(Clone)]
pub enum WorkerInbound {
    /// A policy version to act with.
    Policy(PolicyVersion),
    /// A grant (re-sent every second; repeats are ignored).
    Credit(Credit),
    /// Evaluation trials to run.
    Eval(EvalRequest),
    /// Each world's share of the environments (the coordinator's adaptive schedule).
    Weights(Vec<f64>),
    /// Stop driving (the assignment ended, or the run did).
    End,
}

/// What a worker sends.
#[derive(Clone, Debug)]
pub enum WorkerOutbound {
    /// Episodes.
    Experience(Experience),
    /// Evaluation trials.
    Eval(EvalReport),
}

/// How a worker reaches its learner.
pub trait WorkerLink {
    /// The next message, waiting at most `timeout`. `need_policy` is true while the worker
    /// has no policy to act with (a networked link may ask for the latest one).
    fn next(&mut self, timeout: Duration, need_policy: bool) -> Result<Option<WorkerInbound>, WorkerError>;
    /// Send a result.
    fn send(&mut self, out: WorkerOutbound) -> Result<(), WorkerError>;
}

/// What a worker is built from.
pub struct WorkerSetup {
    /// The worker's id (the learner grants by it).
    pub id: String,
    /// The worlds to drive.
    pub worlds: Vec<EnvSpec>,
    /// Which world environment 0 drives (spreads several workers over the worlds).
    pub offset: usize,
    /// Each world's share of the environments (empty: round-robin from `offset`).
    pub weights: Vec<f64>,
    /// Environments.
    pub envs: usize,
    /// Threads for them.
    pub threads: usize,
    /// The simulator configuration (observation included).
    pub cfg: Arc<SimConfig>,
    /// The reward function.
    pub reward: RewardFn,
    /// The action space (the job's `model_metadata.json`).
    pub space: policy::ActionSpace,
    /// Seed.
    pub seed: u64,
    /// Sequence number of the first experience batch (carry it over from a previous worker
    /// of the same process so the learner's duplicate check holds).
    pub first_seq: u64,
    /// The GPU the policy acts on over the environments (`None`: faer).
    pub gpu: Option<Arc<gpu::Gpu>>,
}

/// One request's part of a batch of checks: its trials and whether all of them ran, or why
/// they could not.
type Ran = Result<(Vec<Trial>, bool), String>;

/// Policy versions kept for evaluation requests that arrive late.
const KEEP_VERSIONS: usize = 4;
/// Evaluation reports kept to answer repeated requests.
const KEEP_REPORTS: usize = 16;
/// Versions kept after evaluating them: a checkpoint that met the lap target is verified next,
/// by the worker that evaluated it, however far training has moved on.
const KEEP_EVALUATED: usize = 2;

/// A worker: environments, the policy versions it holds, its grant, its evaluation queue.
pub struct Worker {
    id: String,
    collector: Collector,
    /// The configuration evaluations and verifications run with (see
    /// [`crate::race::RaceConfig::for_checks`]).
    check_cfg: Arc<SimConfig>,
    worlds: Vec<EnvSpec>,
    /// The world each environment drives, or will once its episode ends.
    plan: Vec<usize>,
    threads: usize,
    versions: VecDeque<PolicyVersion>,
    /// The versions evaluated last.
    evaluated: VecDeque<PolicyVersion>,
    /// (version, round) of the newest grant seen, and the episodes left to start in it.
    grant: Option<(u64, u64, u64)>,
    /// Evaluation requests, each with whether the worker collected a round of episodes while
    /// it waited (it then runs before the next round).
    evals: VecDeque<(EvalRequest, bool)>,
    /// The last reports sent, answered again when their request is repeated.
    reports: VecDeque<EvalReport>,
    /// The verifications chained here, each with the misses it can take and still hold: its
    /// trials stop at one more (the learner would not verify the checkpoint).
    may_miss: Vec<(EvalRequest, usize)>,
    /// Reports to send before any work: a repeated request's answer, and the chained
    /// verifications dropped once another of their version's could no longer hold.
    outbox: VecDeque<EvalReport>,
    /// Messages that arrived while a batch of checks ran, taken before any more work.
    deferred: VecDeque<WorkerInbound>,
    seq: u64,
    steps_reported: u64,
    last_frame: Option<Instant>,
}

impl Worker {
    /// Build the environments.
    pub fn new(s: WorkerSetup) -> Result<Worker, WorkerError> {
        if s.worlds.is_empty() {
            return Err(WorkerError::Env(EnvError::Config("a worker needs at least one world".into())));
        }
        let k = s.worlds.len();
        let envs = s.envs.max(1);
        let plan: Vec<usize> = if s.weights.len() == k {
            replan(&(0..envs).map(|i| (i + s.offset) % k).collect::<Vec<_>>(), &shares(envs, &s.weights))
        } else {
            (0..envs).map(|i| (i + s.offset) % k).collect()
        };
        let specs: Vec<EnvSpec> = plan.iter().map(|&w| s.worlds[w].clone()).collect();
        let vec = VecEnv::new(specs, s.cfg.clone(), s.seed, s.reward, s.threads)?;
        // What the checks see, where it differs from training: head-to-bot's bots at random,
        // changing lanes; and the camera as `coordinator evaluate` and DeepRacer's evaluation
        // see it, nominal light, texture and pose without image noise (a model verified only
        // under randomised frames can miss laps in the nominal ones).
        let race = s.cfg.race.for_checks();
        let camera =
            s.cfg.camera.randomize.then(|| crate::config::CameraConfig { randomize: false, ..s.cfg.camera.clone() });
        if let Some(race) = &race {
            tracing::info!(
                "evaluations and verifications place the {} bots at random and let them change lanes \
                 (race.randomize_bot_car_locations and race.is_lane_change hold for training only)",
                race.number_of_bot_cars
            );
        }
        if camera.is_some() {
            tracing::info!(
                "evaluations and verifications see the camera's nominal light, texture and pose \
                 (camera.randomize holds for training only)"
            );
        }
        let check_cfg = match (race, camera) {
            (None, None) => s.cfg,
            (race, camera) => Arc::new(SimConfig {
                race: race.unwrap_or_else(|| s.cfg.race.clone()),
                camera: camera.unwrap_or_else(|| s.cfg.camera.clone()),
                ..(*s.cfg).clone()
            }),
        };
        Ok(Worker {
            id: s.id,
            collector: match s.gpu {
                Some(g) => Collector::new(vec, s.space, s.seed).with_gpu(g),
                None => Collector::new(vec, s.space, s.seed),
            },
            check_cfg,
            worlds: s.worlds,
            plan,
            threads: s.threads,
            versions: VecDeque::new(),
            evaluated: VecDeque::new(),
            grant: None,
            evals: VecDeque::new(),
            reports: VecDeque::new(),
            may_miss: Vec::new(),
            outbox: VecDeque::new(),
            deferred: VecDeque::new(),
            seq: s.first_seq,
            steps_reported: 0,
            last_frame: None,
        })
    }

    /// The next experience sequence number.
    pub fn seq(&self) -> u64 {
        self.seq
    }

    /// Environment steps simulated so far.
    pub fn env_steps(&self) -> u64 {
        self.collector.env_steps
    }

    /// The newest policy version held.
    pub fn version(&self) -> Option<u64> {
        self.versions.back().map(|p| p.version)
    }

    /// Take a message.
    pub fn take(&mut self, m: WorkerInbound) {
        match m {
            WorkerInbound::Policy(p) => {
                if self.version() == Some(p.version) {
                    return; // a repeat
                }
                // A version at or below one we hold comes from a restarted learner, which
                // resumed from a checkpoint: its word counts, and what we held beyond it is void.
                self.versions.retain(|v| v.version < p.version);
                self.versions.push_back(p);
                while self.versions.len() > KEEP_VERSIONS {
                    self.versions.pop_front();
                }
            }
            WorkerInbound::Credit(c) => {
                self.drop_closed(c.checks_closed_through);
                // Repeats of the grant in hand are ignored; a new version or a later round replaces it.
                let newer = self.grant.is_none_or(|(v, r, _)| c.version != v || c.round > r);
                if newer {
                    let mine = c.episodes.get(&self.id).copied().unwrap_or(0);
                    self.grant = Some((c.version, c.round, mine));
                }
            }
            WorkerInbound::Eval(r) => {
                if r.worker != self.id || self.evals.iter().any(|(e, _)| same_request(e, &r)) {
                    return;
                }
                tracing::debug!(id = r.id, version = r.version, world = %r.world, "evaluation requested");
                // The learner checks one checkpoint at a time, in the order they were written:
                // asking for a version says the checks of every older one are closed, even
                // where no grant came to say so (a stopping learner grants nothing).
                self.drop_closed(r.version.saturating_sub(1));
                match self.reports.iter().find(|d| answers(d, &r)) {
                    Some(done) => self.outbox.push_back(done.clone()),
                    None => self.evals.push_back((r, false)),
                }
            }
            WorkerInbound::Weights(w) => {
                if w.len() != self.worlds.len() {
                    return;
                }
                let next = replan(&self.plan, &shares(self.plan.len(), &w));
                for (i, (&was, &now)) in self.plan.iter().zip(&next).enumerate() {
                    if was != now {
                        self.collector.move_at_episode_end(i, self.worlds[now].clone());
                    }
                }
                if next != self.plan {
                    tracing::info!(
                        environments = ?self.worlds.iter().enumerate().map(|(k, w)| (w.name.as_str(), next.iter().filter(|&&x| x == k).count())).collect::<Vec<_>>(),
                        "the schedule moves environments between worlds"
                    );
                }
                self.plan = next;
            }
            WorkerInbound::End => {}
        }
    }

    /// Do one piece of work: collect the granted episodes, or run one evaluation. `None`
    /// when there is nothing to do until the next message.
    pub fn work(&mut self) -> Result<Option<WorkerOutbound>, WorkerError> {
        self.work_with(&mut || None)
    }

    /// [`Worker::work`], reading `inbox` while a batch of checks runs: a grant saying the
    /// learner closed the batch's version's checks (or the end) stops it, and what came is
    /// taken before any more work (`None` then, with those messages waiting).
    pub fn work_with(
        &mut self,
        inbox: &mut dyn FnMut() -> Option<WorkerInbound>,
    ) -> Result<Option<WorkerOutbound>, WorkerError> {
        if let Some(r) = self.outbox.pop_front() {
            return Ok(Some(WorkerOutbound::Eval(r)));
        }
        // An evaluation that waited through a round of episodes goes first: an off-policy
        // learner grants the next round while it updates, so a worker always holding a grant
        // would never evaluate.
        if let Some(report) = self.evaluate_ready(true, inbox) {
            return Ok(Some(WorkerOutbound::Eval(report)));
        }
        if !self.deferred.is_empty() {
            return Ok(None);
        }
        // Granted episodes next: the learner is waiting for them.
        if let Some((version, round, left)) = self.grant.filter(|g| g.2 > 0) {
            if let Some(p) = self.versions.iter().rev().find(|p| p.version == version).cloned() {
                let t0 = Instant::now();
                tracing::debug!(version, round, episodes = left, "collecting");
                let trajectories = self.collector.collect(&p.model, p.version, left as usize)?;
                tracing::debug!(
                    version,
                    round,
                    episodes = trajectories.len(),
                    seconds = t0.elapsed().as_secs_f64(),
                    "collected"
                );
                self.grant = Some((version, round, 0));
                for (_, waited) in self.evals.iter_mut() {
                    *waited = true;
                }
                self.seq += 1;
                let env_steps = self.collector.env_steps - self.steps_reported;
                self.steps_reported = self.collector.env_steps;
                let frame = self.frame(p.version);
                return Ok(Some(WorkerOutbound::Experience(Experience {
                    worker: self.id.clone(),
                    seq: self.seq,
                    credit: (version, round),
                    trajectories,
                    env_steps,
                    seconds: t0.elapsed().as_secs_f64(),
                    frame,
                })));
            }
            if self.version().is_some_and(|v| v > version) {
                self.grant = Some((version, round, 0)); // a grant for a version we moved past
            }
        }
        Ok(self.evaluate_ready(false, inbox).map(WorkerOutbound::Eval))
    }

    /// Messages that arrived while a batch of checks ran, oldest first.
    pub fn take_deferred(&mut self) -> Option<WorkerInbound> {
        self.deferred.pop_front()
    }

    /// The learner closed every check of the versions up to `through`: their evaluations and
    /// verifications still queued here are dropped, unanswered (it asks no more of them).
    fn drop_closed(&mut self, through: u64) {
        if through == 0 {
            return; // none said (version 0 is never checked)
        }
        let before = self.evals.len();
        self.evals.retain(|(e, _)| e.version > through);
        self.may_miss.retain(|(e, _)| e.version > through);
        if self.evals.len() < before {
            tracing::debug!(through, dropped = before - self.evals.len(), "checks closed by the learner: dropped");
        }
    }

    /// Run the first evaluation whose version we hold (or can no longer hold), of those that
    /// waited through a round of episodes when `waited_only`, and with it, as one batch, the
    /// same checkpoint's other requests of its kind queued here (evaluations, or chained
    /// verifications): three worlds' few trials each fill the cores together. The first
    /// report is returned, the others wait in the outbox.
    fn evaluate_ready(
        &mut self,
        waited_only: bool,
        inbox: &mut dyn FnMut() -> Option<WorkerInbound>,
    ) -> Option<EvalReport> {
        let newest = self.version();
        let ready = self.evals.iter().position(|(r, w)| (*w || !waited_only) && newest.is_some_and(|v| r.version <= v));
        let (first, _) = self.evals.remove(ready?).expect("found");
        let chained =
            |may_miss: &[(EvalRequest, usize)], e: &EvalRequest| may_miss.iter().any(|(m, _)| same_request(m, e));
        let kind = chained(&self.may_miss, &first);
        let (mates, rest): (VecDeque<_>, VecDeque<_>) = std::mem::take(&mut self.evals)
            .into_iter()
            .partition(|(e, _)| e.version == first.version && chained(&self.may_miss, e) == kind);
        self.evals = rest;
        let batch: Vec<EvalRequest> = std::iter::once(first).chain(mates.into_iter().map(|(e, _)| e)).collect();
        for r in &batch {
            tracing::debug!(id = r.id, version = r.version, world = %r.world, "evaluating");
        }
        let held = self.versions.iter().chain(&self.evaluated).find(|p| p.version == batch[0].version).cloned();
        let results: Vec<Ran> = match held {
            Some(p) => {
                let results = self.evaluate(&p, &batch, inbox);
                if !self.evaluated.iter().any(|e| e.version == p.version) {
                    self.evaluated.push_back(p);
                    while self.evaluated.len() > KEEP_EVALUATED {
                        self.evaluated.pop_front();
                    }
                }
                match results {
                    Some(results) => results,
                    None => {
                        // The learner closed this version's checks: nobody waits for them.
                        tracing::debug!(version = batch[0].version, "checks closed by the learner: stopped");
                        self.may_miss.retain(|(m, _)| !batch.iter().any(|r| same_request(m, r)));
                        return None;
                    }
                }
            }
            None => {
                let why = format!("policy v{} is no longer held by {}", batch[0].version, self.id);
                batch.iter().map(|_| Err(why.clone())).collect()
            }
        };
        // Verifications are chained only when every world evaluated here lapped enough: the
        // learner verifies a checkpoint only when all of them did.
        let missed = batch
            .iter()
            .zip(&results)
            .find(|(r, t)| r.then_verify.is_some() && t.as_ref().ok().and_then(|(t, _)| r.chained(t)).is_none());
        match missed {
            Some((r, t)) => self.chain(r, t.as_ref().ok().map(|(t, _)| t.as_slice())),
            None => {
                for (r, t) in batch.iter().zip(&results) {
                    self.chain(r, t.as_ref().ok().map(|(t, _)| t.as_slice()));
                }
            }
        }
        let mut reports: Vec<EvalReport> = Vec::new();
        for (r, t) in batch.into_iter().zip(results) {
            let trials = match t {
                // Stopped by another world's verification, which can no longer hold.
                Ok((t, false)) if !self.gave_up(&r, &t) => {
                    tracing::debug!(
                        id = r.id,
                        version = r.version,
                        world = %r.world,
                        "chained verification dropped: another world's can no longer hold"
                    );
                    self.may_miss.retain(|(m, _)| !same_request(m, &r));
                    Ok(Vec::new())
                }
                Ok((t, _)) => {
                    self.drop_if_missed(&r, &t);
                    Ok(t)
                }
                Err(e) => Err(e),
            };
            let report = EvalReport { id: r.id, worker: self.id.clone(), version: r.version, world: r.world, trials };
            self.keep_report(&report);
            reports.push(report);
        }
        let mut reports = reports.into_iter();
        let first = reports.next();
        // The batch's other reports go before anything a drop queued.
        for (i, r) in reports.enumerate() {
            self.outbox.insert(i, r);
        }
        first
    }

    /// Whether chained verification `r` gave up: its `trials` missed more than it may miss
    /// (false for a request that is not a chained verification).
    fn gave_up(&self, r: &EvalRequest, trials: &[Trial]) -> bool {
        let missed = trials.len().saturating_sub(policy::exchange::summarise(trials).2);
        self.may_miss.iter().find(|(e, _)| same_request(e, r)).is_some_and(|&(_, k)| missed > k)
    }

    /// Keep `report` to answer its request again.
    fn keep_report(&mut self, report: &EvalReport) {
        self.reports.push_back(report.clone());
        while self.reports.len() > KEEP_REPORTS {
            self.reports.pop_front();
        }
    }

    /// After chained verification `r` ran `trials`: when it can no longer hold, the
    /// verifications of its version still queued here are dropped, each answered with no
    /// trials. The learner verifies a checkpoint only when every world holds, so their trials
    /// could not change its verdict; dropping them hands the cores back to training, and the
    /// learner closes the verification and evaluates its next checkpoint sooner.
    fn drop_if_missed(&mut self, r: &EvalRequest, trials: &[Trial]) {
        let Some(&(_, may_miss)) = self.may_miss.iter().find(|(e, _)| same_request(e, r)) else { return };
        if !cannot_hold(r.trials, may_miss, trials) {
            return;
        }
        // The version's chained verifications (those `may_miss` lists) still queued.
        let chained = |e: &EvalRequest| e.version == r.version && self.may_miss.iter().any(|(m, _)| same_request(m, e));
        let (dropped, kept): (VecDeque<_>, VecDeque<_>) =
            std::mem::take(&mut self.evals).into_iter().partition(|(e, _)| chained(e));
        self.evals = kept;
        for (e, _) in dropped {
            tracing::debug!(
                id = e.id,
                version = e.version,
                world = %e.world,
                "chained verification dropped: the one on {} can no longer hold",
                r.world
            );
            self.may_miss.retain(|(m, _)| !same_request(m, &e));
            let report = EvalReport {
                id: e.id,
                worker: self.id.clone(),
                version: e.version,
                world: e.world,
                trials: Ok(Vec::new()),
            };
            self.keep_report(&report);
            self.outbox.push_back(report);
        }
    }

    /// After evaluation `r` (its `trials`, if it ran): the verification chained to it, when
    /// they lapped enough, runs once this worker's other evaluations of the version are done,
    /// before any episodes (the learner stops the run as soon as it holds). When they did not,
    /// the version's chained verifications already queued here are dropped: the learner
    /// verifies only a checkpoint that met the target on every world.
    fn chain(&mut self, r: &EvalRequest, trials: Option<&[Trial]>) {
        let Some(c) = r.then_verify else { return };
        match trials.and_then(|t| r.chained(t)) {
            Some(v) => {
                if self.evals.iter().any(|(e, _)| same_request(e, &v)) || self.reports.iter().any(|d| answers(d, &v)) {
                    return;
                }
                tracing::debug!(id = v.id, version = v.version, world = %v.world, "verification chained to evaluation {}", r.id);
                // The verification needs the evaluation's share of laps (3 of 3 → 10 of 10).
                let needed = policy::exchange::laps_needed(c.laps as usize, r.trials as usize, v.trials as usize);
                self.may_miss.retain(|(e, _)| self.evals.iter().any(|(q, _)| same_request(q, e)));
                self.may_miss.push((v.clone(), v.trials as usize - needed));
                let mut at = 0;
                for (i, (e, waited)) in self.evals.iter_mut().enumerate() {
                    if e.version == v.version {
                        *waited = true;
                        at = i + 1;
                    }
                }
                self.evals.insert(at, (v, true));
            }
            None => {
                let before = self.evals.len();
                self.evals.retain(|(e, _)| !(e.version == r.version && e.seed == c.seed && e.then_verify.is_none()));
                if self.evals.len() < before {
                    tracing::debug!(
                        version = r.version,
                        "chained verifications dropped: {} missed its target",
                        r.world
                    );
                }
            }
        }
    }

    /// What environment 0's camera sees now, at most once a second (camera jobs only).
    fn frame(&mut self, version: u64) -> Option<policy::exchange::Frame> {
        let v = self.collector.vec_env();
        if v.renderer().is_none()
            || v.is_empty()
            || self.last_frame.is_some_and(|t| t.elapsed() < Duration::from_secs(1))
        {
            return None;
        }
        self.last_frame = Some(Instant::now());
        let dim = v.obs_dim();
        let (width, height) = (crate::camera::WIDTH, crate::camera::HEIGHT);
        // One camera, or the stereo pair (its left camera shown).
        let pixels = (width * height) as usize;
        if dim < pixels || !dim.is_multiple_of(pixels) {
            return None;
        }
        Some(policy::exchange::Frame {
            world: v.envs()[0].spec().name.clone(),
            width,
            height,
            gray: v.observations()[..dim].iter().step_by(dim / pixels).map(|&p| p.clamp(0.0, 255.0) as u8).collect(),
            policy_version: version,
            step: 0,
        })
    }

    /// Run `batch`'s trials (one checkpoint's) side by side: per request, its trials and
    /// whether all of them ran (a chained verification that can no longer hold stops the
    /// batch), or why they could not. `inbox` is read before every step, what it brings kept
    /// for later; `None` when a grant in it said the learner closed the version's checks, or
    /// the run ended (the batch stopped there).
    fn evaluate(
        &mut self,
        p: &PolicyVersion,
        batch: &[EvalRequest],
        inbox: &mut dyn FnMut() -> Option<WorkerInbound>,
    ) -> Option<Vec<Ran>> {
        let mut out: Vec<Option<Ran>> = vec![None; batch.len()];
        let mut groups: Vec<(EnvSpec, EvalPlan)> = Vec::new();
        let mut runs: Vec<usize> = Vec::new();
        for (i, r) in batch.iter().enumerate() {
            // A chained verification's misses it may take (`None`: not a chained verification).
            let may_miss = self.may_miss.iter().find(|(e, _)| same_request(e, r)).map(|(_, k)| *k);
            let spec = match self.worlds.iter().find(|w| w.name == r.world) {
                Some(s) => s.clone(),
                None => match tracks::world(&r.world) {
                    Ok(world) => {
                        // A job drives all its worlds one way round: this worker's show which.
                        let direction = self.worlds.first().map_or(tracks::Direction::Forward, |w| w.track.direction());
                        EnvSpec::from_world(&world, direction)
                    }
                    Err(e) => {
                        let e = WorkerError::Env(EnvError::Config(format!("evaluation world: {e}")));
                        out[i] = Some(Err(format!("{e:#}")));
                        continue;
                    }
                },
            };
            let plan = EvalPlan {
                rules: EvalRules::default(),
                count: r.trials.max(1) as usize,
                seed: r.seed,
                threads: self.threads,
                all_frames: false,
                // With a round granted and not yet collected, a PPO learner is waiting for
                // this worker, not updating: the trials may have every core. (SAC updates
                // while its next round is collected, and these trials then share the cores as
                // collection does.) A check that may stop the run (an evaluation chaining a
                // verification, or the verification) has them too: a learner sharing these
                // cores waits for it (`checks_first`), and one on a machine of its own is not
                // on them.
                spread: self.grant.is_some_and(|(_, _, left)| left > 0)
                    || r.then_verify.is_some()
                    || may_miss.is_some(),
                give_up_after_misses: may_miss,
            };
            groups.push((spec, plan));
            runs.push(i);
        }
        if !groups.is_empty() {
            let (version, me) = (p.version, self.id.clone());
            let mut arrived: Vec<WorkerInbound> = Vec::new();
            let mut closed = false;
            let mut go_on = || {
                while !closed && let Some(m) = inbox() {
                    closed = match &m {
                        WorkerInbound::Credit(c) => c.checks_closed_through >= version,
                        WorkerInbound::Eval(r) => r.worker == me && r.version > version,
                        WorkerInbound::End => true,
                        _ => false,
                    };
                    arrived.push(m);
                }
                !closed
            };
            let ran = evaluate_groups(
                &p.model,
                &p.metadata.action_space,
                &groups,
                &self.check_cfg,
                self.collector.gpu_mut(),
                &mut go_on,
            );
            self.deferred.extend(arrived);
            if closed {
                return None;
            }
            match ran {
                Ok(ran) => {
                    for ((g, (spec, _)), &i) in ran.into_iter().zip(&groups).zip(&runs) {
                        let track_len = spec.track.length();
                        let trials = g
                            .trials
                            .into_iter()
                            .map(|t| {
                                let mut t = Trial { track_len, ..Trial::from(t) };
                                for f in &mut t.frames {
                                    f.policy_version = p.version;
                                }
                                t
                            })
                            .collect();
                        out[i] = Some(Ok((trials, g.complete)));
                    }
                }
                Err(e) => {
                    let e = format!("{:#}", WorkerError::from(e));
                    for &i in &runs {
                        out[i] = Some(Err(e.clone()));
                    }
                }
            }
        }
        Some(out.into_iter().map(|o| o.expect("every request answered")).collect())
    }

    /// The worker's loop: take messages, work, send, until the link says [`WorkerInbound::End`]
    /// or closes.
    pub fn drive(&mut self, link: &mut dyn WorkerLink) -> Result<(), WorkerError> {
        loop {
            // Everything that is waiting, then work; block only when idle.
            loop {
                let m = match self.deferred.pop_front() {
                    Some(m) => Some(m),
                    None => link.next(Duration::ZERO, self.versions.is_empty())?,
                };
                match m {
                    Some(WorkerInbound::End) => return Ok(()),
                    Some(m) => self.take(m),
                    None => break,
                }
            }
            // A batch of checks reads the link as it runs (a link error shows at the next read).
            let out = self.work_with(&mut || link.next(Duration::ZERO, false).ok().flatten())?;
            match out {
                Some(out) => link.send(out)?,
                None if !self.deferred.is_empty() => {}
                None => match link.next(Duration::from_millis(100), self.versions.is_empty())? {
                    Some(WorkerInbound::End) => return Ok(()),
                    Some(m) => self.take(m),
                    None => {}
                },
            }
        }
    }
}

/// Whether a verification of `asked` trials that may miss `may_miss` of them can no longer
/// hold after `trials` (those that ran: a verification stops once it cannot hold, so the
/// trials that did not run count as missed).
pub fn cannot_hold(asked: u32, may_miss: usize, trials: &[Trial]) -> bool {
    (asked as usize).saturating_sub(policy::exchange::summarise(trials).2) > may_miss
}

/// The same request: its id, version and world (a learner's new run draws its ids afresh, and
/// two runs' may meet).
fn same_request(a: &EvalRequest, b: &EvalRequest) -> bool {
    a.id == b.id && a.version == b.version && a.world == b.world
}

/// `report` answers `request` (the same id, version and world).
fn answers(report: &EvalReport, request: &EvalRequest) -> bool {
    report.id == request.id && report.version == request.version && report.world == request.world
}

impl From<TrialResult> for Trial {
    fn from(t: TrialResult) -> Trial {
        Trial {
            progress: t.progress,
            lap_time: t.lap_time,
            off_track: t.off_track,
            crashes: t.crashes,
            overtakes: t.overtakes,
            reward: t.reward,
            steps: t.steps,
            status: t.status.label().to_string(),
            choices: t.log.choices,
            rewards: t.log.rewards,
            trace: t.log.trace,
            track_len: 0.0,
            frames: t.log.frames,
        }
    }
}

/// `envs` environments split by `weights` (largest remainders; every world at least one
/// while there are as many environments as worlds). Weights that are not positive and
/// finite count as none.
pub fn shares(envs: usize, weights: &[f64]) -> Vec<usize> {
    let k = weights.len();
    if k == 0 {
        return Vec::new();
    }
    let w: Vec<f64> = weights.iter().map(|&x| if x.is_finite() && x > 0.0 { x } else { 0.0 }).collect();
    let total: f64 = w.iter().sum();
    let w: Vec<f64> = if total > 0.0 { w.iter().map(|x| x / total).collect() } else { vec![1.0 / k as f64; k] };
    let exact: Vec<f64> = w.iter().map(|x| x * envs as f64).collect();
    let mut out: Vec<usize> = exact.iter().map(|x| x.floor() as usize).collect();
    let mut order: Vec<usize> = (0..k).collect();
    order.sort_by(|&a, &b| (exact[b] - exact[b].floor()).total_cmp(&(exact[a] - exact[a].floor())).then(a.cmp(&b)));
    let left = envs - out.iter().sum::<usize>();
    for &i in order.iter().cycle().take(left) {
        out[i] += 1;
    }
    if envs >= k {
        while let Some(empty) = out.iter().position(|&c| c == 0) {
            let most = (0..k).max_by_key(|&i| (out[i], std::cmp::Reverse(i))).expect("k > 0");
            out[most] -= 1;
            out[empty] += 1;
        }
    }
    out
}

/// The world of each environment after the fewest moves that give world `w` `counts[w]`
/// environments: those already on a world keep it up to its count; the rest go, in order,
/// to the worlds still short.
pub fn replan(current: &[usize], counts: &[usize]) -> Vec<usize> {
    let mut left = counts.to_vec();
    let mut out: Vec<Option<usize>> = current
        .iter()
        .map(|&w| {
            let keep = left.get(w).is_some_and(|&c| c > 0);
            if keep {
                left[w] -= 1;
            }
            keep.then_some(w)
        })
        .collect();
    let mut short = left.iter().enumerate().flat_map(|(w, &c)| std::iter::repeat_n(w, c));
    for o in out.iter_mut().filter(|o| o.is_none()) {
        *o = short.next().or(Some(current.first().copied().unwrap_or(0)));
    }
    out.into_iter().map(|o| o.expect("filled")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use policy::exchange::ChainedVerify;
    use policy::{ActorCritic, ModelMetadata};
    use rand::SeedableRng;

    fn trial(lapped: bool) -> Trial {
        Trial { progress: if lapped { 100.0 } else { 40.0 }, lap_time: lapped.then_some(12.0), ..Trial::default() }
    }

    /// Issue 55: a verification can no longer hold once it missed more of its trials than it
    /// may; the trials a stopped verification did not run count as missed.
    #[test]
    fn a_verification_cannot_hold_once_it_missed_more_than_it_may() {
        // (asked, may miss, trials that ran: lapped or not, cannot hold)
        for (asked, may_miss, ran, want) in [
            (10, 0, vec![true; 10], false),
            (10, 0, vec![true, true, false], true),
            (10, 0, vec![true; 9], true),
            (10, 3, vec![true, true, true, true, true, true, true, false, false, false], false),
            (10, 3, vec![false, false, false, false], true),
            (10, 10, vec![], false),
            (3, 0, vec![], true),
        ] {
            let t: Vec<Trial> = ran.iter().map(|&l| trial(l)).collect();
            assert_eq!(cannot_hold(asked, may_miss, &t), want, "{asked} asked, {may_miss} may miss, {ran:?}");
        }
    }

    /// Issue 55: a checkpoint's chained verifications run as one batch, and once one world's
    /// can no longer hold the batch stops: the worlds whose trials were still running are
    /// answered with none, and the worker goes back to its episodes; verifications that can
    /// still hold all run to the end.
    #[test]
    fn a_verification_that_cannot_hold_drops_its_versions_queued_verifications() {
        let meta = ModelMetadata::default_state_vector();
        let cfg = Arc::new(SimConfig::default());
        let spec = |w: &str| EnvSpec::from_world(&tracks::world(w).unwrap(), tracks::Direction::Forward);
        let obs = crate::obs::obs_dim(&cfg.observation);
        // An untrained policy: its trials leave the track within 50 steps, and lap nothing.
        let model = ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9));
        // (misses each verification may take, the reports in order: id and the trials that
        // came back; the untrained policy's trials end at different steps)
        for (may_miss, want) in [(0, [(11, 1), (12, 0), (13, 1)]), (2, [(11, 2), (12, 2), (13, 2)])] {
            let mut w = Worker::new(WorkerSetup {
                id: "w1".into(),
                worlds: vec![spec("reinvent_base")],
                offset: 0,
                weights: Vec::new(),
                envs: 2,
                threads: 1,
                cfg: cfg.clone(),
                reward: RewardFn::Builtin(crate::BuiltinReward::CenterLine),
                space: meta.action_space.clone(),
                seed: 3,
                first_seq: 0,
                gpu: None,
            })
            .unwrap();
            w.take(WorkerInbound::Policy(PolicyVersion {
                version: 1,
                model: Arc::new(model.clone()),
                metadata: Arc::new(meta.clone()),
            }));
            // Three worlds' verifications of v1, chained here, and another version's evaluation.
            let request = |id: u64, version: u64, world: &str, then_verify: Option<ChainedVerify>| EvalRequest {
                id,
                worker: "w1".into(),
                version,
                world: world.into(),
                trials: 2,
                seed: 77,
                then_verify,
            };
            for (id, world) in [(11, "reinvent_base"), (12, "reinvent_wood"), (13, "reinvent_concrete")] {
                let v = request(id, 1, world, None);
                w.may_miss.push((v.clone(), may_miss));
                w.evals.push_back((v, true));
            }
            let other = request(21, 1, "reinvent_base", Some(ChainedVerify { id: 22, trials: 2, seed: 5, laps: 3 }));
            w.evals.push_back((other, true));
            let mut got = Vec::new();
            while got.len() < 3 {
                let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("a report expected") };
                assert_eq!(r.version, 1);
                let trials = r.trials.unwrap();
                if !trials.is_empty() && may_miss == 0 {
                    assert!(cannot_hold(2, 0, &trials), "{}: only a verification that cannot hold comes back", r.id);
                }
                got.push((r.id, trials.len()));
            }
            assert_eq!(got, want, "each verification may miss {may_miss}");
            // The evaluation that is not a chained verification still runs.
            let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
            assert_eq!((r.id, r.trials.map(|t| t.len())), (21, Ok(2)));
            assert!(w.work().unwrap().is_none());
        }
    }
}
