//! The run's logs in the formats the DeepRacer community and the robotics world read, written
//! by the learner from the experience it trains on (agents write nothing on their machines):
//!
//! - DeepRacer's sim-trace (simapp's `StepMetrics` columns) in deepracer-for-cloud's folder
//!   layout: `<worker>/training-simtrace/<N>-iteration.csv` per worker (numbered by first
//!   delivery, `metrics/workers.json`) and `evaluation-<YYYYMMDDHHMMSS>/evaluation-simtrace/
//!   0-iteration.csv` per world evaluated, so `deepracer-utils` loads a run folder as it
//!   loads a DRfC model folder;
//! - DeepRacer's metrics JSON (simapp's `metrics/s3_metrics.py`):
//!   `metrics/TrainingMetrics[_<i>].json` (training and evaluation episodes; Paddock adds each
//!   episode's `world` and `paddock_iteration`) and `metrics/evaluation/evaluation-<ts>.json`
//!   per evaluation; `tracks.json`, the worlds' lines. A training metrics file is appended to
//!   in place ([`MetricsFile`]): a run of days writes each entry once and holds none;
//! - `metrics.jsonl`'s and `evaluations.jsonl`'s lines: [`IterationRecord`] (each update)
//!   and [`EvalRecord`] (each evaluation), which the run writes and its observers hear;
//! - `trace.mcap` for Foxglove: the tracks (`foxglove.SceneUpdate`), each step's pose
//!   (`foxglove.PoseInFrame`) and figures, each update's figures, each evaluation trial (and,
//!   in camera jobs, what the car saw in the first trial, `foxglove.RawImage` mono8), as
//!   JSON with JSON schemas. Episodes are laid end to end on the log's timeline (each at
//!   simulation speed, a second apart), so scrubbing plays one episode after another;
//!   `publish_time` is the wall clock when the step was taken.
//!
//! Only trajectories that carry their steps' traces (`record_trace`, on by default) are
//! written; only what the learner trains on is written (as DeepRacer logs only what its
//! trainer receives).

use crate::algorithm::UpdateStats;
use crate::sac::SacFigures;
use policy::exchange::Trial;
use policy::simtrace::{HEADER, Row, action_text, write_row, write_trajectory};
use policy::{ActionSpace, StepTrace, TrackLines, Trajectory};
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// One update, as `metrics.jsonl` records it.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
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
    /// The learning process's resident memory (MiB) once the update was made and its episodes
    /// dropped (a soak's floor; mimalloc returns freed pages about a second later, so it also
    /// holds the batch just freed, which capped episodes keep steady); absent where the
    /// system does not tell it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resident_mb: Option<f64>,
    /// The bytes the process's allocations hold (MiB) at the same moment: what a leak grows,
    /// where resident memory also grows with what the allocator keeps back; absent where the
    /// binary does not count them (`count_live_bytes_with`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live_mb: Option<f64>,
    /// Of those, the episodes received and waiting for the next update (MiB): experience in
    /// flight, which the rounds bound, not kept; present with `live_mb`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waiting_mb: Option<f64>,
    /// SAC's figures (the Q loss, the temperature, the replay memory); absent for PPO.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sac: Option<SacFigures>,
}

impl IterationRecord {
    /// Take the update's figures from its algorithm's own: PPO's fill the PPO columns, SAC's
    /// its columns and `sac`; the rest stay zero (a refused update's are all zero).
    pub fn take_figures(&mut self, stats: &UpdateStats) {
        match stats {
            UpdateStats::Ppo(s) => {
                (self.policy_loss, self.value_loss, self.entropy) = (s.policy_loss, s.value_loss, s.entropy);
                (self.approx_kl, self.clip_fraction, self.explained_variance) =
                    (s.approx_kl, s.clip_fraction, s.explained_variance);
                (self.gradient_steps, self.kl_stop) = (s.gradient_steps, s.kl_stop);
            }
            UpdateStats::Sac(s) => {
                (self.policy_loss, self.value_loss, self.entropy) = (s.policy_loss, s.value_loss, s.entropy);
                self.gradient_steps = s.gradient_steps;
                self.sac = Some(s.figures);
            }
        }
    }
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
    /// Mean reward over every trial (DeepRacer's evaluation reward).
    pub reward: f64,
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
    /// Bots overtaken in all its trials, in a race with bots.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub overtakes: Option<u32>,
    /// This is the verification of a checkpoint that met the lap target (its own trials, with
    /// fresh noise), not a new checkpoint's evaluation.
    pub verification: bool,
}

/// The MCAP file of a new run (a resumed run writes `trace-<iteration>.mcap`).
pub const MCAP_FILE: &str = "trace.mcap";

/// How the binary's allocator counts the bytes held (set once, by `main`).
static LIVE_BYTES: std::sync::OnceLock<fn() -> usize> = std::sync::OnceLock::new();

