//! Jobs as the coordinator keeps them ([`JobRecord`]: the job, its state, each agent's
//! share, the event log, the learner's last status) and the embedded database (redb) that
//! holds them across restarts, each record protobuf-encoded under its job's id.

use anyhow::{Context, Result};
use prost::Message;
pub use protocol::job::{AgentWork, JobRecord, JobState, now_unix};
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition, TableHandle};
use std::collections::BTreeMap;
use std::path::Path;

const RECORDS: TableDefinition<&str, &[u8]> = TableDefinition::new("job_records");
/// Where an earlier Paddock kept its jobs (as JSON): left as it is, and said so.
const OLD_JSON: &str = "jobs";

/// The database: job records by id.
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
        w.open_table(RECORDS)?;
        w.commit()?;
        let r = db.begin_read()?;
        if let Some(old) = r.list_tables()?.find(|t| t.name() == OLD_JSON) {
            tracing::warn!(
                "the job database {} also holds the table '{}' of an earlier Paddock (jobs as JSON): \
                 those jobs are left in the file untouched and are not listed",
                path.display(),
                old.name()
            );
        }
        Ok(Db { db })
    }

    /// The database itself (other tables beside the jobs': the join tokens').
    pub fn database(&self) -> &Database {
        &self.db
    }

    /// Every job stored; unreadable ones are skipped with a warning.
    pub fn load(&self) -> Result<BTreeMap<String, JobRecord>> {
        let r = self.db.begin_read()?;
        let t = r.open_table(RECORDS)?;
        let mut out = BTreeMap::new();
        for e in t.iter()? {
            let (k, v) = e?;
            match protocol::job::decode_record(v.value()) {
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
            tracing::error!(job = %rec.id(), "could not store the job in the database: {e:#}");
        }
    }

    /// Store a job.
    pub fn save(&self, rec: &JobRecord) -> Result<()> {
        let w = self.db.begin_write()?;
        {
            let mut t = w.open_table(RECORDS)?;
            t.insert(rec.id(), rec.encode_to_vec().as_slice())?;
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
        let job = protocol::Job {
            protocol_version: protocol::PROTOCOL_VERSION,
            id: "job1".into(),
            worlds: vec!["reinvent_wood".into()],
            reward_name: "builtin:center_line".into(),
            reward_source: "builtin:center_line".into(),
            seed: 1,
            envs_per_agent: 8,
            stop: Some(protocol::job::default_stop()),
            obs_size: 27,
            ..Default::default()
        };
        let mut rec = JobRecord::start(job);
        rec.assignments =
            [("a1".to_string(), AgentWork { worlds: vec!["reinvent_wood".into()], offset: 0, generation: 3 })].into();
        rec.generation = 4;
        rec.event("started".into());
        {
            let db = Db::open(&path).unwrap();
            db.save(&rec).unwrap();
            rec.set_state(JobState::Finished);
            db.save(&rec).unwrap();
        }
        let back = Db::open(&path).unwrap().load().unwrap();
        assert_eq!(back.len(), 1);
        assert_eq!(back["job1"].state(), JobState::Finished, "the last save wins");
        assert_eq!(back["job1"], rec);
    }

    /// Issue 29: an earlier JSON table is left alone and unreadable records are skipped.
    #[test]
    fn an_earlier_json_table_is_left_alone_and_unreadable_records_are_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("jobs.redb");
        {
            let db = Database::create(&path).unwrap();
            let w = db.begin_write().unwrap();
            w.open_table(TableDefinition::<&str, &str>::new(OLD_JSON)).unwrap().insert("old", "{}").unwrap();
            w.open_table(RECORDS).unwrap().insert("junk", &b"\xff\x01"[..]).unwrap();
            w.commit().unwrap();
        }
        let db = Db::open(&path).unwrap();
        assert!(db.load().unwrap().is_empty());
        drop(db);
        let db = Database::create(&path).unwrap();
        let r = db.begin_read().unwrap();
        let old = r.open_table(TableDefinition::<&str, &str>::new(OLD_JSON)).unwrap();
        assert_eq!(old.get("old").unwrap().unwrap().value(), "{}", "the earlier table is untouched");
    }
}
