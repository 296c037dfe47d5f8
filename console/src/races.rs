//! Community races, as DeepRacer on AWS runs them: a facilitator opens a race (a window, a
//! track and its direction, a race type with its objects or bots, a ranking method, lap counts,
//! penalties, submissions per racer); racers enter their models while it is open; each entry
//! is evaluated as it arrives (several at once, on the console's own cores) and ranked.
//!
//! Ranking follows DRoA's rules (`ModelPerformanceMetricsHelper.ts`): an entry drives
//! `max_laps` laps, each from the start line, an off-track or a crash putting the car back
//! with its penalty added to the lap; the laps completed count as the longest run of
//! consecutive completed laps, and an entry is ranked only when that reaches `min_laps`. Its
//! score, lower is better, is by the race's method: the total of every lap's time, the best
//! mean over any `min_laps` consecutive completed laps (rounded down to the millisecond), or
//! the fastest completed lap. One row per racer, replaced only by a strictly better score.
//!
//! On disk, under the data folder's `races/NAME/`: `race.json`, and per entry
//! `entries/ID.json` (written whole) with `entries/ID-model/`, the model as it was entered.

use crate::models::FieldError;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use sim_agent::race::RaceConfig;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// How a race ranks its entries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ranking {
    /// The sum of every lap's time (all `max_laps` must be completed).
    TotalTime,
    /// The best mean over `min_laps` consecutive completed laps.
    AverageLap,
    /// The fastest completed lap (at least `min_laps` consecutive completed laps to qualify).
    BestLap,
}

impl Ranking {
    /// The name in the API.
    pub fn name(self) -> &'static str {
        match self {
            Ranking::TotalTime => "total_time",
            Ranking::AverageLap => "average_lap",
            Ranking::BestLap => "best_lap",
        }
    }

    /// The name as the pages show it.
    pub fn title(self) -> &'static str {
        match self {
            Ranking::TotalTime => "Total time",
            Ranking::AverageLap => "Average lap time",
            Ranking::BestLap => "Best lap time",
        }
    }

    fn parse(s: &str) -> Option<Ranking> {
        [Ranking::TotalTime, Ranking::AverageLap, Ranking::BestLap].into_iter().find(|r| r.name() == s)
    }
}

/// A race.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Race {
    /// Its name (DeepRacer's rule for names); also its address.
    pub name: String,
    /// What it is about.
    pub description: String,
    /// `community` (entries evaluated and ranked at any time in the window) or `live` (a
    /// facilitator's queue, each entry shown in turn; `closes` is the event's time).
    pub mode: String,
    /// The track.
    pub track: String,
    /// Driven against the track's own direction.
    pub reversed: bool,
    /// The race type with its objects or bots (the simulator's race table).
    pub race: RaceConfig,
    /// How entries are ranked.
    pub ranking: Ranking,
    /// Consecutive completed laps to be ranked (the averaging window for `average_lap`).
    pub min_laps: u32,
    /// Laps each entry drives.
    pub max_laps: u32,
    /// Seconds added per off-track.
    pub off_track_penalty: f64,
    /// Seconds added per crash.
    pub crash_penalty: f64,
    /// Entries a racer may make.
    pub max_submissions: u32,
    /// When it opens (Unix seconds).
    pub opens: f64,
    /// When it closes (Unix seconds).
    pub closes: f64,
    /// When it was made.
    pub created: f64,
    /// Who made it (none: the console's token).
    pub creator: Option<String>,
    /// Live races: the times a facilitator may reset an entry.
    #[serde(default = "default_resets")]
    pub max_resets: u32,
}

fn default_resets() -> u32 {
    3
}

impl Race {
    /// A live race.
    pub fn live(&self) -> bool {
        self.mode == "live"
    }

    /// `upcoming`, `open` or `closed` at `now` (a live race: `open` until its event time,
    /// then `closed`; its own state is in [`LiveState`]).
    pub fn status(&self, now: f64) -> &'static str {
        if now < self.opens {
            "upcoming"
        } else if now < self.closes {
            "open"
        } else {
            "closed"
        }
    }

    /// As the API shows it, with its status at `now`.
    pub fn to_json(&self, now: f64) -> Value {
        let mut v = serde_json::to_value(self).expect("a race is JSON");
        v["status"] = json!(self.status(now));
        v["race_type"] = v["race"]["race_type"].clone();
        v
    }
}

/// The fields a race takes.
pub const FIELDS: [&str; 15] = [
    "name",
    "description",
    "mode",
    "track",
    "reversed",
    "race",
    "ranking",
    "min_laps",
    "max_laps",
    "off_track_penalty",
    "crash_penalty",
    "max_submissions",
    "opens",
    "closes",
    "max_resets",
];

fn problem(field: &str, message: impl Into<String>) -> FieldError {
    FieldError { field: field.into(), message: message.into(), line: None }
}