/// Have each update's record carry the bytes `probe` says the process's allocations hold (the
/// binary's global allocator counts them; a library cannot).
pub fn count_live_bytes_with(probe: fn() -> usize) {
    let _ = LIVE_BYTES.set(probe);
}

/// The bytes held (MiB), where the binary counts them.
pub(crate) fn live_mb() -> Option<f64> {
    LIVE_BYTES.get().map(|probe| probe() as f64 / (1024.0 * 1024.0))
}

/// Writes a run's logs. Errors are returned for the caller to note; nothing here stops a run.
pub struct Recorder {
    dir: PathBuf,
    space: ActionSpace,
    workers: Vec<String>,
    /// Per worker: training episodes written (DeepRacer's 0-based episode counter).
    episodes: Vec<u64>,
    /// Per worker: its metrics JSON.
    metrics: Vec<MetricsFile>,
    metrics_written: Instant,
    mcap: Option<Mcap>,
    /// The next free instant on the MCAP timeline (ns since the Unix epoch).
    cursor: u64,
    last_eval_stamp: String,
}

/// A worker's metrics JSON (`{"version": 2.0, "best_model_metric": "progress", "metrics":
/// [...]}`), its `metrics` array last: new entries overwrite the closing `]}` with `,` and
/// themselves and `]}` again, one write, so the file stays whole JSON after each and a run of
/// days neither holds its entries nor rewrites them. A write cut short (a full disk) is
/// written again from the same place by the next flush, and the file cut to its end.
struct MetricsFile {
    path: PathBuf,
    /// Entries in the file.
    written: u64,
    /// Where the closing `]}` of the last whole write begins.
    end: u64,
    /// Entries still to be written.
    pending: Vec<Value>,
}

const METRICS_HEAD: &str = r#"{"version":2.0,"best_model_metric":"progress","metrics":["#;
const METRICS_TAIL: &str = "]}";

impl MetricsFile {
    fn new(path: PathBuf) -> MetricsFile {
        MetricsFile { path, written: 0, end: 0, pending: Vec::new() }
    }

    /// A resumed run's file: its entries read (a legacy layout or a last write cut short
    /// mended, the file written again whole); returns it and its training episodes. A file
    /// that is not a metrics JSON at all (empty after a power loss, say) is moved aside to
    /// `<name>.unreadable`, with a warning, and the worker's metrics start again.
    fn resume(path: PathBuf) -> std::io::Result<(MetricsFile, u64)> {
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((MetricsFile::new(path), 0)),
            Err(e) => return Err(e),
        };
        let text = String::from_utf8_lossy(&bytes);
        let Some(entries) = metrics_entries(&text) else {
            let aside = path.with_extension("json.unreadable");
            std::fs::rename(&path, &aside)?;
            tracing::warn!(
                "{}: expected DeepRacer's metrics JSON, an object with a `metrics` array; moved to {} and started again",
                path.display(),
                aside.display()
            );
            return Ok((MetricsFile::new(path), 0));
        };
        let training = entries.iter().filter(|e| e["phase"] == "training").count() as u64;
        let mut whole = String::from(METRICS_HEAD);
        for (i, e) in entries.iter().enumerate() {
            if i > 0 {
                whole.push(',');
            }
            whole.push_str(&serde_json::to_string(e)?);
        }
        whole.push_str(METRICS_TAIL);
        if whole.as_bytes() != bytes {
            write_whole(&path, whole.as_bytes())?;
        }
        let end = (whole.len() - METRICS_TAIL.len()) as u64;
        Ok((MetricsFile { path, written: entries.len() as u64, end, pending: Vec::new() }, training))
    }

    /// Write the pending entries: the file made whole the first time, appended to after.
    fn flush(&mut self) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        if self.pending.is_empty() {
            return Ok(());
        }
        let mut add = String::new();
        for (i, e) in self.pending.iter().enumerate() {
            if i > 0 || self.written > 0 {
                add.push(',');
            }
            add.push_str(&serde_json::to_string(e)?);
        }
        add.push_str(METRICS_TAIL);
        let end = if self.written == 0 {
            std::fs::create_dir_all(self.path.parent().expect("has a parent"))?;
            let whole = format!("{METRICS_HEAD}{add}");
            write_whole(&self.path, whole.as_bytes())?;
            whole.len()
        } else {
            let f = std::fs::OpenOptions::new().write(true).open(&self.path)?;
            f.write_all_at(add.as_bytes(), self.end)?;
            // What a write cut short had left past the end goes.
            f.set_len(self.end + add.len() as u64)?;
            self.end as usize + add.len()
        };
        self.end = (end - METRICS_TAIL.len()) as u64;
        self.written += self.pending.len() as u64;
        self.pending.clear();
        Ok(())
    }
}

