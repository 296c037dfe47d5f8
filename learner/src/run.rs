//! One training run, whatever carries its messages.
//!
//! [`run`] is the whole of training: open (new, resume or clone) the run folder, publish
//! every policy version, grant the workers the episodes the next update needs (flow
//! control), gather experience (dropping duplicates and stale episodes, and counting them),
//! update with PPO, ask the workers for evaluation trials on every world, keep checkpoints and
//! the best model, write metrics, and stop on any [`StopRules`] condition. It talks to the
//! workers through a [`Link`]: `coordinator train` passes in-process channels to a worker
//! thread; `learner serve` passes Zenoh. The loop is the same; only the link differs.
//!
//! Flow control: for each policy version the learner grants the live workers, between them,
//! the episodes it still needs for the next update ([`Credit`]). A worker starts no more
//! episodes than it was granted, so what is simulated is what is trained on; the episodes a
//! worker had running when its grant ran out finish under the next grant, one version old.
//! When a worker goes away before delivering its share, a new round re-grants the shortfall
//! to those still alive.

use crate::checkpoints::{CheckpointRecord, OpenMode, RunDir, RunError};
use crate::hyperparams::Hyperparameters;
use crate::ppo::{Ppo, PpoState, UpdateStats};
use crate::record::Recorder;
use crate::trend::{Trend, TrendRules, Verdict};
use faer::Par;
use policy::exchange::{Credit, EvalReport, EvalRequest, Experience, PolicyVersion, Trial, summarise};
use policy::folder::{self, Manifest, Parent};
use policy::signature::Signer;
use policy::{ActorCritic, ModelMetadata, Trajectory};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
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
    fn update(&mut self, ppo: &mut Ppo, trajs: &[Trajectory]) -> UpdateStats;
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

/// Consecutive evaluations that must complete laps before the run stops.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetLaps {
    /// Laps (of the evaluation's trials, on every world).
    pub laps: usize,
    /// Consecutive evaluations.
    pub evaluations: usize,
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
        if let Some(t) = self.target_laps.filter(|t| t.laps > 0 && s.lap_streak >= t.evaluations.max(1)) {
            return Some(format!(
                "target laps reached: {} laps in {} consecutive evaluations",
                t.laps,
                t.evaluations.max(1)
            ));
        }
        match &s.verdict {
            Verdict::Plateau { .. } if self.plateau_evals.is_some() => return Some(s.verdict.describe()),
            Verdict::Collapse { .. } if self.stop_on_collapse => return Some(s.verdict.describe()),
            _ => {}
        }
        None
    }
}

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
    /// A learner team member taking the run over from a leader that went away: its state
    /// (the team's, as of the last update), used when it is newer than the run folder's.
    pub adopt: Option<PpoState>,
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
    /// The best checkpoint.
    pub best: Option<CheckpointRecord>,
    /// The final policy version.
    pub policy_version: u64,
    /// The run folder.
    pub run_dir: PathBuf,
    /// Writes to the run folder that failed, and the last one's error.
    pub write_failures: (u64, String),
}

/// An evaluation under way: one request per world.
struct PendingEval {
    iteration: u64,
    version: u64,
    model: ActorCritic,
    manifest: Manifest,
    name: String,
    asked: BTreeMap<u64, (String, String, Instant, u32)>, // id -> (world, worker, when, attempts)
    done: BTreeMap<String, Vec<Trial>>,
}