/// Check a race as `POST /api/v1/races` gives it (or an edit: `base`'s fields where `body` has
/// none), at `now`. Every invalid field is named.
pub fn check(body: &Value, base: Option<&Race>, now: f64, creator: Option<&str>) -> Result<Race, Vec<FieldError>> {
    let mut errors = Vec::new();
    let Value::Object(map) = body else { return Err(vec![problem("", "expected a JSON object: a race")]) };
    for key in map.keys().filter(|k| !FIELDS.contains(&k.as_str())) {
        errors.push(problem(key, format!("unknown field; expected one of {}", FIELDS.join(", "))));
    }
    let given = |k: &str| map.get(k).filter(|v| !v.is_null());
    let text = |k: &str, errors: &mut Vec<FieldError>| -> Option<String> {
        match given(k) {
            None => None,
            Some(Value::String(s)) => Some(s.clone()),
            Some(_) => {
                errors.push(problem(k, "expected a string"));
                None
            }
        }
    };
    let name = match (text("name", &mut errors), base) {
        (Some(n), Some(b)) if n != b.name => {
            errors.push(problem("name", "a race's name stays as it was made"));
            n
        }
        (Some(n), _) => {
            if let Some(p) = crate::store::name_problem(&n) {
                errors.push(problem("name", p.replace("a model name", "a race name")));
            }
            n
        }
        (None, Some(b)) => b.name.clone(),
        (None, None) => {
            errors.push(problem("name", "required: the race's name"));
            String::new()
        }
    };
    let description = text("description", &mut errors).or(base.map(|b| b.description.clone())).unwrap_or_default();
    if let Some(p) = crate::store::description_problem(&description) {
        errors.push(problem("description", p));
    }
    let mode = text("mode", &mut errors).or(base.map(|b| b.mode.clone())).unwrap_or_else(|| "community".into());
    if mode != "community" && mode != "live" {
        errors.push(problem("mode", format!("'{mode}': expected community or live")));
    } else if base.is_some_and(|b| b.mode != mode) {
        errors.push(problem("mode", "a race's mode stays as it was made"));
    }
    let track = match text("track", &mut errors).or(base.map(|b| b.track.clone())) {
        Some(t) => match tracks::world(&t) {
            Ok(w) => w.name,
            Err(e) => {
                errors.push(problem("track", e.to_string()));
                t
            }
        },
        None => {
            errors.push(problem("track", "required: a track's name (GET /api/v1/tracks)"));
            String::new()
        }
    };
    let reversed = match given("reversed") {
        None => base.is_some_and(|b| b.reversed),
        Some(Value::Bool(b)) => *b,
        Some(_) => {
            errors.push(problem("reversed", "expected true or false"));
            false
        }
    };
    let race = match given("race") {
        None => base.map(|b| b.race.clone()).unwrap_or_default(),
        Some(v) => crate::evaluations::race_table(v).unwrap_or_else(|e| {
            errors.push(problem("race", e));
            RaceConfig::default()
        }),
    };
    let ranking = match text("ranking", &mut errors) {
        None => base.map(|b| b.ranking).unwrap_or(Ranking::TotalTime),
        Some(s) => Ranking::parse(&s).unwrap_or_else(|| {
            errors.push(problem("ranking", format!("'{s}': expected total_time, average_lap or best_lap")));
            Ranking::TotalTime
        }),
    };
    let number = |k: &str, default: f64, lo: f64, hi: f64, whole: bool, errors: &mut Vec<FieldError>| -> f64 {
        match given(k) {
            None => default,
            Some(v) => match v.as_f64() {
                Some(x) if (lo..=hi).contains(&x) && (!whole || x.fract() == 0.0) => x,
                _ => {
                    let kind = if whole { "a whole number" } else { "a number" };
                    errors.push(problem(k, format!("expected {kind} from {lo} to {hi}, not {v}")));
                    default
                }
            },
        }
    };
    let max_laps = number("max_laps", base.map_or(5.0, |b| f64::from(b.max_laps)), 1.0, 20.0, true, &mut errors) as u32;
    let min_default = match (base, ranking) {
        (Some(b), _) if given("max_laps").is_none() && given("ranking").is_none() => b.min_laps,
        (_, Ranking::TotalTime) => max_laps,
        (_, Ranking::AverageLap) => max_laps.min(3),
        (_, Ranking::BestLap) => 1,
    };
    let min_laps = number("min_laps", f64::from(min_default), 1.0, 20.0, true, &mut errors) as u32;
    if min_laps > max_laps {
        errors.push(problem("min_laps", format!("{min_laps} is more than max_laps ({max_laps})")));
    } else if ranking == Ranking::TotalTime && min_laps != max_laps {
        errors.push(problem(
            "min_laps",
            format!(
                "ranked by total time, every lap counts: min_laps must equal max_laps ({max_laps}), not {min_laps}"
            ),
        ));
    }
    let off_track_penalty =
        number("off_track_penalty", base.map_or(1.0, |b| b.off_track_penalty), 0.0, 60.0, false, &mut errors);
    let crash_penalty = number("crash_penalty", base.map_or(2.0, |b| b.crash_penalty), 0.0, 60.0, false, &mut errors);
    let max_submissions = number(
        "max_submissions",
        base.map_or(99.0, |b| f64::from(b.max_submissions)),
        1.0,
        10_000.0,
        true,
        &mut errors,
    ) as u32;
    let max_resets =
        number("max_resets", base.map_or(3.0, |b| f64::from(b.max_resets)), 0.0, 10.0, true, &mut errors) as u32;
    let opens = number("opens", base.map_or(now, |b| b.opens), 0.0, 1e11, false, &mut errors);
    if mode == "live" && given("opens").is_some() {
        errors.push(problem("opens", "a live race opens when it is made; closes is its event's time"));
    }
    let closes = match (given("closes"), base) {
        (None, Some(b)) => b.closes,
        (None, None) => {
            errors.push(problem("closes", "required: when the race closes (Unix seconds)"));
            now
        }
        (Some(_), _) => number("closes", now, 0.0, 1e11, false, &mut errors),
    };
    if given("closes").is_some() || given("opens").is_some() {
        if closes <= opens {
            errors.push(problem("closes", "the race must close after it opens"));
        } else if closes <= now {
            errors.push(problem("closes", "the race must close in the future"));
        }
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    Ok(Race {
        name,
        description,
        mode,
        track,
        reversed,
        race,
        ranking,
        min_laps,
        max_laps,
        off_track_penalty,
        crash_penalty,
        max_submissions,
        opens,
        closes,
        created: base.map_or(now, |b| b.created),
        creator: base.map_or(creator.map(String::from), |b| b.creator.clone()),
        max_resets,
    })
}

/// One lap of an entry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lap {
    /// Its time, penalties included (ms); a lap not completed: the time it ran.
    pub time_ms: u64,
    /// Completed (100 %).
    pub completed: bool,
    /// Progress reached (%).
    pub progress: f64,
    /// Times the car left the track.
    pub off_tracks: u32,
    /// Times the car crashed.
    pub crashes: u32,
}