/// The `metrics` entries of a metrics JSON's text; a text whose last write was cut short
/// (the file ends inside the array) gives the entries before the cut.
fn metrics_entries(text: &str) -> Option<Vec<Value>> {
    if let Ok(v) = serde_json::from_str::<Value>(text) {
        return v["metrics"].as_array().cloned();
    }
    // Entries are flat objects: the whole ones end at a `}` the array can close after.
    let open = text.find('[')?;
    let mut ends: Vec<usize> = text[open..].rmatch_indices('}').map(|(i, _)| open + i + 1).take(64).collect();
    ends.push(open + 1);
    ends.into_iter().find_map(|end| {
        let v: Value = serde_json::from_str(&format!("{}{METRICS_TAIL}", &text[..end])).ok()?;
        v["metrics"].as_array().cloned()
    })
}

/// Write `bytes` to `path` whole (a temporary file, then a rename).
fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    crate::checkpoints::write_atomic(path, bytes).map_err(std::io::Error::other)
}

fn ms(seconds: f64) -> i64 {
    (seconds * 1000.0).round() as i64
}

fn ns(seconds: f64) -> u64 {
    (seconds.max(0.0) * 1e9) as u64
}

/// A metrics JSON entry for one episode (as simapp's `metrics/s3_metrics.py` writes it).
fn episode_metrics(trace: &[StepTrace], rewards: &[f32], progress: f64) -> Value {
    let start = trace.first().map(|t| t.tstamp).unwrap_or(0.0);
    let end = trace.last().map(|t| t.tstamp).unwrap_or(0.0);
    let status = trace.last().map(|t| t.status).unwrap_or_default();
    json!({
        "reward_score": rewards.iter().map(|&r| r as f64).sum::<f64>().round() as i64,
        "metric_time": ms(end),
        "start_time": ms(start),
        "elapsed_time_in_milliseconds": ms(end - start),
        "completion_percentage": progress.floor() as i64,
        "episode_status": status.metrics_label(),
    })
}

impl Recorder {
    /// Open the logs of the run folder `dir`: a new run starts them; a resumed run (first
    /// iteration > 0) goes on with its workers' numbers, episode counters and metrics.
    pub fn open(
        dir: &Path,
        space: &ActionSpace,
        tracks: &[TrackLines],
        first_iteration: u64,
    ) -> std::io::Result<Recorder> {
        let mut r = Recorder {
            dir: dir.to_path_buf(),
            space: space.clone(),
            workers: Vec::new(),
            episodes: Vec::new(),
            metrics: Vec::new(),
            metrics_written: Instant::now(),
            mcap: None,
            cursor: ns(crate::record::unix_now()),
            last_eval_stamp: String::new(),
        };
        if first_iteration > 0 {
            if let Ok(text) = std::fs::read_to_string(dir.join("metrics/workers.json")) {
                r.workers = serde_json::from_str(&text).unwrap_or_default();
            }
            for i in 0..r.workers.len() {
                let (file, training) = MetricsFile::resume(r.metrics_path(i))?;
                r.episodes.push(training);
                r.metrics.push(file);
            }
        }
        if !tracks.is_empty() {
            // The worlds' lines, for reports drawn from the run folder alone.
            write_whole(&dir.join("tracks.json"), serde_json::to_string(tracks)?.as_bytes())?;
        }
        let name = if first_iteration > 0 { format!("trace-{first_iteration}.mcap") } else { MCAP_FILE.into() };
        let mut mcap = Mcap::create(&dir.join(name))?;
        mcap.tracks(tracks, r.cursor)?;
        r.mcap = Some(mcap);
        Ok(r)
    }

    fn metrics_path(&self, worker: usize) -> PathBuf {
        let name =
            if worker == 0 { "TrainingMetrics.json".to_string() } else { format!("TrainingMetrics_{worker}.json") };
        self.dir.join("metrics").join(name)
    }

    fn worker_index(&mut self, worker: &str) -> std::io::Result<usize> {
        if let Some(i) = self.workers.iter().position(|w| w == worker) {
            return Ok(i);
        }
        self.workers.push(worker.to_string());
        self.episodes.push(0);
        self.metrics.push(MetricsFile::new(self.metrics_path(self.workers.len() - 1)));
        write_whole(&self.dir.join("metrics/workers.json"), serde_json::to_string(&self.workers)?.as_bytes())?;
        Ok(self.workers.len() - 1)
    }

