//! Run folders and checkpoints.
//!
//! ```text
//! RUN/
//!   model/                      the best model so far (a model folder; the final answer)
//!   checkpoints/ckpt_000012/    a model folder per checkpoint (the last 4 and the best are kept)
//!   checkpoints/deepracer_checkpoints.json   {"best_checkpoint": …, "last_checkpoint": …}
//!   metrics.jsonl               one JSON line per iteration
//!   evaluations.jsonl           one JSON line per evaluation (every world)
//!   hyperparameters.json, model_metadata.json, sim.toml   the effective inputs
//! ```
//!
//! Every file is written to a temporary name and renamed into place. The best checkpoint is
//! chosen by mean evaluation progress, then by lap time.

use policy::FileError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Checkpoints kept besides the best.
pub const KEEP_LAST: usize = 4;

/// One checkpoint's record (DeepRacer's `deepracer_checkpoints.json` entries, plus figures).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckpointRecord {
    /// Folder name under `checkpoints/`.
    pub name: String,
    /// Training iteration.
    pub iteration: u64,
    /// Policy version of the weights.
    pub policy_version: u64,
    /// Mean evaluation progress (%) — DeepRacer's `avg_eval_metric` with `BEST_MODEL_METRIC=progress`.
    pub avg_eval_metric: f64,
    /// Mean lap time of the evaluation trials when all completed (s).
    pub avg_lap_time: Option<f64>,
    /// Seconds since training started.
    pub time_stamp: f64,
}

impl CheckpointRecord {
    /// Better by progress, then by lap time.
    pub fn better_than(&self, other: &CheckpointRecord) -> bool {
        if self.avg_eval_metric != other.avg_eval_metric {
            return self.avg_eval_metric > other.avg_eval_metric;
        }
        match (self.avg_lap_time, other.avg_lap_time) {
            (Some(a), Some(b)) => a < b,
            (Some(_), None) => true,
            _ => false,
        }
    }
}

/// `deepracer_checkpoints.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CheckpointIndex {
    /// The best so far.
    pub best_checkpoint: Option<CheckpointRecord>,
    /// The latest.
    pub last_checkpoint: Option<CheckpointRecord>,
}

/// Why a run folder could not be used.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// It exists and neither resuming nor forcing was asked for.
    #[error("{0} already exists: pass --resume to continue that run or --force to start it again")]
    Exists(String),
    /// Resuming a folder that holds no run.
    #[error("{0} holds no run to resume (no model/ folder)")]
    NothingToResume(String),
    /// A file of the folder could not be read or written, or holds something unexpected.
    #[error(transparent)]
    File(#[from] FileError),
}

/// Write `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RunError> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(FileError::io_at(parent))?;
    }
    let tmp = path.with_extension(format!("tmp-{}", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(FileError::io_at(&tmp))?;
    Ok(std::fs::rename(&tmp, path).map_err(FileError::io_at(path))?)
}

/// How to open a run folder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OpenMode {
    /// It must not exist yet.
    New,
    /// It must hold a run; carry on from it.
    Resume,
    /// Delete whatever is there and start again.
    Force,
}

/// A run folder.
#[derive(Clone, Debug)]
pub struct RunDir {
    root: PathBuf,
    /// Writes that failed (a checkpoint on a full disk, say): how many, and the last error.
    failures: std::sync::Arc<std::sync::Mutex<(u64, String)>>,
}

impl RunDir {
    /// Open or create a run folder.
    pub fn open(root: &Path, mode: OpenMode) -> Result<RunDir, RunError> {
        let exists = root.exists() && std::fs::read_dir(root).map(|mut d| d.next().is_some()).unwrap_or(false);
        match mode {
            OpenMode::New if exists => return Err(RunError::Exists(root.display().to_string())),
            OpenMode::Resume if !root.join("model").join("manifest.json").exists() => {
                return Err(RunError::NothingToResume(root.display().to_string()));
            }
            OpenMode::Force if exists => std::fs::remove_dir_all(root).map_err(FileError::io_at(root))?,
            _ => {}
        }
        std::fs::create_dir_all(root.join("checkpoints")).map_err(FileError::io_at(root))?;
        Ok(RunDir { root: root.to_path_buf(), failures: Default::default() })
    }

    /// Note a write that failed (and what stayed in its place); it is reported in the run's
    /// status until the run ends.
    pub fn note_failure(&self, what: String) {
        tracing::error!("{what}");
        let mut f = self.failures.lock().unwrap_or_else(|p| p.into_inner());
        f.0 += 1;
        f.1 = what;
    }

