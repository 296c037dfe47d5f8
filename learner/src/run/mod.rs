//! One training run, whatever carries its messages.
//!
//! [`run`] is the whole of training: open (new, resume or clone) the run folder, publish
//! every policy version, grant the workers the episodes the next update needs (flow
//! control), gather experience (dropping duplicates and stale episodes, and counting them),
//! update (the algorithm, PPO or SAC, alone or with a learner team), ask the workers for
//! evaluation trials on every world, keep checkpoints and the best model, write metrics, and
//! stop on any [`StopRules`] condition. It talks to the workers through a [`Link`]:
//! `coordinator train` passes in-process channels to a worker thread; `learner serve` passes
//! Zenoh. The loop is the same; only the link differs. The run knows its algorithm only
//! through [`crate::algorithm::Algorithm`].
//!
//! The parts, by what each does:
//! - `spec.rs`, `link.rs`: what a run is given and gives back, and how it reaches the
//!   outside ([`RunSpec`], [`Start`], [`Summary`], [`RunFailure`]; [`Link`], [`Inbound`],
//!   [`Observer`]);
//! - `state.rs`, `open.rs`: the state every handler shares and what it has counted, and how
//!   a run opens (its folder, model, inputs, signing key and algorithm);
//! - `handlers.rs`: a message arrived, an update is due, the stop check;
//! - `evaluation.rs`, `pending.rs`: checkpoints, their evaluations on the workers, the best
//!   model, the lap streak, verification and the trend;
//! - `publish.rs`: publication (every version, a new best) and the grant rounds;
//! - `status.rs`: the run's figures ([`RunStatus`]) and the end of the run.
//!
//! The pure rules are modules or functions of their own, tested on tables beside them: the
//! experience buffer and its stale rule (`buffer.rs`), the grant rounds (`grants.rs`), the
//! stop rules (`stop.rs`), and in the parts above, when a checkpoint is due, each world's
//! summary, the lap streak, a verification, when a stopping run is over, the status's
//! windows and how the folder is opened.
//!
//! Flow control: for each policy version the learner grants the live workers, between them,
//! the episodes it still needs for the next update ([`policy::exchange::Credit`]). A worker
//! starts no more episodes than it was granted, so what is simulated is what is trained on;
//! the episodes a worker had running when its grant ran out finish under the next grant, one
//! version old. When a worker goes away before delivering its share, a new round re-grants
//! the shortfall to those still alive. Off-policy (SAC), every episode is kept whatever
//! version acted, and the next round is granted while an update runs.

mod buffer;
mod evaluation;
mod grants;
mod handlers;
mod link;
mod open;
mod pending;
mod publish;
mod spec;
mod state;
mod status;
mod stop;

pub use link::{Inbound, Link, LinkError, Observer, Quiet};
pub use spec::{RunFailure, RunSpec, Start, Summary};
pub use status::{RunStatus, WorldFigures};
pub use stop::{Standing, StopRules, TargetLaps, VERIFY_TRIALS};

use state::Run;
use std::time::Duration;

/// Train until a stop rule, a stop message or a failure. Returns how it ended; the final
/// checkpoint and the best model are in the run folder.
pub fn run(spec: &RunSpec, link: &mut dyn Link, observer: &mut dyn Observer) -> Result<Summary, RunFailure> {
    let mut r = Run::open(spec, link, observer)?;
    loop {
        let timeout = if r.update_ready() { Duration::ZERO } else { Duration::from_millis(50) };
        if let Some(m) = r.link.next(timeout)? {
            r.receive(m)?;
            // Everything else already waiting, before an update holds the loop: an
            // evaluation report behind a round of experience would otherwise wait a whole
            // update, and a long one (SAC from pixels) makes it look lost.
            r.drain()?;
        }
        // An evaluation or verification whose reports are in is judged before another update
        // holds the loop: a verification that holds ends the run now, not an update later.
        // (The other stop rules wait for the update: the episodes that met a budget are
        // trained on.)
        let workers = r.link.workers();
        if r.close_evaluation()? || (r.evals.verified.is_some() && r.should_stop(&workers)) {
            break;
        }
        if r.update_if_ready()? {
            // And what arrived during the update, before an evaluation is judged lost.
            r.drain()?;
        }
        let workers = r.link.workers();
        // The checkpoint before the grant: an evaluation that goes first
        // (`RunSpec::checks_first`) is asked for before any episodes.
        r.checkpoint_if_due(&workers)?;
        r.grant(&workers)?;
        r.chase_evaluation(&workers)?;
        if r.close_evaluation()? || r.should_stop(&workers) {
            break;
        }
        r.report()?;
    }
    r.finish()
}