    /// One update's episodes: their sim-trace (`from[i]` is the worker of `trajs[i]`), metrics
    /// and MCAP messages; [`Recorder::figures`] then records the update's figures.
    pub fn episodes(&mut self, rec: &IterationRecord, trajs: &[Trajectory], from: &[String]) -> std::io::Result<()> {
        let mut by_worker: BTreeMap<usize, Vec<&Trajectory>> = BTreeMap::new();
        for (t, w) in trajs.iter().zip(from) {
            if !t.trace.is_empty() && t.trace.len() == t.len() {
                let i = self.worker_index(w)?;
                by_worker.entry(i).or_default().push(t);
            }
        }
        // DeepRacer numbers iteration files from 0.
        let file = format!("{}-iteration.csv", rec.iteration.saturating_sub(1));
        for (i, ts) in &by_worker {
            let path = self.dir.join(i.to_string()).join("training-simtrace").join(&file);
            std::fs::create_dir_all(path.parent().expect("has a parent"))?;
            let mut out = BufWriter::new(File::create(&path)?);
            writeln!(out, "{HEADER}")?;
            for (trial, t) in ts.iter().enumerate() {
                let episode = self.episodes[*i];
                write_trajectory(&mut out, episode, t, &self.space)?;
                self.episodes[*i] += 1;
                let mut m = episode_metrics(&t.trace, &t.rewards, t.progress);
                m["episode"] = json!(episode + 1);
                m["trial"] = json!(trial + 1);
                m["phase"] = json!("training");
                // Paddock's additions (deepracer-utils ignores them): which world, which update.
                m["world"] = json!(t.world);
                m["paddock_iteration"] = json!(rec.iteration);
                self.metrics[*i].pending.push(m);
                if let Some(mcap) = self.mcap.as_mut() {
                    self.cursor = mcap.episode(self.cursor, "/training", &self.workers[*i], episode, t, &self.space)?;
                }
            }
            out.flush()?;
        }
        if self.metrics_written.elapsed() >= Duration::from_secs(5) {
            self.write_metrics()?;
        }
        Ok(())
    }

    /// One update's figures (`metrics.jsonl`'s line) in the MCAP, after its episodes.
    pub fn figures(&mut self, rec: &IterationRecord) -> std::io::Result<()> {
        if let Some(mcap) = self.mcap.as_mut() {
            mcap.figures("/learner/iteration", "paddock.Iteration", self.cursor, &serde_json::to_value(rec)?)?;
        }
        Ok(())
    }

    /// One evaluation: per world, an `evaluation-<ts>` sim-trace folder and a metrics file,
    /// evaluation entries in worker 0's training metrics, the trials in the MCAP. Returns
    /// the folders written, per world.
    pub fn evaluation(
        &mut self,
        e: &EvalRecord,
        trials: &BTreeMap<String, Vec<Trial>>,
    ) -> std::io::Result<Vec<(String, String)>> {
        let mut written = Vec::new();
        for (world, ts) in trials {
            if ts.is_empty() || ts.iter().any(|t| t.trace.is_empty() || t.trace.len() != t.rewards.len()) {
                continue;
            }
            let stamp = self.eval_stamp();
            let folder = format!("evaluation-{stamp}");
            let csv = self.dir.join(&folder).join("evaluation-simtrace").join("0-iteration.csv");
            std::fs::create_dir_all(csv.parent().expect("has a parent"))?;
            let mut out = BufWriter::new(File::create(&csv)?);
            writeln!(out, "{HEADER}")?;
            let mut entries = Vec::new();
            let episode0 = self.episodes.first().copied().unwrap_or(0);
            for (k, t) in ts.iter().enumerate() {
                let n = t.trace.len();
                for (s, ((tr, c), r)) in t.trace.iter().zip(&t.choices).zip(&t.rewards).enumerate() {
                    let action = action_text(c, &self.space);
                    let (episode, step, reward, done) = (k as u64, s as u64 + 1, *r as f64, s + 1 == n);
                    let row = Row { episode, step, trace: tr, action: &action, reward, done, track_len: t.track_len };
                    write_row(&mut out, &row)?;
                }
                let mut m = episode_metrics(&t.trace, &t.rewards, t.progress);
                let resets = t.off_track.saturating_sub(u32::from(t.status == "off_track"))
                    + t.crashes.saturating_sub(u32::from(t.status == "crashed"));
                let eval_entry = json!({
                    "completion_percentage": m["completion_percentage"],
                    "metric_time": m["metric_time"],
                    "start_time": m["start_time"],
                    "elapsed_time_in_milliseconds": m["elapsed_time_in_milliseconds"],
                    "episode_status": m["episode_status"],
                    "crash_count": t.crashes,
                    "immobilized_count": u32::from(t.status == "immobilized"),
                    "off_track_count": t.off_track,
                    "reversed_count": u32::from(t.status == "reversed"),
                    "reset_count": resets,
                    "trial": k + 1,
                });
                entries.push(eval_entry);
                m["episode"] = json!(episode0);
                m["trial"] = json!(k + 1);
                m["phase"] = json!("evaluation");
                m["world"] = json!(world);
                m["paddock_iteration"] = json!(e.iteration);
                if self.metrics.is_empty() {
                    self.worker_index("evaluation")?;
                }
                self.metrics[0].pending.push(m);
                if let Some(mcap) = self.mcap.as_mut() {
                    let as_traj = Trajectory {
                        world: world.clone(),
                        episode: k as u64,
                        policy_version: e.policy_version,
                        choices: t.choices.clone(),
                        rewards: t.rewards.clone(),
                        done: true,
                        progress: t.progress,
                        track_len: t.track_len,
                        trace: t.trace.clone(),
                        ..Default::default()
                    };
                    let at = self.cursor;
                    self.cursor = mcap.episode(at, "/evaluation", "evaluation", k as u64, &as_traj, &self.space)?;
                    mcap.frames(at, &t.trace, &t.frames)?;
                }
            }
            out.flush()?;
            write_whole(
                &self.dir.join("metrics/evaluation").join(format!("{folder}.json")),
                serde_json::to_string(&json!({ "metrics": entries }))?.as_bytes(),
            )?;
            written.push((world.clone(), folder));
        }
        if let Some(mcap) = self.mcap.as_mut() {
            mcap.figures("/learner/evaluation", "paddock.Evaluation", self.cursor, &serde_json::to_value(e)?)?;
        }
        // The folders are written: a metrics file that could not be is noted, tried again
        // on the clock, and does not hide them.
        if let Err(e) = self.write_metrics() {
            tracing::warn!("the metrics JSON not written (tried again later): {e}");
        }
        Ok(written)
    }

