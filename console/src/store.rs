//! The console's data folder: one folder a model, kept across restarts.
//!
//! ```text
//! DATA/
//!   coordinator.redb          the job database (`console` on one machine)
//!   logs/                     the roles' logs (`console` on one machine)
//!   models/NAME/
//!     model.json              the console's record (name, description, created, job id)
//!     job.toml                the job spec, as `coordinator job start` takes it
//!     reward_function.py      DeepRacer's files, as the user gave them
//!     model_metadata.json
//!     hyperparameters.json
//!     run/                    the learner's run folder (checkpoints, model/, metrics, logs)
//! ```
//!
//! A model's name is DeepRacer's (letters, digits and hyphens, at most 64), so it is a plain
//! folder name: no request reaches outside the data folder. A model is written in a hidden
//! folder and renamed into place whole: nothing is half-made.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// What the console keeps of a model beside DeepRacer's files (`model.json`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ModelRecord {
    /// DeepRacer's model name.
    pub name: String,
    /// Its description (may be empty).
    #[serde(default)]
    pub description: String,
    /// Unix seconds.
    pub created: f64,
    /// The coordinator's job that trains it.
    pub job_id: String,
    /// The worlds it trains on.
    pub tracks: Vec<String>,
    /// Driven the other way round (DeepRacer's `is_reversed`).
    #[serde(default)]
    pub reversed: bool,
    /// The most sim agents it trains on (none: every agent there is).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agents: Option<u32>,
    /// `clipped_ppo` or `sac`.
    pub algorithm: String,
    /// DeepRacer's sensor names.
    pub sensors: Vec<String>,
    /// `builtin:NAME` or `reward_function.py`.
    pub reward: String,
    /// The stop, as the job spec's `[stop]`.
    pub stop: toml::Table,
    /// The model it was cloned from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clone_of: Option<String>,
    /// The user who made it (none: made on the console's token, or before it had users).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub owner: Option<String>,
}

/// Why a store operation failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// No model of that name.
    #[error("no model named '{0}'")]
    NotFound(String),
    /// The name is taken.
    #[error("a model named '{0}' already exists")]
    Taken(String),
    /// A file of the data folder could not be read or written.
    #[error("{path}: {msg}")]
    Io {
        /// The file.
        path: String,
        /// What went wrong.
        msg: String,
    },
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> StoreError + '_ {
    move |e| StoreError::Io { path: path.display().to_string(), msg: e.to_string() }
}

/// Names the console's own addresses take (`/models/new`, `/api/v1/models/import`, …).
pub const RESERVED: [&str; 3] = ["new", "import", "rows"];

/// DeepRacer's model name rule: `^[A-Za-z0-9-]+$`, at most 64 characters.
pub fn name_problem(name: &str) -> Option<String> {
    if name.is_empty() {
        Some("a model name is required".into())
    } else if name.chars().count() > 64 {
        Some(format!("at most 64 characters, not {}", name.chars().count()))
    } else if !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
        Some("letters, digits and hyphens only (DeepRacer's rule: ^[A-Za-z0-9-]+$)".into())
    } else if RESERVED.contains(&name) {
        Some(format!("'{name}' names a page of the console; choose another"))
    } else {
        None
    }
}

/// DeepRacer's description rule: letters, digits, hyphens and spaces, at most 255.
pub fn description_problem(text: &str) -> Option<String> {
    if text.chars().count() > 255 {
        Some(format!("at most 255 characters, not {}", text.chars().count()))
    } else if !text.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == ' ') {
        Some("letters, digits, hyphens and spaces only (DeepRacer's rule: ^[A-Za-z0-9- ]+$)".into())
    } else {
        None
    }
}

/// A model's files, before they are stored.
pub struct NewFiles {
    /// The record.
    pub record: ModelRecord,
    /// `reward_function.py` (none for a built-in).
    pub reward_source: Option<String>,
    /// `model_metadata.json`.
    pub model_metadata: String,
    /// `hyperparameters.json`.
    pub hyperparameters: String,
}

/// The data folder.
#[derive(Clone, Debug)]
pub struct Store {
    root: PathBuf,
}

impl Store {
    /// Open (or make) the data folder.
    pub fn open(root: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(root.join("models")).map_err(io(root))?;
        let root = root.canonicalize().map_err(io(root))?;
        Ok(Store { root })
    }

    /// The data folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// A model's folder (the name must have passed [`name_problem`]).
    pub fn dir(&self, name: &str) -> Result<PathBuf, StoreError> {
        if name_problem(name).is_some() {
            return Err(StoreError::NotFound(name.to_string()));
        }
        Ok(self.root.join("models").join(name))
    }

