//! One training run, whatever carries its messages.
//!
//! [`run`] is the whole of training: open (new, resume or clone) the run folder, publish
//! every policy version, grant the workers the episodes the next update needs (flow
//! control), gather experience (dropping duplicates and stale episodes, and counting them),
//! update (PPO, alone or with a learner [`Team`]), ask the workers for evaluation trials on
//! every world, keep checkpoints and the best model, write metrics, and stop on any
//! [`StopRules`] condition. It talks to the workers through a [`Link`]: `coordinator train`
//! passes in-process channels to a worker thread; `learner serve` passes Zenoh. The loop is
//! the same; only the link differs.
//!
//! The run is a state ([`Run`]) and one handler per event, in the order the loop calls them:
//! a message arrived ([`Run::receive`]), an update is due ([`Run::update_if_ready`]), a grant
//! round ([`Run::grant`]), a checkpoint and its evaluation ([`Run::checkpoint_if_due`],
//! [`Run::chase_evaluation`], [`Run::close_evaluation`]), the stop check
//! ([`Run::should_stop`]) and the status ([`Run::report`]). The pure parts are modules of
//! their own, tested on tables: the experience buffer and its stale rule (`buffer`), the
//! grant rounds (`grants`), the stop rules (`stop`); the best-model choice is
//! [`RunDir::record`]. The update is PPO's ([`Ppo`], alone or through a [`Team`]); a second
//! algorithm (an off-policy one such as SAC, whose replay memory replaces the buffer's stale
//! rule) belongs where [`Run::update_if_ready`] calls it, behind the same loop and links.
//!
//! Flow control: for each policy version the learner grants the live workers, between them,
//! the episodes it still needs for the next update ([`Credit`]). A worker starts no more
//! episodes than it was granted, so what is simulated is what is trained on; the episodes a
//! worker had running when its grant ran out finish under the next grant, one version old.
//! When a worker goes away before delivering its share, a new round re-grants the shortfall
//! to those still alive.

mod buffer;
mod eval;
mod grants;
mod stop;

pub use stop::{Standing, StopRules, TargetLaps, VERIFY_TRIALS};

use crate::algorithm::Algorithm;
use crate::algorithm::{LearnerState, Shared};
use crate::checkpoints::{CheckpointRecord, OpenMode, RunDir, RunError};
use crate::hyperparams::Hyperparameters;
use crate::ppo::{Ppo, Refused, UpdateStats};
use crate::record::Recorder;
use crate::sac::SacTrainer;
use crate::trend::{Trend, TrendRules, Verdict};
use buffer::{Admitted, Buffer};
use eval::{EVAL_REPEAT, EVAL_TIMEOUT, EvalTurns, PendingEval};
use faer::Par;
use grants::Grants;
use policy::exchange::{Credit, EvalReport, EvalRequest, Experience, PolicyVersion, Trial, summarise};
use policy::folder::{self, Manifest, Parent};
use policy::signature::Signer;
use policy::{ActorCritic, ModelMetadata, Trajectory};
use rand::SeedableRng;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What a link failed at.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct LinkError(pub String);