    /// A folder stamp (UTC, to the second) not used before in this run folder.
    fn eval_stamp(&mut self) -> String {
        let mut t = chrono::Utc::now();
        loop {
            let s = t.format("%Y%m%d%H%M%S").to_string();
            if s > self.last_eval_stamp && !self.dir.join(format!("evaluation-{s}")).exists() {
                self.last_eval_stamp = s.clone();
                return s;
            }
            t += chrono::Duration::seconds(1);
        }
    }

    /// Write every worker's pending metrics entries.
    pub fn write_metrics(&mut self) -> std::io::Result<()> {
        // Every worker's file, whatever another's write met; the first error is returned, and
        // what failed is tried again on the clock.
        self.metrics_written = Instant::now();
        let mut first = Ok(());
        for m in &mut self.metrics {
            if let Err(e) = m.flush() {
                first = first.and(Err(e));
            }
        }
        first
    }

    /// Write what is pending and close the MCAP file (its summary and index).
    pub fn finish(&mut self) -> std::io::Result<()> {
        // The MCAP is closed (its summary and index) whatever the metrics met.
        let metrics = self.write_metrics();
        if let Some(mut m) = self.mcap.take() {
            m.finish()?;
        }
        metrics
    }
}

pub use policy::simtrace::unix_now;

fn mcap_err(e: mcap::McapError) -> std::io::Error {
    std::io::Error::other(e)
}

/// Foxglove's `foxglove.PoseInFrame`, as a JSON schema.
const POSE_IN_FRAME: &str = r#"{"title":"foxglove.PoseInFrame","description":"A timestamped pose for an object or reference frame in 3D space","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}}}}"#;

/// Foxglove's `foxglove.SceneUpdate` (the parts used: entities of line strips), as a JSON schema.
const SCENE_UPDATE: &str = r#"{"title":"foxglove.SceneUpdate","description":"An update to the entities displayed in a 3D scene","type":"object","properties":{"deletions":{"type":"array","items":{"type":"object"}},"entities":{"type":"array","items":{"type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"frame_id":{"type":"string"},"id":{"type":"string"},"lifetime":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"frame_locked":{"type":"boolean"},"metadata":{"type":"array"},"arrows":{"type":"array"},"cubes":{"type":"array"},"spheres":{"type":"array"},"cylinders":{"type":"array"},"lines":{"type":"array","items":{"type":"object","properties":{"type":{"type":"integer"},"pose":{"type":"object"},"thickness":{"type":"number"},"scale_invariant":{"type":"boolean"},"points":{"type":"array","items":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}}},"color":{"type":"object","properties":{"r":{"type":"number"},"g":{"type":"number"},"b":{"type":"number"},"a":{"type":"number"}}},"colors":{"type":"array"},"indices":{"type":"array"}}}},"triangles":{"type":"array"},"texts":{"type":"array"},"models":{"type":"array"}}}}}}"#;

/// Foxglove's `foxglove.RawImage`, as a JSON schema (`data` in base64, as Foxglove reads JSON).
const RAW_IMAGE: &str = r#"{"title":"foxglove.RawImage","description":"A raw image","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}},"frame_id":{"type":"string"},"width":{"type":"integer","minimum":0},"height":{"type":"integer","minimum":0},"encoding":{"type":"string"},"step":{"type":"integer","minimum":0},"data":{"type":"string","contentEncoding":"base64"}}}"#;

