//! Track geometry and the world catalog.
//!
//! - [`npy`]: read and validate DeepRacer `.npy` track files (`(N, 6)` float64).
//! - [`geometry`]: a [`Track`] for one driving direction and the queries behind DeepRacer's
//!   reward `params` (projection, progress, closest waypoints, width, road containment).
//! - [`catalog`]: the built-in worlds (track + surface + lighting), embedded in the binary.
//! - [`objects`]: obstacles on the lanes, footprints and the crash rule, as DeepRacer
//!   places and tests them.
//! - [`render`]: top-down PNG drawings.
//! - [`generate`]: random closed tracks of a given length and width, as `.npy` rows.
//! - [`raceline`]: the line of least curvature inside the borders, and the fastest speeds
//!   along a line for a car's limits.
//!
//! Architecture invariant: this crate knows nothing of physics, rewards, Python or the
//! network. It is pure geometry over `nalgebra` points.

pub mod catalog;
pub mod generate;
pub mod geometry;
mod grid;
pub mod npy;
pub mod objects;
pub mod raceline;
pub mod render;

pub use catalog::{Lighting, Surface, World, generated_seed, generated_world, world, world_names, worlds};
pub use geometry::{Direction, P2, Projection, Track, TrackQuery, compute_progress, wrap_degrees};
pub use npy::{TrackRows, parse_track_npy};

use std::path::Path;

/// Why a track could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    /// The file could not be read.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        error: std::io::Error,
    },
    /// The file was read but is not a usable track.
    #[error("{origin}: {msg}")]
    Invalid {
        /// The file (or built-in name).
        origin: String,
        /// What is wrong, naming the row or field.
        msg: String,
    },
    /// No built-in world has this name.
    #[error("no built-in world named '{name}'; known worlds: {known}")]
    UnknownWorld {
        /// The name asked for.
        name: String,
        /// The names that exist.
        known: String,
    },
    /// A generated world (`generated:N`) that cannot be made.
    #[error("world '{name}': {msg}")]
    Generated {
        /// The name asked for.
        name: String,
        /// Why.
        msg: String,
    },
}

/// Read and validate a user's `.npy` track file.
pub fn load_npy(path: &Path) -> Result<TrackRows, TrackError> {
    let bytes =
        std::fs::read(path).map_err(|source| TrackError::Io { path: path.display().to_string(), error: source })?;
    parse_track_npy(&bytes, &path.display().to_string())
}

/// The figures `coordinator tracks show/import` print for a track.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TrackSummary {
    /// Track name.
    pub name: String,
    /// Rows in the file.
    pub rows: usize,
    /// Waypoints reward functions see: the rows less the repeated ones.
    pub waypoints: usize,
    /// Centre-line length (m).
    pub length: f64,
    /// Narrowest width between border rows (m).
    pub min_width: f64,
    /// Mean width (m).
    pub mean_width: f64,
    /// Widest (m).
    pub max_width: f64,
    /// Loop or open.
    pub closed: bool,
    /// "ccw", "cw", or "open".
    pub direction: &'static str,
    /// Rows that repeat the previous row (dropped on load, as DeepRacer's simapp drops them).
    pub repeated_rows: Vec<usize>,
}

impl TrackSummary {
    /// Summarise a track (forward direction).
    pub fn of(name: &str, rows: &TrackRows) -> TrackSummary {
        let track = Track::new(name, rows, Direction::Forward);
        let (min_width, mean_width, max_width) = rows.width_stats();
        TrackSummary {
            name: name.to_string(),
            rows: rows.len(),
            waypoints: track.waypoints().len(),
            length: track.length(),
            min_width,
            mean_width,
            max_width,
            closed: track.is_closed(),
            direction: match (track.is_closed(), track.is_ccw()) {
                (false, _) => "open",
                (true, true) => "ccw",
                (true, false) => "cw",
            },
            repeated_rows: rows.repeated_rows(),
        }
    }
}