/// Why a run could not go on.
#[derive(Debug, thiserror::Error)]
pub enum RunFailure {
    /// The run folder.
    #[error(transparent)]
    Run(#[from] RunError),
    /// A model folder (resume, clone, checkpoint).
    #[error(transparent)]
    Model(#[from] policy::ModelError),
    /// The inputs disagree (resume with another model, say).
    #[error("{0}")]
    Inputs(String),
    /// The transport.
    #[error("link: {0}")]
    Link(#[from] LinkError),
    /// A worker failed (a reward that raised, say): its message, traceback included.
    #[error("worker {worker} failed: {error}")]
    Worker {
        /// The worker.
        worker: String,
        /// What it said.
        error: String,
    },
}

/// What arrives from the workers (and from whoever may stop the run).
#[derive(Clone, Debug)]
pub enum Inbound {
    /// Episodes.
    Experience(Experience),
    /// Evaluation trials.
    Eval(EvalReport),
    /// Stop gracefully (final evaluation, checkpoint and best model), for this reason.
    Stop(String),
    /// A worker cannot go on; the run fails with its message.
    Failed {
        /// The worker.
        worker: String,
        /// Its error, traceback included.
        error: String,
    },
}

/// How the run reaches its workers.
pub trait Link {
    /// Make `policy` the one workers act with (every version is published).
    fn publish(&mut self, policy: &PolicyVersion, manifest: &Manifest, signer: &Signer) -> Result<(), LinkError>;
    /// A new best model (after the evaluation that made it best): cars following "best"
    /// drive it. Default: nothing (no car listens in one process).
    fn best(&mut self, _policy: &PolicyVersion, _manifest: &Manifest, _signer: &Signer) -> Result<(), LinkError> {
        Ok(())
    }
    /// Announce a grant (called again every second: it must be idempotent).
    fn grant(&mut self, credit: &Credit) -> Result<(), LinkError>;
    /// Ask a worker for evaluation trials.
    fn request_eval(&mut self, req: &EvalRequest) -> Result<(), LinkError>;
    /// The next message, waiting at most `timeout`.
    fn next(&mut self, timeout: Duration) -> Result<Option<Inbound>, LinkError>;
    /// The run's figures (after every update and every second).
    fn status(&mut self, status: &RunStatus) -> Result<(), LinkError>;
    /// The workers alive now.
    fn workers(&mut self) -> Vec<String>;
    /// The learners this run's updates are shared with (DD-PPO); `None`: this one alone.
    fn team(&mut self) -> Option<&mut dyn Team> {
        None
    }
}

/// The learners that share a run's updates, as their leader (the learner running [`run`])
/// sees them. Members join and leave between updates; a member lost during an update makes
/// the team's attempt fail, and the leader makes that update again with whoever is left.
pub trait Team {
    /// This iteration's update, made with the members there are (alone when there are none).
    fn update(&mut self, algo: &mut dyn Shared, trajs: &[Trajectory]) -> Result<UpdateStats, Refused>;
    /// Learners in the team besides its leader.
    fn members(&mut self) -> usize {
        0
    }
}

/// Hears about iterations and evaluations (a terminal, a log). Default: nothing.
pub trait Observer {
    /// After every update.
    fn iteration(&mut self, _it: &IterationRecord) {}
    /// After every complete evaluation (all worlds).
    fn evaluation(&mut self, _e: &EvalRecord) {}
}

/// An observer that says nothing.
pub struct Quiet;
impl Observer for Quiet {}

/// How the run folder is opened.
#[derive(Clone, Debug, PartialEq)]
pub enum Start {
    /// A new folder (refused if it holds a run); fresh weights, or the given model folder's
    /// (transfer learning).
    New {
        /// Start from this model folder's weights.
        clone_from: Option<PathBuf>,
    },
    /// Delete the folder and start afresh.
    Force,
    /// Continue from the folder's last checkpoint (refused if there is none).
    Resume,
    /// Continue if the folder holds a run, else start anew (a learner restarted mid-job).
    ResumeOrNew {
        /// Start from this model folder's weights when new.
        clone_from: Option<PathBuf>,
    },
}

/// Everything a run needs to know.
#[derive(Clone)]
pub struct RunSpec {
    /// Names the run in logs and manifests (a job id, or the world).
    pub name: String,
    /// The model's metadata.
    pub metadata: ModelMetadata,
    /// PPO settings.
    pub hyper: Hyperparameters,
    /// Observation length.
    pub obs_size: usize,
    /// The observation settings, for the manifest (the simulator's, as JSON).
    pub observation: serde_json::Value,
    /// The simulator configuration's text, kept in the run folder as `sim.toml`.
    pub sim_toml: String,
    /// The worlds trained on; evaluations run on each.
    pub worlds: Vec<String>,
    /// The run folder.
    pub out: PathBuf,
    /// How to open it.
    pub start: Start,
    /// Seed for fresh weights, minibatch order and evaluation noise.
    pub seed: u64,
    /// Episodes older than this many versions are dropped (and counted).
    pub max_policy_lag: u64,
    /// Evaluation trials per world per checkpoint.
    pub eval_trials: u32,
    /// Seconds between evaluations (and checkpoints).
    pub eval_seconds: f64,
    /// When to stop.
    pub stop: StopRules,
    /// Cores for the update (the camera networks split over them; the MLP does not).
    pub par: Par,
    /// The GPU PPO's update runs on, when it trains alone (`crate::device::open`); `None`:
    /// faer on the CPU.
    pub gpu: Option<std::sync::Arc<gpu::Gpu>>,
    /// A learner team member taking the run over from a leader that went away: its state
    /// (the team's, as of the last update, and SAC's replay memory as bytes), used when it is
    /// newer than the run folder's.
    pub adopt: Option<(LearnerState, Option<Vec<u8>>)>,
    /// The key that signs every published model and model folder (PKCS#8 PEM); `None`: the
    /// run folder's `signing.key`, made on first use (its `signing.pub` is what cars trust).
    pub signing_key: Option<PathBuf>,
    /// The worlds' tracks as lines, drawn in the MCAP log (a world without lines is logged
    /// without its track).
    pub tracks: Vec<policy::TrackLines>,
}

/// One update, as `metrics.jsonl` records it.
#[derive(Clone, Debug, Default, Serialize)]
pub struct IterationRecord {
    /// Iteration (from 1, continuing on resume).
    pub iteration: u64,
    /// Policy version after the update.
    pub policy_version: u64,
    /// Seconds since the start.
    pub time_s: f64,
    /// Episodes in this update.
    pub episodes: usize,
    /// Episodes trained on so far.
    pub total_episodes: u64,
    /// Samples (steps) in this update.
    pub steps: usize,
    /// Environment steps received so far.
    pub env_steps: u64,
    /// Mean episode reward of this update's episodes.
    pub mean_reward: f64,
    /// Mean progress (%) of this update's episodes.
    pub mean_progress: f64,
    /// PPO figures.
    pub policy_loss: f64,
    /// Value loss.
    pub value_loss: f64,
    /// Entropy.
    pub entropy: f64,
    /// Approximate KL.
    pub approx_kl: f64,
    /// Fraction of clipped ratios.
    pub clip_fraction: f64,
    /// Explained variance of the value estimates.
    pub explained_variance: f64,
    /// Seconds spent waiting for this update's experience.
    pub wait_s: f64,
    /// Seconds the update took (forward, backward, Adam).
    pub update_s: f64,
    /// Samples per second of the update alone.
    pub samples_per_s: f64,
    /// Largest policy lag among this update's episodes.
    pub policy_lag: u64,
    /// Episodes received so far (simulated and delivered).
    pub episodes_received: u64,
    /// Episodes dropped as stale so far.
    pub dropped_stale: u64,
    /// Batches dropped as duplicates so far.
    pub dropped_duplicate: u64,
    /// Episodes dropped as malformed so far.
    pub dropped_bad: u64,
    /// Why the update was refused (non-finite loss), if it was.
    pub refused: Option<String>,
    /// Gradient steps the update took.
    pub gradient_steps: usize,
    /// The update stopped at this gradient step, its KL past 1.5 × `target_kl`.
    pub kl_stop: Option<usize>,
    /// The learning rate the update used (`lr` on the job's `lr_schedule`).
    pub lr: f64,
    /// SAC's figures (the Q loss, the temperature, the replay memory); absent for PPO.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sac: Option<crate::sac::SacStats>,
}

/// One evaluation over every world.
#[derive(Clone, Debug, Serialize)]
pub struct EvalRecord {
    /// The iteration whose weights were evaluated.
    pub iteration: u64,
    /// Their policy version.
    pub policy_version: u64,
    /// Per world: mean progress, mean lap time, laps, trials.
    pub worlds: Vec<(String, f64, Option<f64>, usize, usize)>,
    /// Mean progress over every trial.
    pub progress: f64,
    /// Mean lap time when every trial completed.
    pub lap_time: Option<f64>,
    /// Laps completed on the world that completed fewest.
    pub min_laps: usize,
    /// Trials per world.
    pub trials: usize,
    /// This became the best model.
    pub best: bool,
    /// Per world, the folder of its evaluation sim-trace (`evaluation-<YYYYMMDDHHMMSS>`).
    pub simtrace: Vec<(String, String)>,
    /// How the evaluations are going (plateau, collapse), empty while improving.
    pub trend: String,
    /// Crashes in all its trials (obstacles, bots).
    pub crashes: u32,
    /// This is the verification of a checkpoint that met the lap target (its own trials, with
    /// fresh noise), not a new checkpoint's evaluation.
    pub verification: bool,
}

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

/// How a run ended.
#[derive(Clone, Debug)]
pub struct Summary {
    /// Why it stopped.
    pub stop_reason: String,
    /// Updates made (in this process).
    pub iterations: u64,
    /// Episodes trained on.
    pub episodes: u64,
    /// Episodes received.
    pub episodes_received: u64,
    /// Episodes dropped as stale.
    pub dropped_stale: u64,
    /// Environment steps received.
    pub env_steps: u64,
    /// Seconds.
    pub seconds: f64,
    /// The best checkpoint (the verified one when a verification held).
    pub best: Option<CheckpointRecord>,
    /// The checkpoint that held its verification, and what it did.
    pub verified: Option<String>,
    /// The final policy version.
    pub policy_version: u64,
    /// The run folder.
    pub run_dir: PathBuf,
    /// Writes to the run folder that failed, and the last one's error.
    pub write_failures: (u64, String),
}
/// Recent episodes of one world, for the status.
#[derive(Default)]
struct WorldWindow {
    /// (when, worker, progress, reward) of the episodes kept.
    recent: VecDeque<(Instant, String, f64, f64)>,
    /// (when, env steps) delivered.
    steps: VecDeque<(Instant, u64)>,
    episodes: u64,
    crashes: u64,
}

/// Messages taken in one turn of the loop at most (a flood cannot hold it).
const MAX_DRAIN: usize = 1000;

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
        if r.update_if_ready()? {
            // And what arrived during the update, before an evaluation is judged lost.
            r.drain()?;
        }
        let workers = r.link.workers();
        r.grant(&workers)?;
        r.checkpoint_if_due(&workers)?;
        r.chase_evaluation(&workers)?;
        if r.close_evaluation()? || r.should_stop(&workers) {
            break;
        }
        r.report()?;
    }
    r.finish()
}

/// A run under way: everything [`run`]'s handlers share.
struct Run<'a> {
    spec: &'a RunSpec,
    link: &'a mut dyn Link,
    observer: &'a mut dyn Observer,
    dir: RunDir,
    signer: Signer,
    /// The run's logs (sim-trace, metrics JSON, MCAP); `None` when they could not be opened.
    recorder: Option<Recorder>,
    metadata: Arc<ModelMetadata>,
    parent: Option<Parent>,
    /// The algorithm: PPO or SAC.
    algo: Box<dyn Algorithm>,
    /// The run's start (moved back by the training time of a job's earlier learner).
    start: Instant,
    /// Episodes an update takes (DeepRacer's `num_episodes_between_training`).
    want: u64,
    buffer: Buffer,
    grants: Grants,
    /// Per world, and per worker's delivered env steps, over the last seconds.
    windows: BTreeMap<String, WorldWindow>,
    per_worker: BTreeMap<String, VecDeque<(Instant, u64)>>,
    /// (progress, reward) of the last `window` episodes trained on.
    recent: VecDeque<(f64, f64)>,
    episodes: u64,
    env_steps: u64,
    iteration: u64,
    /// Updates made by this process (a resumed run counts from 0).
    iterations_here: u64,
    max_lag: u64,
    best: Option<CheckpointRecord>,
    last_eval: Option<Instant>,
    saved_iteration: Option<u64>,
    evaluated_version: Option<u64>,
    /// Mean progress and weakest world's laps of the last evaluation.
    last_eval_figures: (f64, u64),
    /// Per world, the last evaluation's mean progress and lap time.
    last_eval_worlds: BTreeMap<String, (f64, Option<f64>)>,
    lap_streak: usize,
    /// The checkpoint that held its verification, and what it did.
    verified: Option<String>,
    pending: Option<PendingEval>,
    turns: EvalTurns,
    last_eval_ask: Instant,
    trend: Trend,
    verdict: Verdict,
    last_status: Option<Instant>,
    /// Since the last update: the learner's wait for experience.
    wait_since: Instant,
    stop_reason: Option<String>,
}