/// One step's figures (Paddock's own schema).
const STEP: &str = r#"{"title":"paddock.Step","type":"object","properties":{"world":{"type":"string"},"worker":{"type":"string"},"episode":{"type":"integer"},"step":{"type":"integer"},"policy_version":{"type":"integer"},"action":{"type":"string"},"steer":{"type":"number"},"throttle":{"type":"number"},"reward":{"type":"number"},"progress":{"type":"number"},"all_wheels_on_track":{"type":"boolean"},"closest_waypoint":{"type":"integer"},"status":{"type":"string"}}}"#;

fn stamp(t_ns: u64) -> Value {
    json!({"sec": t_ns / 1_000_000_000, "nsec": t_ns % 1_000_000_000})
}

/// The MCAP log.
struct Mcap {
    out: mcap::Writer<BufWriter<File>>,
    schemas: BTreeMap<&'static str, u16>,
    channels: BTreeMap<String, u16>,
    sequence: u32,
}

impl Mcap {
    fn create(path: &Path) -> std::io::Result<Mcap> {
        let out = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .profile("")
            .create(BufWriter::new(File::create(path)?))
            .map_err(mcap_err)?;
        Ok(Mcap { out, schemas: BTreeMap::new(), channels: BTreeMap::new(), sequence: 0 })
    }

    fn channel(&mut self, topic: &str, schema: &'static str, text: &str) -> std::io::Result<u16> {
        if let Some(c) = self.channels.get(topic) {
            return Ok(*c);
        }
        let sid = match self.schemas.get(schema) {
            Some(s) => *s,
            None => {
                let s = self.out.add_schema(schema, "jsonschema", text.as_bytes()).map_err(mcap_err)?;
                self.schemas.insert(schema, s);
                s
            }
        };
        let c = self.out.add_channel(sid, topic, "json", &BTreeMap::new()).map_err(mcap_err)?;
        self.channels.insert(topic.to_string(), c);
        Ok(c)
    }

    fn write(&mut self, channel: u16, log_time: u64, publish_time: u64, v: &Value) -> std::io::Result<()> {
        self.sequence = self.sequence.wrapping_add(1);
        let header =
            mcap::records::MessageHeader { channel_id: channel, sequence: self.sequence, log_time, publish_time };
        self.out.write_to_known_channel(&header, &serde_json::to_vec(v)?).map_err(mcap_err)
    }

    /// The tracks' lines, once, at the start of the log: centre line dashed grey, borders white.
    fn tracks(&mut self, tracks: &[TrackLines], at: u64) -> std::io::Result<()> {
        if tracks.is_empty() {
            return Ok(());
        }
        let c = self.channel("/track", "foxglove.SceneUpdate", SCENE_UPDATE)?;
        let line = |pts: &[[f64; 2]], rgb: [f64; 3], thickness: f64| {
            json!({
                "type": 0,
                "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                "thickness": thickness,
                "scale_invariant": false,
                "points": pts.iter().map(|p| json!({"x": p[0], "y": p[1], "z": 0.0})).collect::<Vec<_>>(),
                "color": {"r": rgb[0], "g": rgb[1], "b": rgb[2], "a": 1.0},
                "colors": [],
                "indices": [],
            })
        };
        let entities: Vec<Value> = tracks
            .iter()
            .map(|t| {
                json!({
                    "timestamp": stamp(at),
                    "frame_id": "track",
                    "id": t.world,
                    "lifetime": {"sec": 0, "nsec": 0},
                    "frame_locked": false,
                    "metadata": [{"key": "length_m", "value": format!("{:.3}", t.length)}],
                    "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "triangles": [], "texts": [], "models": [],
                    "lines": [line(&t.outer, [1.0, 1.0, 1.0], 0.05), line(&t.inner, [1.0, 1.0, 1.0], 0.05), line(&t.centre, [1.0, 0.8, 0.0], 0.02)],
                })
            })
            .collect();
        self.write(c, at, at, &json!({"deletions": [], "entities": entities}))
    }

