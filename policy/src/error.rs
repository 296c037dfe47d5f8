//! The error every reader and writer of a file shares: the file could not be read or
//! written, or its contents are not what was expected. Both name the file (or what stands
//! for it: an archive's name, a `--set key=value` override), so a message says where to look.
//!
//! The model folder ([`crate::folder`]), key files ([`crate::signature`]), DeepRacer's
//! archive ([`crate::carpkg`]) and the simulator's configuration (sim-agent) use it directly
//! or wrap it.

use std::path::Path;

/// A file that could not be read or written, or whose contents are wrong.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The file could not be read or written.
    // `error` is shown in the message, so it is not also the source: `{:#}` would print it twice.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// What the system said.
        error: std::io::Error,
    },
    /// The file was read but its contents are wrong.
    #[error("{path}: {msg}")]
    Invalid {
        /// The file, or what the text came from (an archive, a `--set` override).
        path: String,
        /// What is wrong, naming the field, entry or line and what was expected.
        msg: String,
    },
}

impl FileError {
    /// Reading or writing `path` failed with `error`.
    pub fn io(path: &Path, error: std::io::Error) -> FileError {
        FileError::Io { path: path.display().to_string(), error }
    }

    /// [`FileError::io`] for `map_err`: `std::fs::read(p).map_err(FileError::io_at(p))`.
    pub fn io_at(path: &Path) -> impl FnOnce(std::io::Error) -> FileError + '_ {
        move |error| FileError::io(path, error)
    }

    /// `origin`'s contents are wrong: `msg` names the field, entry or line and what was
    /// expected.
    pub fn invalid(origin: impl Into<String>, msg: impl Into<String>) -> FileError {
        FileError::Invalid { path: origin.into(), msg: msg.into() }
    }

    /// The file (or origin) the error names.
    pub fn path(&self) -> &str {
        match self {
            FileError::Io { path, .. } | FileError::Invalid { path, .. } => path,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 50: each kind of file error names its file and says what is wrong.
    #[test]
    fn each_file_error_names_its_file_and_what_is_wrong() {
        let missing = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file or directory");
        for (e, want) in [
            (FileError::io(Path::new("run/model.safetensors"), missing), "run/model.safetensors: No such file"),
            (
                FileError::invalid("model_metadata.json", "field 'sensor' is 3, expected a list"),
                "model_metadata.json: field 'sensor' is 3, expected a list",
            ),
            (FileError::invalid("--set race.x=1", "'race' is not a section"), "--set race.x=1: 'race' is not"),
        ] {
            let shown = e.to_string();
            assert!(shown.starts_with(want), "{shown}");
            assert!(shown.starts_with(e.path()), "{shown}");
            // No source besides the message: `{:#}` shows it once.
            assert!(std::error::Error::source(&e).is_none(), "{shown}");
        }
    }
}
