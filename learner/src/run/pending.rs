//! Evaluations under way: one request per world of a checkpoint, asked of the workers in
//! turn, repeated while unanswered and moved to another worker when one goes away. A
//! verification is the same checkpoint evaluated again with more trials and fresh noise, asked
//! of the worker that evaluated each world (it keeps the versions it evaluated). When meeting
//! the lap target would call for a verification, each world's request carries it chained: the
//! worker runs it as soon as that world's trials lap enough, and its report waits here until
//! the evaluation closes and the verification is asked for.

use super::link::{Link, LinkError};
use super::spec::RunSpec;
use policy::ActorCritic;
use policy::exchange::{ChainedVerify, EvalReport, EvalRequest, Trial};
use policy::folder::Manifest;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// How long a worker has to answer an evaluation request before another is asked.
pub(super) const EVAL_TIMEOUT: Duration = Duration::from_secs(180);
/// How often an unanswered evaluation request is repeated.
pub(super) const EVAL_REPEAT: Duration = Duration::from_secs(3);

/// An evaluation under way: one request per world.
pub(super) struct PendingEval {
    pub(super) iteration: u64,
    pub(super) version: u64,
    pub(super) model: ActorCritic,
    pub(super) manifest: Manifest,
    pub(super) name: String,
    pub(super) asked: BTreeMap<u64, (String, String, Instant, u32)>, // id -> (world, worker, when, attempts)
    pub(super) done: BTreeMap<String, Vec<Trial>>,
    /// Per world, the worker whose trials are in `done`.
    pub(super) by: BTreeMap<String, String>,
    /// Trials per world.
    pub(super) trials: u32,
    /// The evaluation's noise.
    pub(super) seed: u64,
    /// This is the verification of a checkpoint that met the lap target.
    pub(super) verifying: bool,
    /// Per world, the verification chained to its request (none when meeting the target would
    /// not call for one).
    pub(super) chain: BTreeMap<String, ChainedVerify>,
    /// Reports of chained verifications that came before this evaluation closed.
    pub(super) early: Vec<EvalReport>,
}

/// What makes a verification's noise differ from its checkpoint's first evaluation.
const VERIFY_SEED: u64 = 0x5eed_0f7e_51f1_ed00;

impl PendingEval {
    /// A checkpoint's evaluation.
    pub(super) fn new(
        spec: &RunSpec,
        iteration: u64,
        version: u64,
        model: ActorCritic,
        manifest: Manifest,
        name: String,
    ) -> Self {
        PendingEval {
            iteration,
            version,
            model,
            manifest,
            name,
            asked: BTreeMap::new(),
            done: BTreeMap::new(),
            by: BTreeMap::new(),
            trials: spec.eval_trials,
            seed: spec.seed ^ iteration,
            verifying: false,
            chain: BTreeMap::new(),
            early: Vec::new(),
        }
    }

    /// Chain to each world's request the verification of `trials` trials that this
    /// checkpoint's [`verification`](Self::verification) would ask for, run once that
    /// world's trials lap `laps`.
    pub(super) fn chain_verification(&mut self, turns: &mut EvalTurns, worlds: &[String], trials: u32, laps: u32) {
        let seed = self.seed ^ VERIFY_SEED;
        for world in worlds {
            self.chain.insert(world.clone(), ChainedVerify { id: turns.next_id(), trials, seed, laps });
        }
    }

    /// The report in hand of `world`'s chained verification.
    pub(super) fn chained_report(&self, world: &str) -> Option<&EvalReport> {
        let c = self.chain.get(world)?;
        self.early.iter().find(|r| r.id == c.id && r.world == world)
    }

    /// A chained verification's report, come before this evaluation closed.
    pub(super) fn is_chained(&self, r: &EvalReport) -> bool {
        !self.verifying && r.version == self.version && self.chain.get(&r.world).is_some_and(|c| c.id == r.id)
    }

    /// The verification of this (finished) evaluation's checkpoint: `trials` trials per world.
    pub(super) fn verification(self, trials: u32) -> Self {
        PendingEval {
            asked: BTreeMap::new(),
            done: BTreeMap::new(),
            by: BTreeMap::new(),
            trials,
            seed: self.seed ^ VERIFY_SEED,
            verifying: true,
            chain: BTreeMap::new(),
            early: Vec::new(),
            ..self
        }
    }

    /// The request for `world`'s trials of this checkpoint, as request `id` to `worker`.
    pub(super) fn request(&self, id: u64, worker: &str, world: &str) -> EvalRequest {
        EvalRequest {
            id,
            worker: worker.into(),
            version: self.version,
            world: world.into(),
            trials: self.trials,
            seed: self.seed,
            then_verify: self.chain.get(world).copied(),
        }
    }
}

/// Who is asked next, and the next request id.
pub(super) struct EvalTurns {
    turn: usize,
    ids: u64,
}

impl Default for EvalTurns {
    /// Ids start at random: a worker keeps the reports it sent by id, and a restarted
    /// learner's requests must not be answered with the last run's.
    fn default() -> Self {
        EvalTurns { turn: 0, ids: rand::random::<u64>() >> 8 }
    }
}

impl EvalTurns {
    /// A request id not used before in this run.
    pub(super) fn next_id(&mut self) -> u64 {
        self.ids += 1;
        self.ids
    }

    /// Ask the next worker in turn for `world`'s trials (this is attempt `attempts`).
    pub(super) fn ask(
        &mut self,
        p: &mut PendingEval,
        link: &mut dyn Link,
        workers: &[String],
        world: String,
        attempts: u32,
    ) -> Result<(), LinkError> {
        let w = workers[self.turn % workers.len()].clone();
        self.turn += 1;
        self.ask_of(p, link, w, world, attempts)
    }

    /// Ask `worker` for `world`'s trials (this is attempt `attempts`).
    pub(super) fn ask_of(
        &mut self,
        p: &mut PendingEval,
        link: &mut dyn Link,
        worker: String,
        world: String,
        attempts: u32,
    ) -> Result<(), LinkError> {
        let id = self.next_id();
        link.request_eval(&p.request(id, &worker, &world))?;
        p.asked.insert(id, (world, worker, Instant::now(), attempts));
        Ok(())
    }

    /// A request that failed or went unanswered: ask another worker, or, after three
    /// attempts (or with nobody left), count the world as evaluated without trials.
    pub(super) fn retry(
        &mut self,
        p: &mut PendingEval,
        link: &mut dyn Link,
        workers: &[String],
        world: String,
        attempts: u32,
    ) -> Result<(), LinkError> {
        if attempts >= 3 || workers.is_empty() {
            p.done.insert(world, Vec::new());
            Ok(())
        } else {
            self.ask(p, link, workers, world, attempts + 1)
        }
    }
}