    /// Writes that failed so far, and the last one's error.
    pub fn failures(&self) -> (u64, String) {
        self.failures.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The run folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The model folder (the best model).
    pub fn model_dir(&self) -> PathBuf {
        self.root.join("model")
    }

    /// A checkpoint's folder.
    pub fn checkpoint_dir(&self, name: &str) -> PathBuf {
        self.root.join("checkpoints").join(name)
    }

    /// The checkpoint name for an iteration.
    pub fn checkpoint_name(iteration: u64) -> String {
        format!("ckpt_{iteration:06}")
    }

    fn index_path(&self) -> PathBuf {
        self.root.join("checkpoints").join("deepracer_checkpoints.json")
    }

    /// Read `deepracer_checkpoints.json` (empty if none yet).
    pub fn index(&self) -> Result<CheckpointIndex, RunError> {
        let p = self.index_path();
        if !p.exists() {
            return Ok(CheckpointIndex::default());
        }
        let text = std::fs::read_to_string(&p).map_err(FileError::io_at(&p))?;
        serde_json::from_str(&text)
            .map_err(|e| RunError::File(FileError::invalid(p.display().to_string(), e.to_string())))
    }

    /// Record a checkpoint that has been written: updates best/last, prunes old ones.
    /// Returns whether it is the new best.
    pub fn record(&self, rec: CheckpointRecord) -> Result<bool, RunError> {
        let mut index = self.index()?;
        // A checkpoint whose folder could not be written (a full disk) is neither best nor
        // last: the index names only folders that load.
        if !self.checkpoint_dir(&rec.name).join("manifest.json").exists() {
            return Ok(false);
        }
        let best = index.best_checkpoint.as_ref().is_none_or(|b| rec.better_than(b));
        if best {
            index.best_checkpoint = Some(rec.clone());
        }
        // An evaluation that comes back late never moves "last" behind a newer checkpoint.
        if index.last_checkpoint.as_ref().is_none_or(|l| l.iteration <= rec.iteration) {
            index.last_checkpoint = Some(rec);
        }
        self.write_index(&index)?;
        Ok(best)
    }

    /// Make a written checkpoint the best whatever its figures (the one that held its
    /// verification: the run's model), and record its figures.
    pub fn record_best(&self, rec: CheckpointRecord) -> Result<(), RunError> {
        let mut index = self.index()?;
        if !self.checkpoint_dir(&rec.name).join("manifest.json").exists() {
            return Err(RunError::File(FileError::invalid(
                self.checkpoint_dir(&rec.name).display().to_string(),
                "the verified checkpoint's folder is missing",
            )));
        }
        index.best_checkpoint = Some(rec);
        self.write_index(&index)
    }

    /// Write the index, then remove the checkpoints it no longer keeps.
    fn write_index(&self, index: &CheckpointIndex) -> Result<(), RunError> {
        write_atomic(&self.index_path(), serde_json::to_string_pretty(index).expect("JSON").as_bytes())?;
        self.prune(index)
    }

    fn prune(&self, index: &CheckpointIndex) -> Result<(), RunError> {
        let dir = self.root.join("checkpoints");
        let mut names: Vec<String> = std::fs::read_dir(&dir)
            .map_err(FileError::io_at(&dir))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("ckpt_"))
            .collect();
        names.sort();
        let best = index.best_checkpoint.as_ref().map(|b| b.name.clone());
        let last = index.last_checkpoint.as_ref().map(|b| b.name.clone());
        let keep_from = names.len().saturating_sub(KEEP_LAST);
        for (i, n) in names.iter().enumerate() {
            if i < keep_from && Some(n) != best.as_ref() && Some(n) != last.as_ref() {
                let p = dir.join(n);
                std::fs::remove_dir_all(&p).map_err(FileError::io_at(&p))?;
            }
        }
        Ok(())
    }

    /// Mark a checkpoint that has been written but not yet evaluated as the last one (what
    /// a restarted learner resumes from); its figures come with [`RunDir::record`].
    pub fn record_last(&self, rec: CheckpointRecord) -> Result<(), RunError> {
        let mut index = self.index()?;
        index.last_checkpoint = Some(rec);
        write_atomic(&self.index_path(), serde_json::to_string_pretty(&index).expect("JSON").as_bytes())
    }

    /// Append one line to `metrics.jsonl` (one per update).
    pub fn append_metrics(&self, line: &serde_json::Value) -> Result<(), RunError> {
        self.append_line("metrics.jsonl", line)
    }

    /// Append one line to `evaluations.jsonl` (one per evaluation over every world).
    pub fn append_evaluation(&self, line: &serde_json::Value) -> Result<(), RunError> {
        self.append_line("evaluations.jsonl", line)
    }

    fn append_line(&self, name: &str, line: &serde_json::Value) -> Result<(), RunError> {
        use std::io::Write;
        let p = self.root.join(name);
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(&p).map_err(FileError::io_at(&p))?;
        Ok(writeln!(f, "{line}").map_err(FileError::io_at(&p))?)
    }