    /// One episode's steps from `at` on (log time = `at` + simulation time); returns where the
    /// next episode starts (a second after this one's end).
    fn episode(
        &mut self,
        at: u64,
        prefix: &str,
        worker: &str,
        episode: u64,
        t: &Trajectory,
        space: &ActionSpace,
    ) -> std::io::Result<u64> {
        let pose = self.channel(&format!("{prefix}/pose"), "foxglove.PoseInFrame", POSE_IN_FRAME)?;
        let step = self.channel(&format!("{prefix}/step"), "paddock.Step", STEP)?;
        let t0 = t.trace.first().map(|s| s.tstamp).unwrap_or(0.0);
        let mut end = at;
        for (i, ((s, c), r)) in t.trace.iter().zip(&t.choices).zip(&t.rewards).enumerate() {
            let log = at + ns(s.tstamp - t0);
            let publish = ns(s.wall_clock);
            let half = (s.yaw as f64).to_radians() / 2.0;
            self.write(
                pose,
                log,
                publish,
                &json!({
                    "timestamp": stamp(log),
                    "frame_id": "track",
                    "pose": {"position": {"x": s.x, "y": s.y, "z": 0.0},
                             "orientation": {"x": 0.0, "y": 0.0, "z": half.sin(), "w": half.cos()}},
                }),
            )?;
            self.write(
                step,
                log,
                publish,
                &json!({
                    "world": t.world, "worker": worker, "episode": episode, "step": i + 1,
                    "policy_version": t.policy_version, "action": action_text(c, space),
                    "steer": s.steer, "throttle": s.throttle, "reward": r, "progress": s.progress,
                    "all_wheels_on_track": s.all_wheels_on_track, "closest_waypoint": s.closest_waypoint,
                    "status": s.status.label(),
                }),
            )?;
            end = log;
        }
        Ok(end + 1_000_000_000)
    }

    /// An evaluation trial's camera frames (grey, `mono8`), each at its step's place on the
    /// timeline of the trial that starts at `at`.
    fn frames(&mut self, at: u64, trace: &[StepTrace], frames: &[policy::exchange::Frame]) -> std::io::Result<()> {
        if frames.is_empty() {
            return Ok(());
        }
        use base64::Engine as _;
        let c = self.channel("/evaluation/camera", "foxglove.RawImage", RAW_IMAGE)?;
        let t0 = trace.first().map(|s| s.tstamp).unwrap_or(0.0);
        for f in frames {
            let here = trace.get(f.step.saturating_sub(1) as usize);
            let log = at + ns(here.map(|s| s.tstamp).unwrap_or(t0) - t0);
            let publish = here.map(|s| ns(s.wall_clock)).unwrap_or(log);
            self.write(
                c,
                log,
                publish,
                &json!({
                    "timestamp": stamp(log),
                    "frame_id": "camera",
                    "width": f.width,
                    "height": f.height,
                    "encoding": "mono8",
                    "step": f.width,
                    "data": base64::engine::general_purpose::STANDARD.encode(&f.gray),
                }),
            )?;
        }
        Ok(())
    }

