//! Jobs as the coordinator keeps them: their state, each agent's share, the event log, and
//! the embedded database (redb) that holds them across restarts.

use anyhow::{Context, Result};
use protocol::job::JobDoc;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::{SystemTime, UNIX_EPOCH};

const JOBS: TableDefinition<&str, &str> = TableDefinition::new("jobs");

/// Seconds since the Unix epoch.
pub fn now_unix() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

/// A job's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Agents and the learner work on it.
    Running,
    /// A stop condition or the user asked it to stop; waiting for the learner's final checkpoint.
    Stopping,
    /// Done: final checkpoint and best model written.
    Finished,
    /// Could not run (a reward that raises, say).
    Failed,
}

/// One agent's share of a job.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgentWork {
    /// The worlds it drives (all at once).
    pub worlds: Vec<String>,
    /// Which of them its environment 0 drives.
    pub offset: u32,
    /// Increases with every change.
    pub generation: u64,
}

/// What the database keeps per job.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobRecord {
    /// The job with its files.
    pub doc: JobDoc,
    /// Its state.
    pub state: JobState,
    /// Unix time it was started.
    pub started: f64,
    /// Unix time it ended.
    pub ended: Option<f64>,
    /// Why it stopped.
    pub stop_reason: Option<String>,
    /// Agent → what it drives.
    pub assignments: BTreeMap<String, AgentWork>,
    /// Next assignment generation.
    pub generation: u64,
    /// Event log.
    pub log: Vec<String>,
    /// The learner's last status, as JSON.
    pub learner: Option<serde_json::Value>,
}

impl JobRecord {
    /// A job starting now: running, nothing assigned yet.
    pub fn new(doc: JobDoc) -> JobRecord {
        JobRecord {
            doc,
            state: JobState::Running,
            started: now_unix(),
            ended: None,
            stop_reason: None,
            assignments: BTreeMap::new(),
            generation: 0,
            log: vec![],
            learner: None,
        }
    }

    /// Log an event (and trace it).
    pub fn event(&mut self, line: String) {
        tracing::info!(job = %self.doc.id, "{line}");
        let t = now_unix() - self.started;
        self.log.push(format!("[{t:>8.1}s] {line}"));
        if self.log.len() > 2000 {
            self.log.drain(..500);
        }
    }
}

/// The database: jobs by id, as JSON.
pub struct Db {
    db: Database,
}

impl Db {
    /// Open (or create) the database file.
    pub fn open(path: &Path) -> Result<Db> {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)?;
        }
        let db = Database::create(path).with_context(|| format!("opening the job database {}", path.display()))?;
        let w = db.begin_write()?;
        w.open_table(JOBS)?;
        w.commit()?;
        Ok(Db { db })
    }

    /// Every job stored; unreadable ones are skipped with a warning.
    pub fn load(&self) -> Result<BTreeMap<String, JobRecord>> {
        let r = self.db.begin_read()?;
        let t = r.open_table(JOBS)?;
        let mut out = BTreeMap::new();
        for e in t.iter()? {
            let (k, v) = e?;
            match serde_json::from_str::<JobRecord>(v.value()) {
                Ok(rec) => {
                    out.insert(k.value().to_string(), rec);
                }
                Err(e) => tracing::warn!("job {} in the database is unreadable, skipped: {e}", k.value()),
            }
        }
        Ok(out)
    }

    /// Save, and say so loudly when the database refuses: the job's state in memory stays
    /// right, and the next change tries again.
    pub fn save_or_log(&self, rec: &JobRecord) {
        if let Err(e) = self.save(rec) {
            tracing::error!(job = %rec.doc.id, "could not store the job in the database: {e:#}");
        }
    }

    /// Store a job.
    pub fn save(&self, rec: &JobRecord) -> Result<()> {
        let w = self.db.begin_write()?;
        {
            let mut t = w.open_table(JOBS)?;
            t.insert(rec.doc.id.as_str(), serde_json::to_string(rec)?.as_str())?;
        }
        w.commit()?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jobs_survive_reopening_the_database() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/jobs.redb");
        let doc: JobDoc = serde_json::from_value(serde_json::json!({
            "id": "job1", "worlds": ["reinvent_wood"], "reward_name": "builtin:center_line",
            "reward_source": "builtin:center_line", "model_metadata_json": "{}", "hyperparameters_json": "{}",
            "sim_config_toml": "", "out": "run", "clone_from": null, "seed": 1, "envs_per_agent": 8,
            "max_policy_lag": 2, "stop": {}, "eval_trials": 3, "obs_size": 27, "observation_json": "{}"
        }))
        .unwrap();
        let mut rec = JobRecord::new(doc);
        rec.assignments =
            [("a1".to_string(), AgentWork { worlds: vec!["reinvent_wood".into()], offset: 0, generation: 3 })].into();
        rec.generation = 4;
        rec.event("started".into());
        {
            let db = Db::open(&path).unwrap();
            db.save(&rec).unwrap();
            rec.state = JobState::Finished;
            db.save(&rec).unwrap();
        }
        let back = Db::open(&path).unwrap().load().unwrap();
        assert_eq!(back.len(), 1);
        let got = &back["job1"];
        assert_eq!(got.state, JobState::Finished, "the last save wins");
        assert_eq!(got.assignments, rec.assignments);
        assert_eq!(serde_json::to_value(got).unwrap(), serde_json::to_value(&rec).unwrap());
    }
}