    /// On resuming from the checkpoint of `iteration`: keep in `metrics.jsonl` and
    /// `evaluations.jsonl` only what that checkpoint had seen (iterations up to it, whole
    /// lines), so that the updates made again after a crash are not recorded twice. Rewritten
    /// atomically; returns the lines dropped.
    pub fn rewind_records(&self, iteration: u64) -> Result<usize, RunError> {
        let mut dropped = 0;
        for name in ["metrics.jsonl", "evaluations.jsonl"] {
            let p = self.root.join(name);
            let Ok(text) = std::fs::read_to_string(&p) else { continue };
            let mut kept = String::with_capacity(text.len());
            for line in text.split_inclusive('\n') {
                let whole = line.ends_with('\n');
                let it =
                    serde_json::from_str::<serde_json::Value>(line.trim()).ok().and_then(|v| v["iteration"].as_u64());
                match it {
                    Some(i) if whole && i <= iteration => kept.push_str(line),
                    _ => dropped += 1,
                }
            }
            if kept.len() != text.len() {
                write_atomic(&p, kept.as_bytes())?;
            }
        }
        Ok(dropped)
    }

    /// The last line of `metrics.jsonl` (where a resumed run takes its totals from).
    pub fn last_metrics(&self) -> Option<serde_json::Value> {
        let text = std::fs::read_to_string(self.root.join("metrics.jsonl")).ok()?;
        text.lines().rev().find_map(|l| serde_json::from_str(l).ok())
    }

    /// Write a file at the run folder's top (atomically).
    pub fn write_file(&self, name: &str, bytes: &[u8]) -> Result<(), RunError> {
        write_atomic(&self.root.join(name), bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(i: u64, progress: f64, lap: Option<f64>) -> CheckpointRecord {
        CheckpointRecord {
            name: RunDir::checkpoint_name(i),
            iteration: i,
            policy_version: i,
            avg_eval_metric: progress,
            avg_lap_time: lap,
            time_stamp: i as f64,
        }
    }

    /// Issue 10: a resumed run records each update once.
    #[test]
    fn a_resumed_run_records_each_update_once() {
        let dir = std::env::temp_dir().join(format!("paddock-rewind-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let run = RunDir::open(&dir, OpenMode::New).unwrap();
        for i in 1..=5u64 {
            run.append_metrics(&serde_json::json!({"iteration": i})).unwrap();
        }
        run.append_evaluation(&serde_json::json!({"iteration": 2})).unwrap();
        run.append_evaluation(&serde_json::json!({"iteration": 4})).unwrap();
        // A crash in the middle of a line.
        std::fs::OpenOptions::new()
            .append(true)
            .open(dir.join("metrics.jsonl"))
            .and_then(|mut f| std::io::Write::write_all(&mut f, b"{\"iteration\": 6, \"po"))
            .unwrap();
        assert_eq!(run.rewind_records(3).unwrap(), 4);
        let m = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
        assert_eq!(m, "{\"iteration\":1}\n{\"iteration\":2}\n{\"iteration\":3}\n");
        let e = std::fs::read_to_string(dir.join("evaluations.jsonl")).unwrap();
        assert_eq!(e, "{\"iteration\":2}\n");
        assert_eq!(run.rewind_records(3).unwrap(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn best_is_progress_then_lap_time_and_old_checkpoints_are_pruned() {
        let dir = std::env::temp_dir().join(format!("paddock-ckpt-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let run = RunDir::open(&dir, OpenMode::New).unwrap();
        let table = [
            (1, 40.0, None, true),
            (2, 100.0, Some(12.0), true),
            (3, 100.0, Some(13.0), false),
            (4, 100.0, Some(11.5), true),
            (5, 90.0, None, false),
        ];
        let make = |i: u64| {
            let d = run.checkpoint_dir(&RunDir::checkpoint_name(i));
            std::fs::create_dir_all(&d).unwrap();
            std::fs::write(d.join("manifest.json"), "{}").unwrap();
        };
        // Never written (a full disk): recorded as evaluated, but neither best nor last.
        assert!(!run.record(rec(0, 100.0, Some(1.0))).unwrap());
        for (i, p, lap, best) in table {
            make(i);
            assert_eq!(run.record(rec(i, p, lap)).unwrap(), best, "iteration {i}");
        }
        for i in 6..=9 {
            make(i);
            run.record(rec(i, 10.0, None)).unwrap();
        }
        let index = run.index().unwrap();
        assert_eq!(index.best_checkpoint.unwrap().iteration, 4);
        assert_eq!(index.last_checkpoint.unwrap().iteration, 9);
        let mut left: Vec<String> = std::fs::read_dir(dir.join("checkpoints"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("ckpt_"))
            .collect();
        left.sort();
        assert_eq!(left, ["ckpt_000004", "ckpt_000006", "ckpt_000007", "ckpt_000008", "ckpt_000009"]);
        assert!(matches!(RunDir::open(&dir, OpenMode::New), Err(RunError::Exists(_))));
        assert!(matches!(RunDir::open(&dir, OpenMode::Resume), Err(RunError::NothingToResume(_))));
        RunDir::open(&dir, OpenMode::Force).unwrap();
        assert!(!dir.join("checkpoints").join("ckpt_000004").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
