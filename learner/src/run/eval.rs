//! Evaluations under way: one request per world of a checkpoint, asked of the workers in
//! turn, repeated while unanswered and moved to another worker when one goes away.

use super::{Link, LinkError, RunSpec};
use policy::ActorCritic;
use policy::exchange::{EvalRequest, Trial};
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
}

impl PendingEval {
    /// The request for `world`'s trials of this checkpoint, as request `id` to `worker`.
    pub(super) fn request(&self, spec: &RunSpec, id: u64, worker: &str, world: &str) -> EvalRequest {
        EvalRequest {
            id,
            worker: worker.into(),
            version: self.version,
            world: world.into(),
            trials: spec.eval_trials,
            seed: spec.seed ^ self.iteration,
        }
    }
}

/// Who is asked next, and the next request id.
#[derive(Default)]
pub(super) struct EvalTurns {
    turn: usize,
    ids: u64,
}

impl EvalTurns {
    /// Ask the next worker in turn for `world`'s trials (this is attempt `attempts`).
    pub(super) fn ask(
        &mut self,
        p: &mut PendingEval,
        link: &mut dyn Link,
        spec: &RunSpec,
        workers: &[String],
        world: String,
        attempts: u32,
    ) -> Result<(), LinkError> {
        let w = workers[self.turn % workers.len()].clone();
        self.turn += 1;
        self.ids += 1;
        link.request_eval(&p.request(spec, self.ids, &w, &world))?;
        p.asked.insert(self.ids, (world, w, Instant::now(), attempts));
        Ok(())
    }

    /// A request that failed or went unanswered: ask another worker, or, after three
    /// attempts (or with nobody left), count the world as evaluated without trials.
    pub(super) fn retry(
        &mut self,
        p: &mut PendingEval,
        link: &mut dyn Link,
        spec: &RunSpec,
        workers: &[String],
        world: String,
        attempts: u32,
    ) -> Result<(), LinkError> {
        if attempts >= 3 || workers.is_empty() {
            p.done.insert(world, Vec::new());
            Ok(())
        } else {
            self.ask(p, link, spec, workers, world, attempts + 1)
        }
    }
}