/// What an entry's laps add up to.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// The longest run of consecutive completed laps.
    pub completed_laps: u32,
    /// Every lap's time (ms).
    pub total_ms: u64,
    /// Every lap's off-tracks.
    pub off_tracks: u32,
    /// Every lap's crashes.
    pub crashes: u32,
    /// The fastest completed lap (ms) and its off-tracks.
    pub best: Option<(u64, u32)>,
    /// The best mean over `window` consecutive completed laps (ms, rounded down) and that
    /// window's off-tracks.
    pub average: Option<(u64, u32)>,
}

/// The stats of `laps`, averaging over `window` consecutive laps.
pub fn stats(laps: &[Lap], window: usize) -> Stats {
    let mut s = Stats {
        total_ms: laps.iter().map(|l| l.time_ms).sum(),
        off_tracks: laps.iter().map(|l| l.off_tracks).sum(),
        crashes: laps.iter().map(|l| l.crashes).sum(),
        ..Stats::default()
    };
    let mut run = 0;
    for l in laps {
        run = if l.completed { run + 1 } else { 0 };
        s.completed_laps = s.completed_laps.max(run);
    }
    // The first of equally fast laps.
    s.best = laps.iter().filter(|l| l.completed).fold(None, |best: Option<(u64, u32)>, l| match best {
        Some((t, _)) if t <= l.time_ms => best,
        _ => Some((l.time_ms, l.off_tracks)),
    });
    if window >= 1 {
        for w in laps.windows(window).filter(|w| w.iter().all(|l| l.completed)) {
            let mean = w.iter().map(|l| l.time_ms).sum::<u64>() / window as u64;
            if s.average.is_none_or(|(best, _)| mean < best) {
                s.average = Some((mean, w.iter().map(|l| l.off_tracks).sum()));
            }
        }
    }
    s
}

/// An entry's score under `race` (ms, lower is better) with the off-tracks that go with it;
/// none when it does not qualify (fewer than `min_laps` consecutive completed laps).
pub fn score(race: &Race, s: &Stats) -> Option<(u64, u32)> {
    if s.completed_laps < race.min_laps {
        return None;
    }
    match race.ranking {
        Ranking::TotalTime => Some((s.total_ms, s.off_tracks)),
        Ranking::AverageLap => s.average,
        Ranking::BestLap => s.best,
    }
}

/// Where an entry stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EntryStatus {
    /// Waiting for a free evaluator.
    Queued,
    /// Being evaluated.
    Running,
    /// Evaluated.
    Done,
    /// Its evaluation failed (`error` says why).
    Failed,
}

/// A submission to a race.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// Its id (`entry-MILLIS`).
    pub id: String,
    /// The racer: the user who owns the model (without users, the model's name).
    pub racer: String,
    /// The model entered.
    pub model: String,
    /// The model's policy version when entered.
    pub policy_version: Option<u64>,
    /// When it was entered.
    pub created: f64,
    /// When its evaluation began (the latest, after a reset).
    #[serde(default)]
    pub started: Option<f64>,
    /// When its evaluation ended.
    pub finished: Option<f64>,
    /// Seconds of evaluation before the latest (a reset entry's earlier runs).
    #[serde(default)]
    pub spent_s: f64,
    /// Where it stands.
    pub status: EntryStatus,
    /// Why it failed.
    pub error: Option<String>,
    /// Its laps, in order.
    pub laps: Vec<Lap>,
    /// The fastest completed lap (or the farthest lap): `[x, y, speed]` a step.
    pub path: Vec<[f64; 3]>,
    /// Live races: when the facilitator launched it.
    #[serde(default)]
    pub launched: Option<f64>,
    /// Live races: the times it was reset.
    #[serde(default)]
    pub resets: u32,
    /// Live races: its replay's length (the simulator's seconds).
    #[serde(default)]
    pub replay_s: Option<f64>,
}