    /// Every model, newest first; folders without a readable record are left out (and logged).
    pub fn list(&self) -> Vec<ModelRecord> {
        let mut out = Vec::new();
        let Ok(entries) = std::fs::read_dir(self.root.join("models")) else { return out };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            match self.get(&name) {
                Ok(r) => out.push(r),
                Err(e) => tracing::warn!("the data folder's model '{name}' is left out: {e}"),
            }
        }
        out.sort_by(|a, b| b.created.total_cmp(&a.created).then_with(|| a.name.cmp(&b.name)));
        out
    }

    /// One model's record.
    pub fn get(&self, name: &str) -> Result<ModelRecord, StoreError> {
        let path = self.dir(name)?.join("model.json");
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(StoreError::NotFound(name.to_string())),
            Err(e) => return Err(io(&path)(e)),
        };
        serde_json::from_str(&text).map_err(|e| StoreError::Io { path: path.display().to_string(), msg: e.to_string() })
    }

    /// A model's folder, made whole: its files written in a hidden folder, the job spec made by
    /// `spec` from that folder (an error removes everything), then renamed into place.
    pub fn create<T, E: From<StoreError>>(
        &self,
        files: &NewFiles,
        spec: impl FnOnce(&Path) -> Result<T, E>,
    ) -> Result<T, E> {
        let name = &files.record.name;
        let dir = self.dir(name)?;
        if dir.exists() {
            return Err(StoreError::Taken(name.clone()).into());
        }
        let tmp = self.root.join("models").join(format!(".new-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        let made = (|| -> Result<T, E> {
            std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
            let write = |file: &str, text: &str| -> Result<(), StoreError> {
                let p = tmp.join(file);
                std::fs::write(&p, text).map_err(io(&p))
            };
            if let Some(src) = &files.reward_source {
                write("reward_function.py", src)?;
            }
            write("model_metadata.json", &files.model_metadata)?;
            write("hyperparameters.json", &files.hyperparameters)?;
            let record = serde_json::to_string_pretty(&files.record).expect("a record serialises");
            write("model.json", &record)?;
            let made = spec(&tmp)?;
            if dir.exists() {
                return Err(StoreError::Taken(name.clone()).into());
            }
            std::fs::rename(&tmp, &dir).map_err(io(&dir))?;
            Ok(made)
        })();
        if made.is_err() {
            let _ = std::fs::remove_dir_all(&tmp);
        }
        made
    }

    /// Remove a model's folder.
    pub fn delete(&self, name: &str) -> Result<(), StoreError> {
        let dir = self.dir(name)?;
        if !dir.join("model.json").exists() {
            return Err(StoreError::NotFound(name.to_string()));
        }
        // Renamed first, so a half-removed folder is never listed.
        let gone = self.root.join("models").join(format!(".deleted-{name}-{}", std::process::id()));
        std::fs::rename(&dir, &gone).map_err(io(&dir))?;
        std::fs::remove_dir_all(&gone).map_err(io(&gone))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_descriptions_follow_deepracers_rules() {
        for (name, ok) in [
            ("TopModel-reInventTrack", true),
            ("a", true),
            ("", false),
            ("has space", false),
            ("../etc", false),
            ("<img src=x onerror=alert(1)>", false),
            ("import", false),
            ("new", false),
            (&"x".repeat(64), true),
            (&"x".repeat(65), false),
        ] {
            assert_eq!(name_problem(name).is_none(), ok, "{name}");
        }
        for (text, ok) in [("", true), ("My first model - v2", true), ("no, punctuation", false)] {
            assert_eq!(description_problem(text).is_none(), ok, "{text}");
        }
        assert!(description_problem(&"x".repeat(256)).is_some());
    }

    fn files(name: &str) -> NewFiles {
        NewFiles {
            record: ModelRecord {
                name: name.into(),
                description: String::new(),
                created: 1.0,
                job_id: format!("{name}-1"),
                tracks: vec!["reinvent_base".into()],
                reversed: false,
                agents: None,
                owner: None,
                algorithm: "clipped_ppo".into(),
                sensors: vec!["FRONT_FACING_CAMERA".into()],
                reward: "builtin:center_line".into(),
                stop: toml::Table::new(),
                clone_of: None,
            },
            reward_source: None,
            model_metadata: "{}".into(),
            hyperparameters: "{}".into(),
        }
    }

    #[test]
    fn a_model_is_stored_whole_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let failed: Result<(), StoreError> =
            store.create(&files("m1"), |_| Err(StoreError::Io { path: "job.toml".into(), msg: "bad".into() }));
        assert!(failed.is_err());
        assert!(store.list().is_empty(), "nothing half-made is listed");
        assert_eq!(std::fs::read_dir(dir.path().join("models")).unwrap().count(), 0, "no leftovers");
        let had_record = store.create::<bool, StoreError>(&files("m1"), |d| Ok(d.join("model.json").exists())).unwrap();
        assert!(had_record, "the record is written before the spec is made");
        let again = store.create::<(), StoreError>(&files("m1"), |_| Ok(()));
        assert!(matches!(again, Err(StoreError::Taken(_))));
        let back = Store::open(dir.path()).unwrap();
        assert_eq!(back.list(), vec![files("m1").record], "a new console finds it");
        assert!(matches!(back.get("../m1"), Err(StoreError::NotFound(_))));
        back.delete("m1").unwrap();
        assert!(back.list().is_empty());
        assert!(matches!(back.delete("m1"), Err(StoreError::NotFound(_))));
    }
}