    /// A record of figures (an update's, an evaluation's) under Paddock's own schema.
    fn figures(&mut self, topic: &str, schema: &'static str, at: u64, v: &Value) -> std::io::Result<()> {
        let text: &'static str = if schema == "paddock.Iteration" {
            r#"{"title":"paddock.Iteration","description":"One PPO update: metrics.jsonl's line","type":"object"}"#
        } else {
            r#"{"title":"paddock.Evaluation","description":"One evaluation over every world: evaluations.jsonl's line","type":"object"}"#
        };
        let c = self.channel(topic, schema, text)?;
        self.write(c, at, ns(unix_now()), v)
    }

    fn finish(&mut self) -> std::io::Result<()> {
        self.out.finish().map(|_| ()).map_err(mcap_err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ppo::PpoStats;
    use crate::sac::SacStats;

    fn entry(episode: u64, phase: &str) -> Value {
        json!({"episode": episode, "phase": phase, "completion_percentage": 100, "episode_status": "Lap complete"})
    }

    fn read_entries(path: &Path) -> Vec<Value> {
        let v: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        assert_eq!(v["version"], json!(2.0));
        assert_eq!(v["best_model_metric"], "progress");
        v["metrics"].as_array().unwrap().clone()
    }

    /// Issue 54: a metrics JSON is appended to in place, whole JSON after every write, and a
    /// resumed run goes on with its entries and its training episodes counted.
    #[test]
    fn a_metrics_file_is_appended_in_place_and_a_resumed_run_goes_on_with_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics/TrainingMetrics.json");
        let mut m = MetricsFile::new(path.clone());
        m.pending.extend([entry(1, "training"), entry(2, "training")]);
        m.flush().unwrap();
        assert_eq!(read_entries(&path).len(), 2);
        m.pending.push(entry(2, "evaluation"));
        m.flush().unwrap();
        m.flush().unwrap();
        let entries = read_entries(&path);
        assert_eq!(entries, vec![entry(1, "training"), entry(2, "training"), entry(2, "evaluation")]);
        let (mut again, training) = MetricsFile::resume(path.clone()).unwrap();
        assert_eq!((again.written, training), (3, 2));
        again.pending.push(entry(3, "training"));
        again.flush().unwrap();
        assert_eq!(read_entries(&path)[3], entry(3, "training"));
        // A write cut short (a full disk) left part of an entry past the end: the next flush
        // writes from the same place and cuts the file to its end.
        let whole = std::fs::read(&path).unwrap();
        let mut torn = whole[..whole.len() - METRICS_TAIL.len()].to_vec();
        torn.extend_from_slice(br#",{"episode":4,"pha"#);
        std::fs::write(&path, &torn).unwrap();
        again.pending.push(entry(4, "training"));
        again.flush().unwrap();
        let entries = read_entries(&path);
        assert_eq!((entries.len(), &entries[4]), (5, &entry(4, "training")));
    }

    /// Issue 54: a file whose last write was cut short (the machine lost power) resumes with
    /// the entries before the cut, and an older Paddock's layout (the array in the middle)
    /// resumes whole; each is written again whole in the appendable layout.
    #[test]
    fn a_metrics_file_cut_short_or_in_the_older_layout_resumes_with_its_whole_entries() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("TrainingMetrics.json");
        let whole = format!(
            "{METRICS_HEAD}{},{},{}{METRICS_TAIL}",
            entry(1, "training"),
            entry(2, "training"),
            entry(3, "training")
        );
        let cases: [(&str, String, usize); 4] = [
            ("cut inside the third entry", whole[..whole.len() - 20].to_string(), 2),
            ("cut after a comma", whole[..whole.rfind(",{").unwrap() + 1].to_string(), 2),
            ("cut before its first entry", METRICS_HEAD.to_string(), 0),
            (
                "the older layout",
                format!(
                    r#"{{"best_model_metric":"progress","metrics":[{},{}],"version":2.0}}"#,
                    entry(1, "training"),
                    entry(2, "evaluation")
                ),
                2,
            ),
        ];
        for (what, text, kept) in cases {
            std::fs::write(&path, &text).unwrap();
            let (mut m, _) = MetricsFile::resume(path.clone()).unwrap();
            assert_eq!(m.written as usize, kept, "{what}");
            assert_eq!(read_entries(&path).len(), kept, "{what}");
            m.pending.push(entry(9, "training"));
            m.flush().unwrap();
            assert_eq!(read_entries(&path).len(), kept + 1, "{what}");
        }
        // Not a metrics JSON at all (empty after a power loss, or anything else): moved aside,
        // and the worker's metrics start again.
        for junk in ["", "not JSON at all"] {
            std::fs::write(&path, junk).unwrap();
            let (mut m, training) = MetricsFile::resume(path.clone()).unwrap();
            assert_eq!((m.written, training), (0, 0));
            assert_eq!(std::fs::read_to_string(path.with_extension("json.unreadable")).unwrap(), junk);
            m.pending.push(entry(1, "training"));
            m.flush().unwrap();
            assert_eq!(read_entries(&path), vec![entry(1, "training")]);
        }
    }

    /// Issue 50: an update's line in `metrics.jsonl` takes PPO's figures into PPO's columns
    /// and SAC's into the shared columns and `sac`; what the algorithm does not have stays
    /// zero, and a line without SAC's figures has no `sac`.
    #[test]
    fn each_algorithms_figures_fill_its_own_columns() {
        let ppo = PpoStats {
            samples: 64,
            policy_loss: 0.5,
            value_loss: 2.0,
            entropy: 1.5,
            approx_kl: 0.01,
            clip_fraction: 0.25,
            explained_variance: 0.75,
            gradient_steps: 4,
            value_steps: 4,
            policy_version: 3,
            kl_stop: Some(4),
        };
        let figures =
            SacFigures { q_loss: 3.0, q_mean: -1.0, alpha: 0.2, replay: 500, new_transitions: 70, refused_episodes: 1 };
        let sac = SacStats {
            samples: 256,
            policy_loss: -0.5,
            value_loss: 0.125,
            entropy: 2.5,
            gradient_steps: 8,
            policy_version: 3,
            figures,
        };
        // (stats, (policy loss, value loss, entropy, KL, clip fraction, explained variance),
        // (gradient steps, KL stop), SAC's figures)
        for (stats, losses, steps, own) in [
            (UpdateStats::Ppo(ppo), (0.5, 2.0, 1.5, 0.01, 0.25, 0.75), (4, Some(4)), None),
            (UpdateStats::Sac(sac), (-0.5, 0.125, 2.5, 0.0, 0.0, 0.0), (8, None), Some(figures)),
        ] {
            let mut rec = IterationRecord { iteration: 7, lr: 3e-4, ..IterationRecord::default() };
            rec.take_figures(&stats);
            let r = &rec;
            let got = (r.policy_loss, r.value_loss, r.entropy, r.approx_kl, r.clip_fraction, r.explained_variance);
            assert_eq!(got, losses, "{stats:?}");
            assert_eq!(((r.gradient_steps, r.kl_stop), r.sac), (steps, own), "{stats:?}");
            assert_eq!((r.iteration, r.lr), (7, 3e-4), "the rest is the run's");
            let line = serde_json::to_value(r).unwrap();
            assert_eq!(line.get("sac").is_some(), own.is_some(), "{line}");
        }
    }
}