impl Entry {
    /// As the API shows it: its stats and score under `race`, without its path.
    pub fn to_json(&self, race: &Race) -> Value {
        let mut v = serde_json::to_value(self).expect("an entry is JSON");
        if let Some(o) = v.as_object_mut() {
            o.remove("path");
        }
        if self.status == EntryStatus::Done {
            let s = stats(&self.laps, race.min_laps as usize);
            let sc = score(race, &s);
            v["completed_laps"] = json!(s.completed_laps);
            v["ranked"] = json!(sc.is_some());
            v["time_ms"] = json!(sc.map(|x| x.0));
            v["best_lap_ms"] = json!(s.best.map(|x| x.0));
            v["total_ms"] = json!(s.total_ms);
        }
        v
    }
}

/// One line of a leaderboard.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// 1 for the fastest.
    pub rank: usize,
    /// The racer.
    pub racer: String,
    /// The model of their best entry.
    pub model: String,
    /// That entry.
    pub entry: String,
    /// Its score (ms).
    pub time_ms: u64,
    /// Behind the first (ms).
    pub gap_ms: u64,
    /// Its off-tracks, as the ranking method counts them.
    pub off_tracks: u32,
}

/// The leaderboard: each racer's best ranked entry (an earlier entry keeps its row against an
/// equal score), fastest first.
pub fn leaderboard(race: &Race, entries: &[Entry]) -> Vec<Row> {
    let mut done: Vec<&Entry> = entries.iter().filter(|e| e.status == EntryStatus::Done).collect();
    done.sort_by(|a, b| a.created.total_cmp(&b.created).then_with(|| a.id.cmp(&b.id)));
    let mut best: std::collections::BTreeMap<&str, (u64, u32, &Entry)> = Default::default();
    for e in done {
        let Some((t, off)) = score(race, &stats(&e.laps, race.min_laps as usize)) else { continue };
        match best.get(e.racer.as_str()) {
            Some((held, _, _)) if *held <= t => {}
            _ => {
                best.insert(&e.racer, (t, off, e));
            }
        }
    }
    let mut rows: Vec<(u64, u32, &Entry)> = best.into_values().collect();
    rows.sort_by(|a, b| a.0.cmp(&b.0).then_with(|| a.2.created.total_cmp(&b.2.created)));
    let first = rows.first().map_or(0, |r| r.0);
    rows.iter()
        .enumerate()
        .map(|(i, (t, off, e))| Row {
            rank: i + 1,
            racer: e.racer.clone(),
            model: e.model.clone(),
            entry: e.id.clone(),
            time_ms: *t,
            gap_ms: t - first,
            off_tracks: *off,
        })
        .collect()
}

/// `MM:SS.mmm`, as DeepRacer's leaderboards write times.
pub fn clock(ms: u64) -> String {
    format!("{:02}:{:02}.{:03}", ms / 60_000, ms / 1000 % 60, ms % 1000)
}

/// Why a race's storage failed.
#[derive(Debug, thiserror::Error)]
pub enum RaceError {
    /// No such race.
    #[error("no race named '{0}'")]
    NotFound(String),
    /// The name is taken.
    #[error("a race named '{0}' already exists")]
    Taken(String),
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> RaceError + '_ {
    move |source| RaceError::Io { path: path.to_path_buf(), source }
}

pub(crate) fn write_whole(path: &Path, bytes: &[u8]) -> Result<(), RaceError> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(io(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io(path))
}

fn copy_dir(from: &Path, to: &Path) -> Result<(), RaceError> {
    std::fs::create_dir_all(to).map_err(io(to))?;
    for e in std::fs::read_dir(from).map_err(io(from))? {
        let e = e.map_err(io(from))?;
        let (src, dst) = (e.path(), to.join(e.file_name()));
        if e.file_type().map_err(io(&src))?.is_dir() {
            copy_dir(&src, &dst)?;
        } else {
            std::fs::copy(&src, &dst).map_err(io(&src))?;
        }
    }
    Ok(())
}

/// The races in a data folder. Entering is serialised (a racer's count of entries is checked
/// and the entry written under one lock).
#[derive(Clone)]
pub struct Races {
    root: PathBuf,
    pub(crate) lock: Arc<Mutex<()>>,
}

impl Races {
    /// The races of the data folder `data`.
    pub fn open(data: &Path) -> Races {
        Races { root: data.join("races"), lock: Arc::default() }
    }

    fn dir(&self, name: &str) -> Result<PathBuf, RaceError> {
        if crate::store::name_problem(name).is_some() {
            return Err(RaceError::NotFound(name.to_string()));
        }
        Ok(self.root.join(name))
    }

    /// A file of a race's folder.
    pub(crate) fn race_file(&self, race: &str, file: &str) -> Result<PathBuf, RaceError> {
        Ok(self.dir(race)?.join(file))
    }

    fn entry_file(&self, race: &str, id: &str, suffix: &str) -> Result<PathBuf, RaceError> {
        if crate::store::name_problem(id).is_some() {
            return Err(RaceError::NotFound(format!("{race}/{id}")));
        }
        Ok(self.dir(race)?.join("entries").join(format!("{id}{suffix}")))
    }

