//! The built-in world catalog: DeepRacer's track files embedded in the binary, each paired
//! with a surface and lighting.
//!
//! The track files are byte-exact copies of DeepRacer simapp's `bundle/routes/*.npy`
//! (Apache-2.0; `tracks/data/SOURCE.md` and `tracks/data/NOTICE.md`).

use crate::TrackError;
use crate::geometry::{Direction, Track};
use crate::npy::{TrackRows, parse_track_npy};
use serde::{Deserialize, Serialize};

/// What the car drives on: sets the tyres' grip and the floor's look in the camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Surface {
    /// The printed track mat of the virtual tracks (default surface).
    Asphalt,
    /// Carpet tiles: the grippiest.
    Carpet,
    /// Sealed concrete floor.
    Concrete,
    /// Polished wood floor: the least grip.
    Wood,
}

impl Surface {
    /// Every surface, in display order.
    pub const ALL: [Surface; 4] = [Surface::Asphalt, Surface::Carpet, Surface::Concrete, Surface::Wood];

    /// Tyre–surface friction coefficient (peak, dimensionless). These are modelling choices
    /// for a 1/18 car on foam tyres, ordered as users report grip, not measurements.
    pub fn friction(self) -> f64 {
        match self {
            Surface::Asphalt => 0.9,
            Surface::Carpet => 1.0,
            Surface::Concrete => 0.75,
            Surface::Wood => 0.55,
        }
    }

    /// The lower-case name used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Surface::Asphalt => "asphalt",
            Surface::Carpet => "carpet",
            Surface::Concrete => "concrete",
            Surface::Wood => "wood",
        }
    }

    /// Parse a surface name.
    pub fn from_name(name: &str) -> Option<Surface> {
        Surface::ALL.into_iter().find(|s| s.name() == name)
    }
}

/// Scene lighting (used by the camera; recorded with every world now).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lighting {
    /// Light direction in the track plane, degrees from +x, counter-clockwise.
    pub azimuth_deg: f64,
    /// Light elevation above the floor, degrees.
    pub elevation_deg: f64,
    /// Relative intensity (1 = nominal).
    pub intensity: f64,
}

impl Default for Lighting {
    fn default() -> Self {
        Lighting { azimuth_deg: 45.0, elevation_deg: 60.0, intensity: 1.0 }
    }
}

/// A world: a track, the surface it lies on, and its lighting.
#[derive(Clone, Debug)]
pub struct World {
    /// Catalog name (DeepRacer's `WORLD_NAME`).
    pub name: String,
    /// The track file's rows.
    pub rows: TrackRows,
    /// What the car drives on.
    pub surface: Surface,
    /// Lighting for the camera.
    pub lighting: Lighting,
}

impl World {
    /// The track geometry for a driving direction.
    pub fn track(&self, direction: Direction) -> Track {
        Track::new(&self.name, &self.rows, direction)
    }
}

struct Entry {
    name: &'static str,
    bytes: &'static [u8],
    surface: Surface,
}

macro_rules! world {
    ($name:literal, $surface:ident) => {
        Entry { name: $name, bytes: include_bytes!(concat!("../data/", $name, ".npy")), surface: Surface::$surface }
    };
}

const CATALOG: &[Entry] = &[
    world!("reinvent_base", Asphalt),
    world!("reinvent_carpet", Carpet),
    world!("reinvent_concrete", Concrete),
    world!("reinvent_wood", Wood),
    world!("reInvent2019_track", Asphalt),
    world!("reInvent2019_track_ccw", Asphalt),
    world!("reInvent2019_track_cw", Asphalt),
    world!("reInvent2019_wide", Asphalt),
    world!("2022_reinvent_champ_ccw", Asphalt),
    world!("2022_reinvent_champ_cw", Asphalt),
    world!("AWS_track", Asphalt),
    world!("Bowtie_track", Asphalt),
    world!("China_track", Asphalt),
    world!("LGSWide", Asphalt),
    world!("Mexico_track", Asphalt),
    world!("Oval_track", Asphalt),
    world!("Straight_track", Asphalt),
    world!("Tokyo_Training_track", Asphalt),
    world!("Vegas_track", Asphalt),
];

/// Names of every built-in world, in catalog order.
pub fn world_names() -> impl Iterator<Item = &'static str> {
    CATALOG.iter().map(|e| e.name)
}

/// The prefix of a generated world's name: `generated:N` is the track
/// `coordinator tracks generate --seed N` makes at [`GENERATED_LENGTH`] and
/// [`GENERATED_WIDTH`] (asphalt), the same on every machine. Training on it draws a new track
/// every few episodes (the simulator's `generated.episodes_per_track`); evaluations keep to
/// track N.
pub const GENERATED: &str = "generated:";
/// A generated world's centre-line length, m (DeepRacer's tracks: 17–33 m).
pub const GENERATED_LENGTH: f64 = 22.0;
/// A generated world's width, m (DeepRacer's tracks: about 1.07).
pub const GENERATED_WIDTH: f64 = 1.07;

/// The seed of a generated world's name (`generated:N`), when it is one.
pub fn generated_seed(name: &str) -> Option<u64> {
    name.strip_prefix(GENERATED)?.parse().ok()
}

/// The generated track of `seed`, named `name`.
pub fn generated_world(name: &str, seed: u64) -> Result<World, TrackError> {
    let spec = crate::generate::GenSpec { seed, length: GENERATED_LENGTH, width: GENERATED_WIDTH };
    let rows = crate::generate::generate(&spec)
        .map_err(|e| TrackError::Generated { name: name.to_string(), msg: e.to_string() })?;
    Ok(World { name: name.to_string(), rows, surface: Surface::Asphalt, lighting: Lighting::default() })
}

/// Load a built-in world by name, or a generated one (`generated:N`).
pub fn world(name: &str) -> Result<World, TrackError> {
    if let Some(rest) = name.strip_prefix(GENERATED) {
        let seed = generated_seed(name).ok_or_else(|| TrackError::Generated {
            name: name.to_string(),
            msg: format!("'{rest}' is not a seed: expected generated:N with N a whole number"),
        })?;
        return generated_world(name, seed);
    }
    let entry = CATALOG.iter().find(|e| e.name == name).ok_or_else(|| TrackError::UnknownWorld {
        name: name.to_string(),
        known: world_names().collect::<Vec<_>>().join(", ") + ", generated:N (a generated track)",
    })?;
    let rows = parse_track_npy(entry.bytes, &format!("built-in {}.npy", entry.name))?;
    Ok(World { name: entry.name.to_string(), rows, surface: entry.surface, lighting: Lighting::default() })
}

/// Every built-in world.
pub fn worlds() -> Vec<World> {
    world_names().map(|n| world(n).expect("built-in tracks are validated by tests")).collect()
}