impl PendingEval {
    /// The request for `world`'s trials of this checkpoint, as request `id` to `worker`.
    fn request(&self, spec: &RunSpec, id: u64, worker: &str, world: &str) -> EvalRequest {
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
struct EvalTurns {
    turn: usize,
    ids: u64,
}

impl EvalTurns {
    /// Ask the next worker in turn for `world`'s trials (this is attempt `attempts`).
    fn ask(
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
    fn retry(
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

/// A grant round in progress.
struct Round {
    credit: Credit,
    delivered: BTreeMap<String, u64>,
    started: Instant,
    last_delivery: Instant,
}

/// Recent episodes of one world.
#[derive(Default)]
struct WorldWindow {
    recent: VecDeque<(Instant, String, f64, f64)>,
    steps: VecDeque<(Instant, u64)>,
    episodes: u64,
}

/// How long a worker has to answer an evaluation request before another is asked.
const EVAL_TIMEOUT: Duration = Duration::from_secs(180);
/// How often an unanswered evaluation request is repeated.
const EVAL_REPEAT: Duration = Duration::from_secs(3);

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

/// Train until a stop rule, a stop message or a failure. Returns how it ended; the final
/// checkpoint and the best model are in the run folder.
pub fn run(spec: &RunSpec, link: &mut dyn Link, observer: &mut dyn Observer) -> Result<Summary, RunFailure> {
    let start = Instant::now();
    if spec.worlds.is_empty() {
        return Err(RunFailure::Inputs("the run names no world".into()));
    }
    let (run, model, version, parent, first_iteration) = open(spec)?;
    // A learner restarted mid-job goes on from the run's records: the training time, episodes
    // and env steps so far count towards the job's stop rules (it does not start over). A
    // person's `train --resume` asks for a new stretch of training instead.
    let mid_job = matches!(spec.start, Start::ResumeOrNew { .. });
    let resumed = if first_iteration > 0 && mid_job { run.last_metrics() } else { None };
    let so_far = |k: &str| resumed.as_ref().and_then(|m| m[k].as_f64()).unwrap_or(0.0);
    let start = start.checked_sub(Duration::from_secs_f64(so_far("time_s"))).unwrap_or(start);
    let signer = signer_for(spec, &run)?;
    run.write_file("model_metadata.json", spec.metadata.to_json().as_bytes())?;
    run.write_file("hyperparameters.json", spec.hyper.to_json().as_bytes())?;
    // deepracer-for-cloud's place for it (`ip/`), where deepracer-utils looks.
    run.write_file("ip/hyperparameters.json", spec.hyper.to_json().as_bytes())?;
    run.write_file("sim.toml", spec.sim_toml.as_bytes())?;
    let mut recorder = noted(
        &run,
        "the run's logs (sim-trace, metrics JSON, MCAP) not opened",
        Recorder::open(&spec.out, &spec.metadata.action_space, &spec.tracks, first_iteration),
    );
    let metadata = Arc::new(spec.metadata.clone());
    let hyper = &spec.hyper;
    let want = hyper.num_episodes_between_training.max(1) as u64;
    let mut ppo = Ppo::new(model, hyper.clone(), version, spec.seed, spec.par);
    if let Some(state) = spec.adopt.clone().filter(|s| s.version > ppo.version) {
        let v = state.version;
        match ppo.restore(state) {
            Ok(()) => {
                tracing::info!(run = %spec.name, version = v, "taking over from the team's state (newer than the run folder's)")
            }
            Err(e) => tracing::warn!(run = %spec.name, "the team's state does not fit this run: {e}"),
        }
    }
    let manifest_for = |ppo: &Ppo, training: serde_json::Value| Manifest {
        format: "paddock-model-1".into(),
        policy_version: ppo.version,
        parent: parent.clone(),
        weights_sha256: String::new(),
        obs_size: spec.obs_size,
        observation: spec.observation.clone(),
        training,
    };
    let publish = |ppo: &Ppo, link: &mut dyn Link| -> Result<(), LinkError> {
        let p = PolicyVersion { version: ppo.version, model: Arc::new(ppo.model.clone()), metadata: metadata.clone() };
        link.publish(&p, &manifest_for(ppo, serde_json::json!({"run": spec.name})), &signer)
    };
    publish(&ppo, link)?;
    tracing::info!(run = %spec.name, version = ppo.version, folder = %spec.out.display(), "training");

    let mut buffer: Vec<Trajectory> = Vec::new();
    let mut buffer_from: Vec<String> = Vec::new(); // the worker of each buffered trajectory
    let mut seen: HashMap<String, BTreeSet<u64>> = HashMap::new();
    let mut windows: BTreeMap<String, WorldWindow> = BTreeMap::new();
    let mut per_worker: BTreeMap<String, VecDeque<(Instant, u64)>> = BTreeMap::new();
    let mut recent: VecDeque<(f64, f64)> = VecDeque::new();
    let (episodes0, env_steps0) = (so_far("total_episodes") as u64, so_far("env_steps") as u64);
    let (mut dup, mut stale, mut bad, mut received) = (0u64, 0u64, 0u64, episodes0);
    let (mut episodes, mut env_steps, mut iteration, mut max_lag) = (episodes0, env_steps0, first_iteration, 0u64);
    let mut iterations_here = 0u64;
    let mut best = run.index()?.best_checkpoint;
    let mut last_eval: Option<Instant> = None;
    let mut saved_iteration: Option<u64> = None;
    let mut evaluated_version: Option<u64> = None;
    let mut last_eval_figures = (0.0, 0u64);
    let mut lap_streak = 0usize;
    let mut pending: Option<PendingEval> = None;
    let mut trend = Trend::new(TrendRules {
        plateau_evals: spec.stop.plateau_evals.unwrap_or(TrendRules::default().plateau_evals),
        ..TrendRules::default()
    });
    let mut verdict = Verdict::Improving;
    let mut turns = EvalTurns::default();
    let mut last_eval_ask = Instant::now();
    let mut round: Option<Round> = None;
    // Rounds count up from the run's start time, so a restarted learner's grants are never
    // mistaken for repeats of its predecessor's.
    let round_base = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64 * 1000)
        .unwrap_or(0);
    let mut last_grant = Instant::now() - Duration::from_secs(60);
    let mut round_seconds: Option<f64> = None;
    let mut last_status = Instant::now() - Duration::from_secs(60);
    let mut wait_since = Instant::now();
    let mut stop_reason: Option<String> = None;
    let eval_every = Duration::from_secs_f64(spec.eval_seconds.max(0.0));

    // Grant the shortfall to the workers alive now, in a new round.
    let new_round = |version: u64, number: u64, need: u64, workers: &[String]| -> Option<Round> {
        if workers.is_empty() || need == 0 {
            return None;
        }
        let n = workers.len() as u64;
        let episodes =
            workers.iter().enumerate().map(|(i, w)| (w.clone(), need / n + u64::from((i as u64) < need % n))).collect();
        let now = Instant::now();
        Some(Round {
            credit: Credit { version, round: number, episodes },
            delivered: BTreeMap::new(),
            started: now,
            last_delivery: now,
        })
    };

    loop {
        // 1. What arrived.
        let timeout = if buffer.len() as u64 >= want { Duration::ZERO } else { Duration::from_millis(50) };
        match link.next(timeout)? {
            Some(Inbound::Experience(e)) => {
                if !seen.entry(e.worker.clone()).or_default().insert(e.seq) {
                    dup += 1;
                } else {
                    env_steps += e.env_steps;
                    let now = Instant::now();
                    per_worker.entry(e.worker.clone()).or_default().push_back((now, e.env_steps));
                    if let Some(r) = round.as_mut().filter(|r| (r.credit.version, r.credit.round) == e.credit) {
                        *r.delivered.entry(e.worker.clone()).or_default() += e.trajectories.len() as u64;
                        r.last_delivery = now;
                        if round_seconds.is_none() || r.delivered.len() == r.credit.episodes.len() {
                            let took = now.duration_since(r.started).as_secs_f64();
                            round_seconds = Some(round_seconds.map_or(took, |s| 0.8 * s + 0.2 * took));
                        }
                    }
                    let share = e.env_steps / e.trajectories.len().max(1) as u64;
                    for t in e.trajectories {
                        received += 1;
                        let w = windows.entry(t.world.clone()).or_default();
                        w.steps.push_back((now, share));
                        if t.obs.len() != t.len() * spec.obs_size || t.is_empty() {
                            bad += 1;
                            continue;
                        }
                        if t.policy_version > ppo.version || ppo.version - t.policy_version > spec.max_policy_lag {
                            // Too old, or from a version this learner never published (before a restart).
                            stale += 1;
                            continue;
                        }
                        w.recent.push_back((now, e.worker.clone(), t.progress, episode_reward(&t)));
                        w.episodes += 1;
                        buffer.push(t);
                        buffer_from.push(e.worker.clone());
                    }
                }
            }
            Some(Inbound::Eval(r)) => {
                if let Some(p) = pending.as_mut().filter(|p| p.asked.contains_key(&r.id) && p.version == r.version) {
                    let (world, worker, _, attempts) = p.asked.remove(&r.id).expect("checked");
                    match r.trials {
                        Ok(trials) => {
                            p.done.insert(world, trials);
                        }
                        Err(why) => {
                            tracing::warn!(run = %spec.name, worker = %worker, world = %world, "evaluation failed: {why}");
                            let workers = link.workers();
                            turns.retry(p, link, spec, &workers, world, attempts)?;
                        }
                    }
                }
            }
            Some(Inbound::Stop(why)) => {
                stop_reason.get_or_insert(why);
            }
            Some(Inbound::Failed { worker, error }) => return Err(RunFailure::Worker { worker, error }),
            None => {}
        }

        // 2. Update when the episodes are in.
        if buffer.len() as u64 >= want && stop_reason.is_none() {
            // Exactly the episodes an iteration takes (DeepRacer's `num_episodes_between_training`),
            // the first to arrive; the rest wait for the next update.
            let take = (want as usize).min(buffer.len());
            let trajs: Vec<Trajectory> = buffer.drain(..take).collect();
            let from: Vec<String> = buffer_from.drain(..take).collect();
            let lag = trajs.iter().map(|t| ppo.version - t.policy_version).max().unwrap_or(0);
            max_lag = max_lag.max(lag);
            let wait_s = wait_since.elapsed().as_secs_f64();
            let lr = spec.stop.lr(hyper, start.elapsed().as_secs_f64(), episodes, env_steps);
            ppo.set_lr(lr);
            let t1 = Instant::now();
            let stats: UpdateStats = match link.team() {
                Some(team) => team.update(&mut ppo, &trajs),
                None => ppo.update(&trajs),
            };
            let update_s = t1.elapsed().as_secs_f64();
            wait_since = Instant::now();
            iteration += 1;
            iterations_here += 1;
            episodes += trajs.len() as u64;
            for t in &trajs {
                recent.push_back((t.progress, episode_reward(t)));
            }
            while recent.len() as u64 > spec.stop.window.max(1) {
                recent.pop_front();
            }
            if let Some(why) = &stats.refused {
                tracing::warn!(run = %spec.name, iteration, "{why}");
            }
            publish(&ppo, link)?;
            // Episodes left for the next update that this one made too old: stale.
            let mut i = 0;
            while i < buffer.len() {
                if ppo.version - buffer[i].policy_version > spec.max_policy_lag {
                    buffer.remove(i);
                    buffer_from.remove(i);
                    stale += 1;
                } else {
                    i += 1;
                }
            }
            round = None;
            last_grant = Instant::now() - Duration::from_secs(60);
            let steps: usize = trajs.iter().map(|t| t.len()).sum();
            let rec = IterationRecord {
                iteration,
                policy_version: ppo.version,
                time_s: start.elapsed().as_secs_f64(),
                episodes: trajs.len(),
                total_episodes: episodes,
                steps,
                env_steps,
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
                episodes_received: received,
                dropped_stale: stale,
                dropped_duplicate: dup,
                dropped_bad: bad,
                refused: stats.refused.clone(),
                gradient_steps: stats.gradient_steps,
                kl_stop: stats.kl_stop,
                lr,
            };
            noted(
                &run,
                "metrics.jsonl: an update's line not written",
                run.append_metrics(&serde_json::to_value(&rec).expect("JSON")),
            );
            if let Some(r) = recorder.as_mut() {
                noted(
                    &run,
                    "an update's sim-trace, metrics JSON or MCAP not written",
                    r.iteration(&rec, &trajs, &from),
                );
            }
            observer.iteration(&rec);
            last_status = Instant::now() - Duration::from_secs(60);
        }

        // 3. Flow control: grant what the next update still needs.
        let workers = link.workers();
        let shortfall = want.saturating_sub(buffer.len() as u64);
        // A round is spent when every worker it granted delivered or went away; it is void when
        // nothing came for much longer than rounds take (a batch lost while a peer's
        // subscription was still on its way, say): then the shortfall is granted anew.
        let stall_after = round_seconds.map_or(30.0, |s| (4.0 * s).max(10.0));
        let round_spent = round.as_ref().is_none_or(|r| {
            let stalled = r.last_delivery.elapsed().as_secs_f64() > stall_after;
            if stalled {
                tracing::warn!(run = %spec.name, version = r.credit.version, "no episodes for {stall_after:.0} s: granting the shortfall again");
            }
            stalled
                || r.credit.episodes.iter().all(|(w, n)| r.delivered.get(w).copied().unwrap_or(0) >= *n || !workers.contains(w))
        });
        if stop_reason.is_none() && shortfall > 0 && round_spent {
            let number = round.as_ref().map(|r| r.credit.round + 1).unwrap_or(round_base + 1);
            round = new_round(ppo.version, number, shortfall, &workers);
            tracing::debug!(run = %spec.name, version = ppo.version, shortfall, workers = ?workers, granted = round.is_some(), "grant round");
            last_grant = Instant::now() - Duration::from_secs(60);
        }
        if let Some(r) = &round
            && last_grant.elapsed() >= Duration::from_secs(1)
        {
            link.grant(&r.credit)?;
            last_grant = Instant::now();
        }

        // 4. Checkpoints when due (every `eval_seconds`, and the last version when stopping);
        // each is evaluated on the workers unless an evaluation is still under way.
        let due = iterations_here > 0
            && stop_reason.is_none()
            && saved_iteration != Some(iteration)
            && last_eval.is_none_or(|t| t.elapsed() >= eval_every);
        let final_due = stop_reason.is_some()
            && iterations_here > 0
            && evaluated_version != Some(ppo.version)
            && pending.is_none()
            && !workers.is_empty();
        if due || final_due {
            let name = RunDir::checkpoint_name(iteration);
            let manifest = manifest_for(
                &ppo,
                serde_json::json!({"run": spec.name, "worlds": spec.worlds, "iteration": iteration, "episodes": episodes,
                    "env_steps": env_steps, "seconds": start.elapsed().as_secs_f64(), "hyperparameters": hyper}),
            );
            if saved_iteration != Some(iteration) {
                // A checkpoint that cannot be written (a full disk) is reported and training
                // goes on: the previous checkpoint stays the one a restart resumes from.
                let written = folder::save_signed(
                    &run.checkpoint_dir(&name),
                    &spec.metadata,
                    &ppo.model,
                    &manifest,
                    Some(&signer),
                )
                .map_err(|e| e.to_string())
                .and_then(|_| {
                    run.record_last(CheckpointRecord {
                        name: name.clone(),
                        iteration,
                        policy_version: ppo.version,
                        avg_eval_metric: 0.0,
                        avg_lap_time: None,
                        time_stamp: start.elapsed().as_secs_f64(),
                    })
                    .map_err(|e| e.to_string())
                });
                if let Err(e) = written {
                    let kept = run
                        .index()
                        .ok()
                        .and_then(|i| i.last_checkpoint)
                        .map(|l| l.name)
                        .unwrap_or_else(|| "none".into());
                    run.note_failure(format!(
                        "checkpoint {name} not written ({e}); the last checkpoint is still {kept}"
                    ));
                }
                saved_iteration = Some(iteration);
            }
            last_eval = Some(Instant::now());
            if pending.is_none() && !workers.is_empty() {
                let mut p = PendingEval {
                    iteration,
                    version: ppo.version,
                    model: ppo.model.clone(),
                    manifest,
                    name,
                    asked: BTreeMap::new(),
                    done: BTreeMap::new(),
                };
                for world in &spec.worlds {
                    turns.ask(&mut p, link, spec, &workers, world.clone(), 1)?;
                }
                pending = Some(p);
            }
        }
        if let Some(p) = pending.as_mut() {
            // Ask again every few seconds (a request can be lost while the worker's subscription
            // is on its way; the worker answers a repeat from its cache); ask another worker when
            // this one went away or never answered.
            if last_eval_ask.elapsed() >= EVAL_REPEAT {
                last_eval_ask = Instant::now();
                for (id, (world, w, _, _)) in &p.asked {
                    link.request_eval(&p.request(spec, *id, w, world))?;
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
                turns.retry(p, link, spec, &workers, world, attempts)?;
            }
        }
        if pending.as_ref().is_some_and(|p| p.asked.is_empty()) {
            let p = pending.take().expect("checked");
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
                time_stamp: start.elapsed().as_secs_f64(),
            };
            let mut manifest = p.manifest.clone();
            if let Some(obj) = manifest.training.as_object_mut() {
                obj.insert("eval_progress".into(), progress.into());
                obj.insert("eval_lap_time".into(), serde_json::json!(lap_time));
                obj.insert("eval_worlds".into(), serde_json::to_value(&per_world).expect("JSON"));
            }
            let is_best = noted(&run, "the checkpoint index not written", run.record(rec.clone())).unwrap_or(false);
            evaluated_version = Some(p.version);
            if is_best || !run.model_dir().join("manifest.json").exists() {
                noted(
                    &run,
                    &format!("the best model (v{}) not written; model/ holds the previous best", p.version),
                    folder::save_signed(&run.model_dir(), &spec.metadata, &p.model, &manifest, Some(&signer)),
                );
            }
            if is_best {
                let best_policy =
                    PolicyVersion { version: p.version, model: Arc::new(p.model.clone()), metadata: metadata.clone() };
                link.best(&best_policy, &manifest, &signer)?;
            }
            if is_best {
                best = Some(rec);
            }
            if let Some(t) = spec.stop.target_laps {
                lap_streak =
                    if t.laps > 0 && min_laps >= t.laps.min(spec.eval_trials as usize) { lap_streak + 1 } else { 0 };
            }
            last_eval_figures = (progress, min_laps as u64);
            let mut e = EvalRecord {
                iteration: p.iteration,
                policy_version: p.version,
                worlds: per_world,
                progress,
                lap_time,
                min_laps,
                trials: spec.eval_trials as usize,
                best: is_best,
                simtrace: Vec::new(),
                trend: String::new(),
            };
            let now = trend.push(p.iteration, progress);
            if std::mem::discriminant(&now) != std::mem::discriminant(&verdict) {
                match &now {
                    Verdict::Improving => tracing::info!(run = %spec.name, "evaluation progress improving again"),
                    v => tracing::warn!(run = %spec.name, "{}", v.describe()),
                }
            }
            verdict = now;
            e.trend = verdict.describe();

            if let Some(r) = recorder.as_mut() {
                e.simtrace = noted(
                    &run,
                    "an evaluation's sim-trace, metrics JSON or MCAP not written",
                    r.evaluation(&e, &p.done),
                )
                .unwrap_or_default();
            }
            noted(
                &run,
                "evaluations.jsonl: an evaluation's line not written",
                run.append_evaluation(&serde_json::to_value(&e).expect("JSON")),
            );
            observer.evaluation(&e);
            // The final evaluation (of the last version) closes a stopping run.
            if stop_reason.is_some() && p.version == ppo.version {
                break;
            }
        }

        // 5. Stop rules.
        if stop_reason.is_none() {
            let full = recent.len() as u64 >= spec.stop.window.max(1);
            let standing = Standing {
                seconds: start.elapsed().as_secs_f64(),
                episodes,
                env_steps,
                window: full.then(|| (mean(recent.iter().map(|r| r.0)), mean(recent.iter().map(|r| r.1)))),
                lap_streak,
                verdict: verdict.clone(),
            };
            if let Some(why) = spec.stop.check(hyper, &standing) {
                tracing::info!(run = %spec.name, "stopping: {why}");
                stop_reason = Some(why);
                round = None;
            }
        }
        if stop_reason.is_some() {
            // Done once the last version's evaluation is recorded (or there is nothing to
            // evaluate, or nobody left to evaluate it).
            if iterations_here == 0 || (pending.is_none() && evaluated_version == Some(ppo.version)) {
                break;
            }
            if workers.is_empty() {
                tracing::warn!(run = %spec.name, "no worker left to run the final evaluation");
                break;
            }
        }

        // 6. Status.
        if last_status.elapsed() >= Duration::from_secs(1) {
            last_status = Instant::now();
            let s = status(
                &ppo,
                iteration,
                episodes,
                received,
                env_steps,
                &recent,
                max_lag,
                (stale, dup, bad),
                last_eval_figures,
                &mut windows,
                &mut per_worker,
                &run,
            );
            link.status(&RunStatus { stop_reason: stop_reason.clone(), trend: verdict.describe(), ..s })?;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let reason = stop_reason.unwrap_or_else(|| "stopped".into());
    let mut s = status(
        &ppo,
        iteration,
        episodes,
        received,
        env_steps,
        &recent,
        max_lag,
        (stale, dup, bad),
        last_eval_figures,
        &mut windows,
        &mut per_worker,
        &run,
    );
    s.finished = true;
    s.trend = verdict.describe();
    s.stop_reason = Some(reason.clone());
    link.status(&s)?;
    if let Some(r) = recorder.as_mut() {
        noted(&run, "the run's logs not closed", r.finish());
    }
    let (write_failures, write_error) = run.failures();
    let summary = run.write_file(
        "summary.json",
        serde_json::to_string_pretty(&serde_json::json!({
            "run": spec.name, "worlds": spec.worlds, "iterations": iteration, "episodes": episodes,
            "episodes_received": received, "dropped_stale": stale, "env_steps": env_steps,
            "seconds": seconds, "stop_reason": reason, "best": best, "policy_version": ppo.version,
            "write_failures": write_failures, "write_error": write_error, "trend": verdict.describe(),
        }))
        .expect("JSON")
        .as_bytes(),
    );
    noted(&run, "summary.json not written", summary);
    tracing::info!(run = %spec.name, version = ppo.version, "run finished: {reason}");
    Ok(Summary {
        stop_reason: reason,
        iterations: iteration,
        episodes,
        episodes_received: received,
        dropped_stale: stale,
        env_steps,
        seconds,
        best,
        policy_version: ppo.version,
        run_dir: spec.out.clone(),
        write_failures: run.failures(),
    })
}

#[allow(clippy::too_many_arguments)]
fn status(
    ppo: &Ppo,
    iteration: u64,
    episodes: u64,
    received: u64,
    env_steps: u64,
    recent: &VecDeque<(f64, f64)>,
    max_lag: u64,
    (stale, dup, bad): (u64, u64, u64),
    (eval_progress, eval_laps): (f64, u64),
    windows: &mut BTreeMap<String, WorldWindow>,
    per_worker: &mut BTreeMap<String, VecDeque<(Instant, u64)>>,
    run: &RunDir,
) -> RunStatus {
    let now = Instant::now();
    let ten = Duration::from_secs(10);
    let worlds = windows
        .iter_mut()
        .map(|(name, w)| {
            while w.recent.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                w.recent.pop_front();
            }
            while w.steps.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                w.steps.pop_front();
            }
            let span = w.steps.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
            let workers: BTreeSet<&String> = w.recent.iter().map(|r| &r.1).collect();
            WorldFigures {
                world: name.clone(),
                workers: workers.len() as u32,
                episodes: w.episodes,
                mean_progress: mean(w.recent.iter().map(|r| r.2)),
                mean_reward: mean(w.recent.iter().map(|r| r.3)),
                steps_per_s: w.steps.iter().map(|r| r.1).sum::<u64>() as f64 / span,
            }
        })
        .collect();
    let workers = per_worker
        .iter_mut()
        .filter_map(|(id, q)| {
            while q.front().is_some_and(|r| now.duration_since(r.0) > ten) {
                q.pop_front();
            }
            let span = q.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
            (!q.is_empty()).then(|| (id.clone(), q.iter().map(|r| r.1).sum::<u64>() as f64 / span))
        })
        .collect();
    let (write_failures, write_error) = run.failures();
    RunStatus {
        policy_version: ppo.version,
        iteration,
        episodes,
        episodes_received: received,
        env_steps,
        window_reward: mean(recent.iter().map(|r| r.1)),
        window_progress: mean(recent.iter().map(|r| r.0)),
        max_lag,
        dropped_stale: stale,
        dropped_duplicate: dup,
        dropped_bad: bad,
        eval_progress,
        eval_laps,
        finished: false,
        stop_reason: None,
        run_dir: run.root().display().to_string(),
        worlds,
        workers,
        write_failures,
        write_error,
        trend: String::new(),
    }
}