    /// A live race entry's replay.
    pub fn replay(&self, race: &str, id: &str) -> Option<crate::live::Replay> {
        let text = std::fs::read_to_string(self.entry_file(race, id, ".replay").ok()?).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// A live race entry's camera frames file.
    pub fn frames_file(&self, race: &str, id: &str) -> Result<PathBuf, RaceError> {
        self.entry_file(race, id, "-frames.bin")
    }

    /// Remove an entry with its model and replay.
    pub(crate) fn remove_entry(&self, race: &str, id: &str) -> Result<(), RaceError> {
        for suffix in [".json", ".replay", "-frames.bin"] {
            let f = self.entry_file(race, id, suffix)?;
            if f.exists() {
                std::fs::remove_file(&f).map_err(io(&f))?;
            }
        }
        let model = self.entry_file(race, id, "-model")?;
        if model.exists() {
            std::fs::remove_dir_all(&model).map_err(io(&model))?;
        }
        Ok(())
    }

    /// A race.
    pub fn get(&self, name: &str) -> Result<Race, RaceError> {
        let path = self.dir(name)?.join("race.json");
        let text = std::fs::read_to_string(&path).map_err(|_| RaceError::NotFound(name.to_string()))?;
        serde_json::from_str(&text).map_err(|e| RaceError::Io { path, source: std::io::Error::other(e) })
    }

    /// Every race, the latest to close first.
    pub fn list(&self) -> Vec<Race> {
        let mut out: Vec<Race> = std::fs::read_dir(&self.root)
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                self.get(&name).map_err(|err| tracing::warn!("the race '{name}' is left out: {err}")).ok()
            })
            .collect();
        out.sort_by(|a, b| b.closes.total_cmp(&a.closes).then_with(|| a.name.cmp(&b.name)));
        out
    }

    /// Keep a new race (`Taken` if its name is).
    pub fn create(&self, race: &Race) -> Result<(), RaceError> {
        let _held = self.lock.lock().expect("races");
        let dir = self.dir(&race.name)?;
        if dir.exists() {
            return Err(RaceError::Taken(race.name.clone()));
        }
        std::fs::create_dir_all(dir.join("entries")).map_err(io(&dir))?;
        self.save(race)
    }

    /// Write a race's record (whole).
    pub fn save(&self, race: &Race) -> Result<(), RaceError> {
        let dir = self.dir(&race.name)?;
        write_whole(&dir.join("race.json"), serde_json::to_string_pretty(race).expect("JSON").as_bytes())
    }

    /// Remove a race and its entries.
    pub fn delete(&self, name: &str) -> Result<(), RaceError> {
        let dir = self.dir(name)?;
        if !dir.join("race.json").exists() {
            return Err(RaceError::NotFound(name.into()));
        }
        std::fs::remove_dir_all(&dir).map_err(io(&dir))
    }

    /// A race's entries, oldest first.
    pub fn entries(&self, race: &str) -> Vec<Entry> {
        let Ok(dir) = self.dir(race) else { return vec![] };
        let mut out: Vec<Entry> = std::fs::read_dir(dir.join("entries"))
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.path().extension().is_some_and(|x| x == "json"))
            .filter_map(|e| std::fs::read_to_string(e.path()).ok())
            .filter_map(|t| serde_json::from_str::<Entry>(&t).ok())
            .collect();
        out.sort_by(|a, b| a.created.total_cmp(&b.created).then_with(|| a.id.cmp(&b.id)));
        out
    }

    /// Keep what an evaluation found, on the entry as it is now on disk: a facilitator's launch,
    /// reset or removal while it ran stands (a removed entry's leftovers are removed).
    pub(crate) fn evaluated(&self, race: &str, e: &Entry) -> Result<(), RaceError> {
        let _held = self.lock.lock().expect("races");
        let Some(mut now) = self.entry(race, &e.id) else { return self.remove_entry(race, &e.id) };
        if now.resets != e.resets {
            // Reset while it ran: the run that counts is the one the reset started.
            return Ok(());
        }
        now.status = e.status;
        now.error = e.error.clone();
        now.laps = e.laps.clone();
        now.path = e.path.clone();
        now.policy_version = e.policy_version;
        now.started = e.started;
        now.finished = e.finished;
        now.replay_s = e.replay_s;
        self.save_entry(race, &now)
    }

    /// One entry.
    pub fn entry(&self, race: &str, id: &str) -> Option<Entry> {
        if crate::store::name_problem(id).is_some() {
            return None;
        }
        let text = std::fs::read_to_string(self.dir(race).ok()?.join("entries").join(format!("{id}.json"))).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Write an entry's record (whole).
    pub fn save_entry(&self, race: &str, e: &Entry) -> Result<(), RaceError> {
        let dir = self.dir(race)?.join("entries");
        write_whole(&dir.join(format!("{}.json", e.id)), serde_json::to_string(e).expect("JSON").as_bytes())
    }

    /// The folder holding an entry's model.
    pub fn entry_model(&self, race: &str, id: &str) -> Result<PathBuf, RaceError> {
        Ok(self.dir(race)?.join("entries").join(format!("{id}-model")))
    }

    /// Enter the model folder `model_dir` as `entry` in `race` (a live race: at the end of its
    /// queue), unless the racer has made `race.max_submissions` entries already, or (a live
    /// race) the model is entered already: `Err(Ok(why))`. The model is copied, so a model
    /// trained on afterwards races as it was entered.
    pub fn enter(&self, race: &Race, entry: &Entry, model_dir: &Path) -> Result<(), Result<String, RaceError>> {
        let _held = self.lock.lock().expect("races");
        let entries = self.entries(&race.name);
        let made = entries.iter().filter(|e| e.racer == entry.racer).count();
        if made >= race.max_submissions as usize {
            return Err(Ok(format!(
                "race '{}' takes at most {} entries a racer: {} has made them all",
                race.name, race.max_submissions, entry.racer
            )));
        }
        if race.live() && entries.iter().any(|e| e.model == entry.model) {
            return Err(Ok(format!("model '{}' is in the live race's queue already", entry.model)));
        }
        let to = self.entry_model(&race.name, &entry.id).map_err(Err)?;
        copy_dir(model_dir, &to).map_err(Err)?;
        self.save_entry(&race.name, entry).map_err(Err)?;
        if race.live() {
            let mut s = self.live(&race.name);
            s.queue.push(entry.id.clone());
            self.save_live(&race.name, &s).map_err(Err)?;
        }
        Ok(())
    }

    /// Minutes spent evaluating entries (their owners' quotas count them), by model, at `now`:
    /// each run from its start to its end (or `now`), a reset entry's earlier runs included.
    pub fn minutes_by_model(&self, now: f64) -> std::collections::HashMap<String, f64> {
        let mut out = std::collections::HashMap::new();
        for e in self.list().iter().flat_map(|r| self.entries(&r.name)) {
            let run = e.started.map_or(0.0, |s| (e.finished.unwrap_or(now) - s).max(0.0));
            *out.entry(e.model.clone()).or_insert(0.0) += (e.spent_s + run) / 60.0;
        }
        out
    }

    /// The entry `id` of whichever race has it (entries' ids are the console's, made once).
    pub fn find_entry(&self, id: &str) -> Option<Entry> {
        if !id.starts_with("entry-") {
            return None;
        }
        self.list().iter().find_map(|r| self.entry(&r.name, id))
    }

    /// Every entry still queued or running (to run again after a restart).
    pub fn unfinished(&self) -> Vec<(String, Entry)> {
        let mut out: Vec<(String, Entry)> = self
            .list()
            .iter()
            .flat_map(|r| {
                self.entries(&r.name)
                    .into_iter()
                    .filter(|e| matches!(e.status, EntryStatus::Queued | EntryStatus::Running))
                    .map(|e| (r.name.clone(), e))
            })
            .collect();
        out.sort_by(|a, b| a.1.created.total_cmp(&b.1.created));
        out
    }
}