impl<'a> Run<'a> {
    /// Open the run folder (new, resumed or cloned), write the run's inputs into it and
    /// publish the first policy.
    fn open(spec: &'a RunSpec, link: &'a mut dyn Link, observer: &'a mut dyn Observer) -> Result<Run<'a>, RunFailure> {
        let start = Instant::now();
        if spec.worlds.is_empty() {
            return Err(RunFailure::Inputs("the run names no world".into()));
        }
        let (dir, model, version, parent, first_iteration) = open(spec)?;
        // A learner restarted mid-job goes on from the run's records: the training time,
        // episodes and env steps so far count towards the job's stop rules (it does not start
        // over). A person's `train --resume` asks for a new stretch of training instead.
        let mid_job = matches!(spec.start, Start::ResumeOrNew { .. });
        let resumed = if first_iteration > 0 && mid_job { dir.last_metrics() } else { None };
        let so_far = |k: &str| resumed.as_ref().and_then(|m| m[k].as_f64()).unwrap_or(0.0);
        let start = start.checked_sub(Duration::from_secs_f64(so_far("time_s"))).unwrap_or(start);
        let signer = signer_for(spec, &dir)?;
        dir.write_file("model_metadata.json", spec.metadata.to_json().as_bytes())?;
        dir.write_file("hyperparameters.json", spec.hyper.to_json().as_bytes())?;
        // deepracer-for-cloud's place for it (`ip/`), where deepracer-utils looks.
        dir.write_file("ip/hyperparameters.json", spec.hyper.to_json().as_bytes())?;
        dir.write_file("sim.toml", spec.sim_toml.as_bytes())?;
        let recorder = noted(
            &dir,
            "the run's logs (sim-trace, metrics JSON, MCAP) not opened",
            Recorder::open(&spec.out, &spec.metadata.action_space, &spec.tracks, first_iteration),
        );
        let algo = algorithm(spec, &dir, model, version, first_iteration)?;
        let best = dir.index()?.best_checkpoint;
        let trend = Trend::new(TrendRules {
            plateau_evals: spec.stop.plateau_evals.unwrap_or(TrendRules::default().plateau_evals),
            ..TrendRules::default()
        });
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
            windows: BTreeMap::new(),
            per_worker: BTreeMap::new(),
            recent: VecDeque::new(),
            episodes: so_far("total_episodes") as u64,
            env_steps: so_far("env_steps") as u64,
            iteration: first_iteration,
            iterations_here: 0,
            max_lag: 0,
            best,
            last_eval: None,
            saved_iteration: None,
            evaluated_version: None,
            last_eval_figures: (0.0, 0),
            last_eval_worlds: BTreeMap::new(),
            lap_streak: 0,
            verified: None,
            pending: None,
            turns: EvalTurns::default(),
            last_eval_ask: Instant::now(),
            trend,
            verdict: Verdict::Improving,
            last_status: None,
            wait_since: Instant::now(),
            stop_reason: None,
        };
        r.publish()?;
        tracing::info!(run = %spec.name, version = r.algo.version(), folder = %spec.out.display(), "training");
        Ok(r)
    }