/// Evaluate `entry` of `race` (blocking) and keep its laps; an evaluation that fails marks the
/// entry failed with the reason.
pub fn evaluate(races: &Races, race: &Race, mut entry: Entry) {
    entry.status = EntryStatus::Running;
    entry.started = Some(protocol::job::now_unix());
    entry.finished = None;
    if let Err(e) = races.evaluated(&race.name, &entry) {
        tracing::error!("{e}");
    }
    let control_hz = sim_agent::SimConfig::default().control_hz;
    let outcome = tracks::world(&race.track).map_err(anyhow::Error::from).and_then(|world| {
        let request = coordinator::evaluation::Request {
            worlds: vec![world],
            reversed: race.reversed,
            trials: race.max_laps as usize,
            seed: entry.created as u64 + u64::from(entry.resets),
            race: race.race.clone(),
            rules: sim_agent::EvalRules {
                max_resets: 100,
                penalty_s: race.off_track_penalty,
                collision_penalty_s: race.crash_penalty,
                time_limit_s: None,
            },
            record: true,
            all_frames: race.live(),
        };
        coordinator::evaluation::run(&races.entry_model(&race.name, &entry.id)?, &request)
    });
    match outcome {
        Ok(done) => {
            let trials = done.worlds.into_iter().next().map(|w| w.trials).unwrap_or_default();
            entry.policy_version = Some(done.policy_version);
            if race.live() {
                let kept = races.frames_file(&race.name, &entry.id).and_then(|frames| {
                    let replay = crate::live::Replay::keep(&trials, control_hz, &frames)
                        .map_err(|e| RaceError::Io { path: frames.clone(), source: e })?;
                    let path = races.entry_file(&race.name, &entry.id, ".replay")?;
                    write_whole(&path, serde_json::to_string(&replay).expect("JSON").as_bytes())?;
                    Ok(replay.duration_s())
                });
                match kept {
                    Ok(s) => entry.replay_s = Some(s),
                    Err(e) => tracing::error!("the entry's replay was not kept: {e}"),
                }
            }
            entry.laps = trials
                .iter()
                .map(|t| Lap {
                    time_ms: (t.lap_time.unwrap_or(t.steps as f64 / control_hz) * 1000.0).round() as u64,
                    completed: t.lap_time.is_some(),
                    progress: t.progress,
                    off_tracks: t.off_track,
                    crashes: t.crashes,
                })
                .collect();
            let key = |t: &sim_agent::rollout::TrialResult| (t.lap_time.unwrap_or(f64::INFINITY), -t.progress);
            if let Some(best) =
                trials.iter().min_by(|a, b| key(a).partial_cmp(&key(b)).unwrap_or(std::cmp::Ordering::Equal))
            {
                entry.path = best.log.trace.iter().map(|s| [s.x, s.y, f64::from(s.throttle)]).collect();
            }
            entry.status = EntryStatus::Done;
        }
        Err(e) => {
            entry.status = EntryStatus::Failed;
            entry.error = Some(format!("{e:#}"));
        }
    }
    entry.finished = Some(protocol::job::now_unix());
    if let Err(e) = races.evaluated(&race.name, &entry) {
        tracing::error!("{e}");
    }
    // The copy of the model is kept: the leaderboard's models can be driven again.
}

#[cfg(test)]
mod tests {
    use super::*;

    fn race(ranking: Ranking, min_laps: u32, max_laps: u32) -> Race {
        let now = 1_800_000_000.0;
        let body = json!({"name": "cup", "track": "reinvent_base", "ranking": ranking.name(),
                          "min_laps": min_laps, "max_laps": max_laps, "closes": now + 3600.0});
        check(&body, None, now, Some("fay")).unwrap()
    }

    /// A lap: seconds (a completed lap) or `-seconds` (one that was not), and its off-tracks.
    fn laps(spec: &[(f64, u32)]) -> Vec<Lap> {
        spec.iter()
            .map(|&(s, off)| Lap {
                time_ms: (s.abs() * 1000.0).round() as u64,
                completed: s > 0.0,
                progress: if s > 0.0 { 100.0 } else { 40.0 },
                off_tracks: off,
                crashes: 0,
            })
            .collect()
    }

    /// Issue 52: laps ranked by each method against DRoA's rules worked by hand.
    ///
    /// Total time sums every lap and needs all `max_laps` completed; average lap takes the best
    /// mean over `min_laps` consecutive completed laps, rounded down to the millisecond; best
    /// lap takes the fastest completed lap once `min_laps` consecutive laps are completed. The
    /// off-tracks are those of what was timed.
    #[test]
    fn laps_are_ranked_by_each_method_as_deepracer_ranks_them() {
        use Ranking::*;
        // (ranking, min, max, laps, score ms and off-tracks; None: not ranked)
        type Case<'a> = (Ranking, u32, u32, &'a [(f64, u32)], Option<(u64, u32)>);
        let table: [Case; 12] = [
            // 10.5 + 11.25 + 9.75 = 31.5 s; 0 + 2 + 1 off-tracks.
            (TotalTime, 3, 3, &[(10.5, 0), (11.25, 2), (9.75, 1)], Some((31_500, 3))),
            // One lap not completed: total time needs every lap.
            (TotalTime, 3, 3, &[(10.5, 0), (-4.0, 5), (9.75, 1)], None),
            (TotalTime, 1, 1, &[(12.0, 1)], Some((12_000, 1))),
            // Windows of 2: (10+12)/2 = 11, (12+9)/2 = 10.5, lap 4 breaks it, (8.001+8.002)/2 =
            // 8.0015 → 8001 ms (rounded down); its off-tracks 0 + 3.
            (AverageLap, 2, 6, &[(10.0, 1), (12.0, 0), (9.0, 0), (-3.0, 4), (8.001, 0), (8.002, 3)], Some((8_001, 3))),
            // Windows of 3: only laps 1–3 are consecutive and completed: 31/3 = 10.333… → 10333.
            (AverageLap, 3, 5, &[(10.0, 0), (12.0, 1), (9.0, 0), (-3.0, 0), (7.0, 0)], Some((10_333, 1))),
            // No run of 3 completed laps: not ranked, however fast lap 5 was.
            (AverageLap, 3, 5, &[(10.0, 0), (12.0, 1), (-9.0, 0), (7.0, 0), (7.0, 0)], None),
            // Best lap: the fastest completed lap; the failed lap 2's short time does not count.
            (BestLap, 1, 3, &[(10.0, 0), (-2.0, 6), (9.5, 2)], Some((9_500, 2))),
            // Two equally fast laps: the first one's off-tracks.
            (BestLap, 1, 3, &[(9.0, 1), (9.0, 0), (11.0, 0)], Some((9_000, 1))),
            // Best lap with a gate of 2 consecutive laps: laps 1 and 3 do not make a run.
            (BestLap, 2, 3, &[(10.0, 0), (-2.0, 0), (9.0, 0)], None),
            (BestLap, 2, 4, &[(10.0, 0), (-2.0, 0), (9.0, 0), (9.2, 0)], Some((9_000, 0))),
            // Nothing completed.
            (BestLap, 1, 2, &[(-5.0, 3), (-6.0, 3)], None),
            (AverageLap, 1, 2, &[(-5.0, 3), (6.0, 0)], Some((6_000, 0))),
        ];
        for (ranking, min, max, spec, want) in table {
            let r = race(ranking, min, max);
            let got = score(&r, &stats(&laps(spec), min as usize));
            assert_eq!(got, want, "{ranking:?} min {min} max {max} laps {spec:?}");
        }
    }

    fn entry(id: &str, racer: &str, created: f64, spec: &[(f64, u32)]) -> Entry {
        Entry {
            id: id.into(),
            racer: racer.into(),
            model: format!("{racer}-{id}"),
            policy_version: Some(1),
            created,
            finished: Some(created + 1.0),
            status: EntryStatus::Done,
            error: None,
            laps: laps(spec),
            path: vec![],
            launched: None,
            resets: 0,
            replay_s: None,
            started: None,
            spent_s: 0.0,
        }
    }

    /// Issue 52: one row per racer, replaced only by a strictly better score; unranked entries
    /// and those not done have none; gaps are to the first.
    #[test]
    fn the_leaderboard_keeps_each_racers_best_entry_only() {
        let r = race(Ranking::BestLap, 1, 2);
        let mut pending = entry("e5", "zed", 5.0, &[(1.0, 0), (1.0, 0)]);
        pending.status = EntryStatus::Running;
        let entries = vec![
            entry("e1", "rita", 1.0, &[(10.0, 1), (11.0, 0)]),
            entry("e2", "rex", 2.0, &[(9.0, 0), (12.0, 0)]),
            // Rita's equal score later: her first entry keeps the row.
            entry("e3", "rita", 3.0, &[(10.0, 0), (10.5, 0)]),
            // Rex's worse score later: his row stays.
            entry("e4", "rex", 4.0, &[(9.5, 0), (9.6, 0)]),
            pending,
            entry("e6", "ann", 6.0, &[(-1.0, 9), (-1.0, 9)]),
            // Ann's later, ranked entry.
            entry("e7", "ann", 7.0, &[(12.25, 2), (13.0, 0)]),
        ];
        let rows: Vec<(usize, &str, &str, u64, u64, u32)> = leaderboard(&r, &entries)
            .iter()
            .map(|r| (r.rank, &*r.racer.clone().leak(), &*r.entry.clone().leak(), r.time_ms, r.gap_ms, r.off_tracks))
            .collect();
        assert_eq!(
            rows,
            vec![
                (1, "rex", "e2", 9_000, 0, 0),
                (2, "rita", "e1", 10_000, 1_000, 1),
                (3, "ann", "e7", 12_250, 3_250, 2)
            ]
        );
        // A strictly better one replaces it.
        let mut more = entries.clone();
        more.push(entry("e8", "rita", 8.0, &[(8.75, 0), (20.0, 0)]));
        let board = leaderboard(&r, &more);
        assert_eq!((board[0].racer.as_str(), board[0].entry.as_str(), board[1].gap_ms), ("rita", "e8", 250));
        assert_eq!(board.len(), 3);
        assert_eq!(clock(9_000), "00:09.000");
        assert_eq!(clock(83_456), "01:23.456");
    }

    /// Bad races are refused naming each field.
    #[test]
    fn a_bad_race_is_refused_naming_each_field() {
        let now = 1_800_000_000.0;
        for (body, field, says) in [
            (json!({"track": "reinvent_base", "closes": now + 60.0}), "name", "required"),
            (json!({"name": "a b", "track": "reinvent_base", "closes": now + 60.0}), "name", "hyphens"),
            (json!({"name": "c", "track": "nowhere", "closes": now + 60.0}), "track", "nowhere"),
            (json!({"name": "c", "track": "reinvent_base"}), "closes", "required"),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now - 60.0, "opens": now - 120.0}),
                "closes",
                "future",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "opens": now + 120.0}),
                "closes",
                "after it opens",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "ranking": "fastest"}),
                "ranking",
                "best_lap",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "min_laps": 2}),
                "min_laps",
                "equal max_laps",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "ranking": "best_lap", "min_laps": 6}),
                "min_laps",
                "more than max_laps",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "max_laps": 2.5}),
                "max_laps",
                "whole",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "mode": "drag"}),
                "mode",
                "community or live",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "race": {"race_type": "drag"}}),
                "race",
                "drag",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "colour": "red"}),
                "colour",
                "unknown",
            ),
            (
                json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "off_track_penalty": -1}),
                "off_track_penalty",
                "from 0",
            ),
        ] {
            let errors = check(&body, None, now, None).expect_err(&body.to_string());
            assert!(
                errors.iter().any(|e| e.field == field && e.message.contains(says)),
                "{body}: wanted {field} '{says}', got {errors:?}"
            );
        }
        // Each race type with its objects or bots, as the simulator's race table takes them.
        for (race, kind, count) in [
            (json!({"race_type": "object_avoidance", "number_of_obstacles": 3}), "object_avoidance", 3),
            (json!({"race_type": "head_to_bot", "number_of_bot_cars": 2, "bot_car_speed": 0.5}), "head_to_bot", 2),
        ] {
            let body = json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0, "race": race});
            let r = check(&body, None, now, None).unwrap();
            assert_eq!(r.to_json(now)["race_type"], kind);
            let n = if kind == "head_to_bot" { r.race.number_of_bot_cars } else { r.race.number_of_obstacles };
            assert_eq!(n, count);
        }
        // DRoA's defaults: total time over 5 laps, 1 s off-track, 99 submissions.
        let r = check(&json!({"name": "c", "track": "reinvent_base", "closes": now + 60.0}), None, now, None).unwrap();
        assert_eq!(
            (r.ranking, r.min_laps, r.max_laps, r.off_track_penalty, r.max_submissions),
            (Ranking::TotalTime, 5, 5, 1.0, 99)
        );
    }
}