    /// The manifest of the current model, with `training`'s figures.
    fn manifest(&self, training: serde_json::Value) -> Manifest {
        Manifest {
            format: "paddock-model-1".into(),
            policy_version: self.algo.version(),
            parent: self.parent.clone(),
            weights_sha256: String::new(),
            obs_size: self.spec.obs_size,
            observation: self.spec.observation.clone(),
            training,
        }
    }

    /// Make the current model the one workers act with.
    fn publish(&mut self) -> Result<(), LinkError> {
        let p = PolicyVersion {
            version: self.algo.version(),
            model: Arc::new(self.algo.model().clone()),
            metadata: self.metadata.clone(),
        };
        let manifest = self.manifest(serde_json::json!({"run": self.spec.name}));
        self.link.publish(&p, &manifest, &self.signer)
    }

    /// The episodes for an update are in, and the run is not stopping.
    fn update_ready(&self) -> bool {
        self.buffer.len() as u64 >= self.want && self.stop_reason.is_none()
    }

    /// A message from the workers (or whoever may stop the run).
    fn receive(&mut self, m: Inbound) -> Result<(), RunFailure> {
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

    /// Episodes: counted, and kept for training unless duplicate, bad or stale.
    fn experience(&mut self, e: Experience) {
        if !self.buffer.first_sight(&e.worker, e.seq) {
            return;
        }
        self.env_steps += e.env_steps;
        let now = Instant::now();
        self.per_worker.entry(e.worker.clone()).or_default().push_back((now, e.env_steps));
        self.grants.delivered(e.credit, &e.worker, e.trajectories.len() as u64, now);
        let share = e.env_steps / e.trajectories.len().max(1) as u64;
        // Off-policy experience is never stale.
        let lag = if self.algo.off_policy() { u64::MAX } else { self.spec.max_policy_lag };
        let (version, obs) = (self.algo.version(), self.spec.obs_size);
        for t in e.trajectories {
            let w = self.windows.entry(t.world.clone()).or_default();
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

    /// Trials for the evaluation under way (a failed request is asked of another worker).
    fn evaluated(&mut self, r: EvalReport) -> Result<(), LinkError> {
        let Some(p) = self.pending.as_mut().filter(|p| p.asked.contains_key(&r.id) && p.version == r.version) else {
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
                self.turns.retry(p, &mut *self.link, &workers, world, attempts)?;
            }
        }
        Ok(())
    }

    /// Update once the episodes are in: exactly the episodes an iteration takes, the first to
    /// arrive (the rest wait for the next update); publish the new version and record it.
    /// Take every message already waiting (at most [`MAX_DRAIN`]).
    fn drain(&mut self) -> Result<(), RunFailure> {
        for _ in 0..MAX_DRAIN {
            match self.link.next(Duration::ZERO)? {
                Some(m) => self.receive(m)?,
                None => break,
            }
        }
        Ok(())
    }

    /// Make the update when one is due; true when one was made (or refused).
    fn update_if_ready(&mut self) -> Result<bool, RunFailure> {
        if !self.update_ready() {
            return Ok(false);
        }
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
        self.max_lag = self.max_lag.max(lag);
        let wait_s = self.wait_since.elapsed().as_secs_f64();
        let lr = spec.stop.lr(&spec.hyper, self.start.elapsed().as_secs_f64(), self.episodes, self.env_steps);
        self.algo.set_lr(lr);
        let t1 = Instant::now();
        let result = self.algo.update(&trajs, self.link.team());
        // A refused update changed nothing; it is recorded, and the next one goes on.
        let (stats, refused) = match result {
            Ok(stats) => (stats, None),
            Err(why) => {
                (UpdateStats { policy_version: self.algo.version(), ..UpdateStats::default() }, Some(why.to_string()))
            }
        };
        let update_s = t1.elapsed().as_secs_f64();
        self.wait_since = Instant::now();
        self.iteration += 1;
        self.iterations_here += 1;
        self.episodes += trajs.len() as u64;
        for t in &trajs {
            self.recent.push_back((t.progress, episode_reward(t)));
        }
        while self.recent.len() as u64 > spec.stop.window.max(1) {
            self.recent.pop_front();
        }
        if let Some(why) = &refused {
            tracing::warn!(run = %spec.name, iteration = self.iteration, "{why}");
        }
        self.publish()?;
        if !off_policy {
            self.buffer.drop_stale(self.algo.version(), spec.max_policy_lag);
            self.grants.clear();
        }
        let steps: usize = trajs.iter().map(|t| t.len()).sum();
        let rec = IterationRecord {
            iteration: self.iteration,
            policy_version: self.algo.version(),
            time_s: self.start.elapsed().as_secs_f64(),
            episodes: trajs.len(),
            total_episodes: self.episodes,
            steps,
            env_steps: self.env_steps,
            mean_reward: mean(trajs.iter().map(episode_reward)),
            mean_progress: mean(trajs.iter().map(|t| t.progress)),
            policy_loss: stats.policy_loss,
            value_loss: stats.value_loss,
            entropy: stats.entropy,
            approx_kl: stats.approx_kl,
            clip_fraction: stats.clip_fraction,
            explained_variance: stats.explained_variance,
            wait_s,
            update_s,
            samples_per_s: steps as f64 / update_s.max(1e-9),
            policy_lag: lag,
            episodes_received: self.buffer.received,
            dropped_stale: self.buffer.stale,
            dropped_duplicate: self.buffer.dup,
            dropped_bad: self.buffer.bad,
            refused,
            gradient_steps: stats.gradient_steps,
            kl_stop: stats.kl_stop,
            lr,
            sac: stats.sac,
        };
        noted(
            &self.dir,
            "metrics.jsonl: an update's line not written",
            self.dir.append_metrics(&serde_json::to_value(&rec).expect("JSON")),
        );
        if let Some(r) = self.recorder.as_mut() {
            noted(
                &self.dir,
                "an update's sim-trace, metrics JSON or MCAP not written",
                r.iteration(&rec, &trajs, &from),
            );
        }
        self.observer.iteration(&rec);
        self.last_status = None;
        Ok(true)
    }

    /// Flow control: grant what the next update still needs (see [`grants`]).
    fn grant(&mut self, workers: &[String]) -> Result<(), LinkError> {
        if self.stop_reason.is_some() {
            return Ok(());
        }
        let shortfall = self.want.saturating_sub(self.buffer.len() as u64);
        match self.grants.due(self.algo.version(), shortfall, workers, Instant::now()) {
            Some(credit) => self.link.grant(&credit),
            None => Ok(()),
        }
    }

    /// A checkpoint when due (every `eval_seconds`, and the last version when stopping), each
    /// evaluated on the workers unless an evaluation is still under way.
    fn checkpoint_if_due(&mut self, workers: &[String]) -> Result<(), LinkError> {
        let spec = self.spec;
        let every = Duration::from_secs_f64(spec.eval_seconds.max(0.0));
        let due = self.iterations_here > 0
            && self.stop_reason.is_none()
            && self.saved_iteration != Some(self.iteration)
            && self.last_eval.is_none_or(|t| t.elapsed() >= every);
        let final_due = self.stop_reason.is_some()
            && self.iterations_here > 0
            && self.evaluated_version != Some(self.algo.version())
            && self.pending.is_none()
            && !workers.is_empty();
        if !(due || final_due) {
            return Ok(());
        }
        let name = RunDir::checkpoint_name(self.iteration);
        let manifest = self.manifest(serde_json::json!({"run": spec.name, "worlds": spec.worlds,
            "iteration": self.iteration, "episodes": self.episodes, "env_steps": self.env_steps,
            "seconds": self.start.elapsed().as_secs_f64(), "hyperparameters": spec.hyper}));
        if self.saved_iteration != Some(self.iteration) {
            self.save_checkpoint(&name, &manifest);
            noted(&self.dir, "the replay memory's part not kept", self.algo.save_memory_part(self.dir.root()));
            self.saved_iteration = Some(self.iteration);
        }
        self.last_eval = Some(Instant::now());
        if self.pending.is_none() && !workers.is_empty() {
            let mut p =
                PendingEval::new(spec, self.iteration, self.algo.version(), self.algo.model().clone(), manifest, name);
            for world in &spec.worlds {
                self.turns.ask(&mut p, &mut *self.link, workers, world.clone(), 1)?;
            }
            self.pending = Some(p);
        }
        Ok(())
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
        .and_then(|_| self.algo.save_state(&self.dir.checkpoint_dir(name)))
        .and_then(|_| {
            self.dir
                .record_last(CheckpointRecord {
                    name: name.to_string(),
                    iteration: self.iteration,
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

    /// Keep the evaluation under way going: ask again every few seconds (a request can be lost
    /// while the worker's subscription is on its way; the worker answers a repeat from its
    /// cache), and ask another worker when this one went away or never answered.
    fn chase_evaluation(&mut self, workers: &[String]) -> Result<(), LinkError> {
        let Some(p) = self.pending.as_mut() else { return Ok(()) };
        if self.last_eval_ask.elapsed() >= EVAL_REPEAT {
            self.last_eval_ask = Instant::now();
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
            self.turns.retry(p, &mut *self.link, workers, world, attempts)?;
        }
        Ok(())
    }

    /// Once every world's trials are in: record the evaluation, keep the model if it is the
    /// best, follow the lap streak and the trend. True when this was the final evaluation of
    /// a stopping run (the run is over).
    fn close_evaluation(&mut self) -> Result<bool, LinkError> {
        if !self.pending.as_ref().is_some_and(|p| p.asked.is_empty()) {
            return Ok(false);
        }
        let spec = self.spec;
        let mut p = self.pending.take().expect("checked");
        let all: Vec<Trial> = p.done.values().flatten().cloned().collect();
        let (progress, lap_time, _) = summarise(&all);
        let per_world: Vec<(String, f64, Option<f64>, usize, usize)> = spec
            .worlds
            .iter()
            .map(|w| {
                let t = p.done.get(w).map(Vec::as_slice).unwrap_or(&[]);
                let (pr, lap, laps) = summarise(t);
                (w.clone(), pr, lap, laps, t.len())
            })
            .collect();
        let min_laps = per_world.iter().map(|w| w.3).min().unwrap_or(0);
        let rec = CheckpointRecord {
            name: p.name.clone(),
            iteration: p.iteration,
            policy_version: p.version,
            avg_eval_metric: progress,
            avg_lap_time: lap_time,
            time_stamp: self.start.elapsed().as_secs_f64(),
        };
        let mut manifest = p.manifest.clone();
        if let Some(obj) = manifest.training.as_object_mut() {
            obj.insert("eval_progress".into(), progress.into());
            obj.insert("eval_lap_time".into(), serde_json::json!(lap_time));
            obj.insert("eval_worlds".into(), serde_json::to_value(&per_world).expect("JSON"));
            if p.verifying {
                obj.insert("verified_trials".into(), p.trials.into());
            }
        }
        let target = spec.stop.target_laps.filter(|t| t.laps > 0);
        let is_best = if p.verifying {
            // The checkpoint that holds its verification is the run's model, whatever an
            // earlier evaluation's figures were; one that does not hold changes nothing.
            let held = target.is_some_and(|t| self.verification_held(&p, &t, &per_world));
            if held {
                noted(&self.dir, "the checkpoint index not written", self.dir.record_best(rec.clone()));
            }
            held
        } else {
            noted(&self.dir, "the checkpoint index not written", self.dir.record(rec.clone())).unwrap_or(false)
        };
        self.evaluated_version = Some(p.version);
        if is_best || !self.dir.model_dir().join("manifest.json").exists() {
            noted(
                &self.dir,
                &format!("the best model (v{}) not written; model/ holds the previous best", p.version),
                folder::save_signed(&self.dir.model_dir(), &spec.metadata, &p.model, &manifest, Some(&self.signer)),
            );
        }
        if is_best {
            let best =
                PolicyVersion { version: p.version, model: Arc::new(p.model.clone()), metadata: self.metadata.clone() };
            self.link.best(&best, &manifest, &self.signer)?;
            self.best = Some(rec);
        }
        let mut verify = None;
        if let (Some(t), false) = (target, p.verifying) {
            let met = min_laps >= t.needed(spec.eval_trials as usize, spec.eval_trials as usize);
            self.lap_streak = if met { self.lap_streak + 1 } else { 0 };
            if met && t.verify_trials > 0 && self.lap_streak >= t.evaluations.max(1) && self.stop_reason.is_none() {
                verify = Some(t.verify_trials as u32);
            }
        }
        if !p.verifying {
            self.last_eval_figures = (progress, min_laps as u64);
            self.last_eval_worlds = per_world.iter().map(|w| (w.0.clone(), (w.1, w.2))).collect();
            let now = self.trend.push(p.iteration, progress);
            if std::mem::discriminant(&now) != std::mem::discriminant(&self.verdict) {
                match &now {
                    Verdict::Improving => tracing::info!(run = %spec.name, "evaluation progress improving again"),
                    v => tracing::warn!(run = %spec.name, "{}", v.describe()),
                }
            }
            self.verdict = now;
        }
        let mut e = EvalRecord {
            iteration: p.iteration,
            policy_version: p.version,
            worlds: per_world,
            progress,
            lap_time,
            min_laps,
            trials: p.trials as usize,
            best: is_best,
            simtrace: Vec::new(),
            trend: self.verdict.describe(),
            crashes: all.iter().map(|t| t.crashes).sum(),
            verification: p.verifying,
        };
        if let Some(r) = self.recorder.as_mut() {
            e.simtrace = noted(
                &self.dir,
                "an evaluation's sim-trace, metrics JSON or MCAP not written",
                r.evaluation(&e, &p.done),
            )
            .unwrap_or_default();
        }
        noted(
            &self.dir,
            "evaluations.jsonl: an evaluation's line not written",
            self.dir.append_evaluation(&serde_json::to_value(&e).expect("JSON")),
        );
        self.observer.evaluation(&e);
        // A checkpoint that met the target is verified at once, each world by the worker that
        // evaluated it (it keeps that version).
        let workers = self.link.workers();
        if let (Some(trials), false) = (verify, workers.is_empty()) {
            let by = std::mem::take(&mut p.by);
            let mut v = p.verification(trials);
            tracing::info!(run = %spec.name, checkpoint = %v.name, trials, "verifying the checkpoint that met the lap target");
            for world in &spec.worlds {
                match by.get(world).filter(|w| workers.contains(w)) {
                    Some(w) => self.turns.ask_of(&mut v, &mut *self.link, w.clone(), world.clone(), 1)?,
                    None => self.turns.ask(&mut v, &mut *self.link, &workers, world.clone(), 1)?,
                }
            }
            self.last_eval_ask = Instant::now();
            self.pending = Some(v);
            return Ok(false);
        }
        // The final evaluation (of the last version) closes a stopping run.
        Ok(self.stop_reason.is_some() && p.version == self.algo.version())
    }

    /// Whether a verification's trials lap the target's share on every world; one that holds
    /// becomes [`Run::verified`], one that does not ends the lap streak.
    fn verification_held(
        &mut self,
        p: &PendingEval,
        t: &TargetLaps,
        per_world: &[(String, f64, Option<f64>, usize, usize)],
    ) -> bool {
        let needed = t.needed(self.spec.eval_trials as usize, p.trials as usize);
        let held = per_world.iter().all(|w| w.3 >= needed && w.4 == p.trials as usize);
        let min_laps = per_world.iter().map(|w| w.3).min().unwrap_or(0);
        let what = format!(
            "{} (v{}) lapped {min_laps} of {} trials on every world in its verification ({needed} needed)",
            p.name, p.version, p.trials
        );
        if held {
            tracing::info!(run = %self.spec.name, "verified: {what}");
            self.verified = Some(what);
        } else {
            tracing::warn!(run = %self.spec.name, "not verified, training goes on: {what}");
            self.lap_streak = 0;
        }
        held
    }

    /// Check the stop rules; true when the run is over: stopping, and the last version's
    /// evaluation is recorded (or there is nothing to evaluate, or nobody left to evaluate it).
    fn should_stop(&mut self, workers: &[String]) -> bool {
        if self.stop_reason.is_none() {
            let full = self.recent.len() as u64 >= self.spec.stop.window.max(1);
            let standing = Standing {
                seconds: self.start.elapsed().as_secs_f64(),
                episodes: self.episodes,
                env_steps: self.env_steps,
                window: full.then(|| (mean(self.recent.iter().map(|r| r.0)), mean(self.recent.iter().map(|r| r.1)))),
                lap_streak: self.lap_streak,
                verified: self.verified.clone(),
                verdict: self.verdict.clone(),
            };
            if let Some(why) = self.spec.stop.check(&self.spec.hyper, &standing) {
                tracing::info!(run = %self.spec.name, "stopping: {why}");
                self.stop_reason = Some(why);
                self.grants.clear();
            }
        }
        if self.stop_reason.is_none() {
            return false;
        }
        // A verified checkpoint is the run's model: no later version is evaluated.
        if self.verified.is_some() && self.pending.is_none() {
            return true;
        }
        if self.iterations_here == 0 || (self.pending.is_none() && self.evaluated_version == Some(self.algo.version()))
        {
            return true;
        }
        if workers.is_empty() {
            tracing::warn!(run = %self.spec.name, "no worker left to run the final evaluation");
            return true;
        }
        false
    }

    /// The run's figures to the link, every second (and after every update).
    fn report(&mut self) -> Result<(), LinkError> {
        if self.last_status.is_some_and(|t| t.elapsed() < Duration::from_secs(1)) {
            return Ok(());
        }
        self.last_status = Some(Instant::now());
        let s = self.status();
        self.link.status(&s)
    }

    /// The run's figures now (the windows over the last 10 s are trimmed on the way).
    fn status(&mut self) -> RunStatus {
        let now = Instant::now();
        let ten = Duration::from_secs(10);
        let worlds = self
            .windows
            .iter_mut()
            .map(|(name, w)| {
                while w.recent.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                    w.recent.pop_front();
                }
                while w.steps.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                    w.steps.pop_front();
                }
                let span =
                    w.steps.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
                let workers: BTreeSet<&String> = w.recent.iter().map(|r| &r.1).collect();
                WorldFigures {
                    world: name.clone(),
                    workers: workers.len() as u32,
                    episodes: w.episodes,
                    mean_progress: mean(w.recent.iter().map(|r| r.2)),
                    mean_reward: mean(w.recent.iter().map(|r| r.3)),
                    steps_per_s: w.steps.iter().map(|r| r.1).sum::<u64>() as f64 / span,
                    crashes: w.crashes,
                    eval: self.last_eval_worlds.get(name).copied(),
                }
            })
            .collect();
        let workers = self
            .per_worker
            .iter_mut()
            .filter_map(|(id, q)| {
                while q.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                    q.pop_front();
                }
                let span = q.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
                (!q.is_empty()).then(|| (id.clone(), q.iter().map(|r| r.1).sum::<u64>() as f64 / span))
            })
            .collect();
        let (write_failures, write_error) = self.dir.failures();
        RunStatus {
            policy_version: self.algo.version(),
            iteration: self.iteration,
            episodes: self.episodes,
            episodes_received: self.buffer.received,
            env_steps: self.env_steps,
            window_reward: mean(self.recent.iter().map(|r| r.1)),
            window_progress: mean(self.recent.iter().map(|r| r.0)),
            max_lag: self.max_lag,
            dropped_stale: self.buffer.stale,
            dropped_duplicate: self.buffer.dup,
            dropped_bad: self.buffer.bad,
            eval_progress: self.last_eval_figures.0,
            eval_laps: self.last_eval_figures.1,
            finished: false,
            stop_reason: self.stop_reason.clone(),
            run_dir: self.dir.root().display().to_string(),
            worlds,
            workers,
            write_failures,
            write_error,
            trend: self.verdict.describe(),
        }
    }

    /// The run is over: the final status, the logs closed, `summary.json`.
    fn finish(mut self) -> Result<Summary, RunFailure> {
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
        let summary = self.dir.write_file(
            "summary.json",
            serde_json::to_string_pretty(&serde_json::json!({
                "run": spec.name, "worlds": spec.worlds, "iterations": self.iteration, "episodes": self.episodes,
                "episodes_received": self.buffer.received, "dropped_stale": self.buffer.stale,
                "env_steps": self.env_steps, "seconds": seconds, "stop_reason": reason, "best": self.best,
                "policy_version": self.algo.version(), "write_failures": write_failures, "write_error": write_error,
                "trend": self.verdict.describe(), "verified": self.verified,
            }))
            .expect("JSON")
            .as_bytes(),
        );
        noted(&self.dir, "summary.json not written", summary);
        tracing::info!(run = %spec.name, version = self.algo.version(), "run finished: {reason}");
        Ok(Summary {
            stop_reason: reason,
            iterations: self.iteration,
            episodes: self.episodes,
            episodes_received: self.buffer.received,
            dropped_stale: self.buffer.stale,
            env_steps: self.env_steps,
            seconds,
            best: self.best,
            verified: self.verified.clone(),
            policy_version: self.algo.version(),
            run_dir: spec.out.clone(),
            write_failures: self.dir.failures(),
        })
    }
}

/// The run's algorithm for its metadata, from the opened model: PPO (taking over a team's
/// newer state when the spec carries one) or SAC (with the critics of the checkpoint it
/// resumes from and the replay memory the run folder kept, when there are).
fn algorithm(
    spec: &RunSpec,
    dir: &RunDir,
    model: ActorCritic,
    version: u64,
    first_iteration: u64,
) -> Result<Box<dyn Algorithm>, RunFailure> {
    if spec.metadata.training_algorithm == policy::TrainingAlgorithm::Sac {
        let mut sac = SacTrainer::new(model, &spec.metadata, spec.obs_size, &spec.hyper, version, spec.seed, spec.par)
            .map_err(RunFailure::Inputs)?;
        if first_iteration > 0 {
            let last = dir.index()?.last_checkpoint.map(|l| dir.checkpoint_dir(&l.name));
            match last.map(|d| sac.load_state(&d)).transpose() {
                Ok(Some(true)) => tracing::info!(run = %spec.name, "SAC: the critics go on from the checkpoint"),
                Ok(_) => tracing::warn!(run = %spec.name, "SAC: the checkpoint holds no critics: they start afresh"),
                Err(e) => tracing::warn!(run = %spec.name, "SAC: the critics start afresh: {e}"),
            }
            match sac.load_memory(dir.root()) {
                Ok(true) => {
                    tracing::info!(run = %spec.name, transitions = sac.replay().len(), "SAC: the replay memory goes on")
                }
                Ok(false) => {
                    tracing::warn!(run = %spec.name, "SAC: the run folder holds no replay memory: it starts empty")
                }
                Err(e) => tracing::warn!(run = %spec.name, "SAC: the replay memory starts empty: {e}"),
            }
        }
        if let Some(g) = &spec.gpu {
            sac = sac.with_gpu(g.clone());
        }
        adopt(spec, &mut sac);
        return Ok(Box::new(sac));
    }
    let mut ppo = Ppo::new(model, spec.hyper.clone(), version, spec.seed, spec.par);
    if let Some(g) = &spec.gpu {
        ppo = ppo.with_gpu(g.clone());
    }
    adopt(spec, &mut ppo);
    Ok(Box::new(ppo))
}

/// Take over the team's state the spec carries, when it is newer than the run folder's.
fn adopt(spec: &RunSpec, algo: &mut dyn Shared) {
    let Some((state, memory)) = spec.adopt.as_ref().filter(|(s, _)| s.version > algo.version()) else { return };
    let v = state.version;
    match algo.restore(state.clone(), memory.as_deref()) {
        Ok(()) => {
            tracing::info!(run = %spec.name, version = v, "taking over from the team's state (newer than the run folder's)")
        }
        Err(e) => tracing::warn!(run = %spec.name, "the team's state does not fit this run: {e}"),
    }
}

/// Open the run folder and the model.
fn open(spec: &RunSpec) -> Result<(RunDir, ActorCritic, u64, Option<Parent>, u64), RunFailure> {
    let (mode, clone_from) = match &spec.start {
        Start::New { clone_from } => (OpenMode::New, clone_from.clone()),
        Start::Force => (OpenMode::Force, None),
        Start::Resume => (OpenMode::Resume, None),
        Start::ResumeOrNew { clone_from } => {
            if spec.out.join("model").join("manifest.json").exists() {
                (OpenMode::Resume, None)
            } else {
                (OpenMode::New, clone_from.clone())
            }
        }
    };
    // A leftover empty (or log-only) folder from an earlier attempt is not a run.
    let mode = if mode == OpenMode::New && spec.out.exists() && !spec.out.join("model").exists() {
        OpenMode::Force
    } else {
        mode
    };
    let run = RunDir::open(&spec.out, mode)?;
    if mode == OpenMode::Resume {
        let index = run.index()?;
        let dir = index
            .last_checkpoint
            .as_ref()
            .map(|l| run.checkpoint_dir(&l.name))
            .filter(|d| d.exists())
            .unwrap_or_else(|| run.model_dir());
        let f = folder::load(&dir)?;
        if let Err(why) = f.metadata.compatible_with(&spec.metadata) {
            return Err(RunFailure::Inputs(format!("{}: cannot continue this run: {why}", dir.display())));
        }
        if f.manifest.obs_size != spec.obs_size {
            return Err(RunFailure::Inputs(format!(
                "{}: the model takes {} inputs, this configuration's observation has {}",
                dir.display(),
                f.manifest.obs_size,
                spec.obs_size
            )));
        }
        let iteration = index.last_checkpoint.map(|l| l.iteration).unwrap_or(0);
        let dropped = run.rewind_records(iteration)?;
        if dropped > 0 {
            tracing::warn!(run = %spec.name, iteration, dropped, "records after the last checkpoint dropped: those updates are made again");
        }
        tracing::info!(run = %spec.name, from = %dir.display(), version = f.manifest.policy_version, "resuming");
        return Ok((run, f.model, f.manifest.policy_version, f.manifest.parent, iteration));
    }
    if let Some(from) = clone_from {
        let f = folder::load(&from)?;
        f.metadata
            .compatible_with(&spec.metadata)
            .map_err(|why| RunFailure::Inputs(format!("{}: {why}", from.display())))?;
        if f.manifest.obs_size != spec.obs_size {
            return Err(RunFailure::Inputs(format!(
                "{}: the model takes {} inputs, this configuration's observation has {}",
                from.display(),
                f.manifest.obs_size,
                spec.obs_size
            )));
        }
        if f.manifest.training.get("imported").is_some() && spec.hyper.value_warmup_updates <= f.manifest.policy_version
        {
            tracing::warn!(
                run = %spec.name,
                from = %from.display(),
                "the model was imported from DeepRacer's graph with a new value tower, and value_warmup_updates \
                 does not hold the policy for it: the policy trains from the first update (`coordinator clone` sets a warm-up)"
            );
        }
        let parent = Parent {
            path: from.display().to_string(),
            policy_version: f.manifest.policy_version,
            weights_sha256: f.manifest.weights_sha256.clone(),
        };
        return Ok((run, f.model, f.manifest.policy_version, Some(parent), 0));
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(spec.seed);
    Ok((run, ActorCritic::new(&spec.metadata, spec.obs_size, &mut rng), 0, None, 0))
}

/// The run's signing key: the one the spec names, or the run folder's `signing.key` (made on
/// first use, with `signing.pub` beside it).
fn signer_for(spec: &RunSpec, run: &RunDir) -> Result<Signer, RunFailure> {
    let r = match &spec.signing_key {
        Some(path) => Signer::load(path),
        None => Signer::load_or_create(&run.root().join("signing.key")),
    };
    r.map_err(|e| RunFailure::Inputs(format!("signing key: {e}")))
}

/// A write to the run folder that training does not stop for: a failure is noted (logged, and
/// reported in the run's status) and `None`.
fn noted<T, E: std::fmt::Display>(run: &RunDir, what: &str, r: Result<T, E>) -> Option<T> {
    match r {
        Ok(v) => Some(v),
        Err(e) => {
            run.note_failure(format!("{what}: {e}"));
            None
        }
    }
}

fn mean(xs: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

fn episode_reward(t: &Trajectory) -> f64 {
    t.rewards.iter().map(|r| *r as f64).sum()
}
