//! Live races: a facilitator's queue of entries shown one at a time, as DeepRacer on AWS's
//! Live Racing runs them, but evaluated side by side as they arrive (on the console's race
//! slots) and each replayed in queue order when launched: every viewer sees the car go round
//! (its place on the track, its camera for camera models, each lap's time as it ends) in the
//! simulator's time, scaled by the console's `--live-speed`.
//!
//! The race goes `scheduled → in_progress → completed` (the facilitator declares the winner);
//! an entry is `pending` until launched, then `in_progress` (being evaluated, then replayed),
//! then `completed` or `failed`. Only completed entries, launched since the leaderboard was
//! last cleared, are ranked. The state is `races/NAME/live.json`, each entry's replay
//! `entries/ID.replay` (JSON) with its camera frames in `entries/ID-frames.bin`.

use crate::races::{Entry, EntryStatus, Race, RaceError, Races, Row};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::path::Path;

/// Where a live race stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Before the first launch.
    #[default]
    Scheduled,
    /// Entries are being shown.
    InProgress,
    /// The winner is declared; the leaderboard is locked.
    Completed,
}

/// A live race's state (`live.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LiveState {
    /// Where it stands.
    pub phase: Phase,
    /// Racers may enter.
    pub submissions_open: bool,
    /// The next pending entry is launched as soon as the current one ends.
    pub autolaunch: bool,
    /// The entries in the order they will be shown.
    pub queue: Vec<String>,
    /// Entries launched before this (Unix seconds) are off the leaderboard.
    pub cleared_at: f64,
    /// The winner's row, once declared.
    pub winner: Option<Row>,
}

impl Default for LiveState {
    fn default() -> Self {
        LiveState {
            phase: Phase::Scheduled,
            submissions_open: true,
            autolaunch: false,
            queue: vec![],
            cleared_at: 0.0,
            winner: None,
        }
    }
}

/// One lap of a replay.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReplayLap {
    /// Each step: `[x, y, yaw, progress]`.
    pub steps: Vec<[f32; 4]>,
    /// Its first camera frame in the frames file.
    pub first_frame: usize,
    /// Its camera frames (one every second step).
    pub frames: usize,
}

/// An entry's laps as they were driven, to be shown in the simulator's time.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Replay {
    /// Steps a second.
    pub hz: f64,
    /// The camera's frame size (0: no camera).
    pub width: u32,
    /// The camera's frame height.
    pub height: u32,
    /// The laps in order.
    pub laps: Vec<ReplayLap>,
}

/// Where the replay is at a moment.
#[derive(Clone, Debug, PartialEq)]
pub struct Moment {
    /// The lap (0-based).
    pub lap: usize,
    /// Seconds into that lap.
    pub lap_s: f64,
    /// `[x, y, yaw, progress]`.
    pub pose: [f32; 4],
    /// The camera frame to show, if any.
    pub frame: Option<usize>,
}

impl Replay {
    /// Its length in the simulator's seconds.
    pub fn duration_s(&self) -> f64 {
        self.laps.iter().map(|l| l.steps.len()).sum::<usize>() as f64 / self.hz.max(1e-9)
    }

    /// Where it is `t` seconds in (the last step once it has ended).
    pub fn at(&self, t: f64) -> Option<Moment> {
        let mut step = (t.max(0.0) * self.hz) as usize;
        for (i, lap) in self.laps.iter().enumerate() {
            let last = i + 1 == self.laps.len();
            if step < lap.steps.len() || (last && !lap.steps.is_empty()) {
                let s = step.min(lap.steps.len() - 1);
                let frame = (lap.frames > 0).then(|| lap.first_frame + (s / 2).min(lap.frames - 1));
                return Some(Moment { lap: i, lap_s: s as f64 / self.hz, pose: lap.steps[s], frame });
            }
            step -= lap.steps.len();
        }
        None
    }

    /// The replay of an evaluation's trials (one a lap), with their frames written to `frames`.
    pub fn keep(trials: &[sim_agent::rollout::TrialResult], hz: f64, frames: &Path) -> std::io::Result<Replay> {
        let mut out = Replay { hz, ..Replay::default() };
        let mut bytes = Vec::new();
        let mut count = 0;
        for t in trials {
            let steps = t.log.trace.iter().map(|s| [s.x as f32, s.y as f32, s.yaw, s.progress]).collect();
            let lap = ReplayLap { steps, first_frame: count, frames: t.log.frames.len() };
            for f in &t.log.frames {
                out.width = f.width;
                out.height = f.height;
                bytes.extend_from_slice(&f.gray);
            }
            count += t.log.frames.len();
            out.laps.push(lap);
        }
        if !bytes.is_empty() {
            std::fs::write(frames, bytes)?;
        }
        Ok(out)
    }

    /// Frame `i` of `frames` as a PNG.
    pub fn frame_png(&self, frames: &Path, i: usize) -> Option<Vec<u8>> {
        use std::io::{Read, Seek, SeekFrom};
        let size = (self.width * self.height) as usize;
        if size == 0 {
            return None;
        }
        let mut f = std::fs::File::open(frames).ok()?;
        f.seek(SeekFrom::Start((i * size) as u64)).ok()?;
        let mut gray = vec![0u8; size];
        f.read_exact(&mut gray).ok()?;
        let img = image::GrayImage::from_raw(self.width, self.height, gray)?;
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).ok()?;
        Some(png)
    }
}

/// Where an entry of a live race stands at `now`, its replay played at `speed`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shown {
    /// Not launched.
    Pending,
    /// Launched; being evaluated still.
    Evaluating,
    /// Launched and being shown since `start` (Unix seconds).
    Racing {
        /// When its replay began.
        start: f64,
    },
    /// Shown to its end.
    Completed,
    /// Its evaluation failed.
    Failed,
}

impl Shown {
    /// The queue's word for it.
    pub fn name(self) -> &'static str {
        match self {
            Shown::Pending => "pending",
            Shown::Evaluating | Shown::Racing { .. } => "in_progress",
            Shown::Completed => "completed",
            Shown::Failed => "failed",
        }
    }
}

/// Where `e` stands at `now` (`speed`: simulator seconds a second).
pub fn shown(e: &Entry, now: f64, speed: f64) -> Shown {
    let Some(launched) = e.launched else { return Shown::Pending };
    match e.status {
        EntryStatus::Failed => Shown::Failed,
        EntryStatus::Queued | EntryStatus::Running => Shown::Evaluating,
        EntryStatus::Done => {
            let start = launched.max(e.finished.unwrap_or(launched));
            let length = e.replay_s.unwrap_or(0.0) / speed.max(1e-9);
            if now < start + length { Shown::Racing { start } } else { Shown::Completed }
        }
    }
}

/// The entries a live race ranks at `now`: those shown to their end since the last clear.
pub fn ranked_entries(state: &LiveState, entries: &[Entry], now: f64, speed: f64) -> Vec<Entry> {
    entries
        .iter()
        .filter(|e| e.launched.is_some_and(|l| l >= state.cleared_at))
        .filter(|e| shown(e, now, speed) == Shown::Completed)
        .cloned()
        .collect()
}

/// A refusal of a facilitator's action: 409 with its reason.
#[derive(Debug)]
pub struct Refused(pub String);

/// The facilitator's actions.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    /// Show the next pending entry.
    Launch,
    /// Launch the next entry as each ends.
    Autolaunch(bool),
    /// Open or close submissions.
    Submissions(bool),
    /// Move an entry to a place in the queue (0 first).
    Move(String, usize),
    /// Take an entry out of the race.
    Remove(String),
    /// Run an entry again (a failed or shown one), up to the race's `max_resets`.
    Reset(String),
    /// Empty the leaderboard (entries shown so far stop counting).
    Clear,
    /// Declare the first of the leaderboard the winner and lock it.
    Winner,
}

impl Action {
    /// Read `{"action": …}` (`launch`, `autolaunch` with `on`, `submissions` with `open`,
    /// `move` with `entry` and `to`, `remove`/`reset` with `entry`, `clear`, `winner`).
    pub fn parse(v: &Value) -> Result<Action, String> {
        let entry = || v["entry"].as_str().map(String::from).ok_or_else(|| "expected entry: an entry's id".to_string());
        let flag = |k: &str| v[k].as_bool().ok_or_else(|| format!("expected {k}: true or false"));
        Ok(match v["action"].as_str() {
            Some("launch") => Action::Launch,
            Some("autolaunch") => Action::Autolaunch(flag("on")?),
            Some("submissions") => Action::Submissions(flag("open")?),
            Some("move") => Action::Move(
                entry()?,
                v["to"].as_u64().ok_or("expected to: the entry's new place in the queue (0 first)")? as usize,
            ),
            Some("remove") => Action::Remove(entry()?),
            Some("reset") => Action::Reset(entry()?),
            Some("clear") => Action::Clear,
            Some("winner") => Action::Winner,
            _ => {
                return Err(
                    "expected action: launch, autolaunch, submissions, move, remove, reset, clear or winner".into()
                );
            }
        })
    }
}

/// What an action asks the caller to do after it is applied.
#[derive(Debug, Default)]
pub struct After {
    /// Entries to evaluate (again).
    pub evaluate: Vec<Entry>,
}

impl Races {
    /// A live race's state (the default before anything happened).
    pub fn live(&self, race: &str) -> LiveState {
        self.race_file(race, "live.json")
            .ok()
            .and_then(|p| std::fs::read_to_string(p).ok())
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default()
    }

    pub(crate) fn save_live(&self, race: &str, state: &LiveState) -> Result<(), RaceError> {
        let path = self.race_file(race, "live.json")?;
        crate::races::write_whole(&path, serde_json::to_string_pretty(state).expect("JSON").as_bytes())
    }

    /// Apply a facilitator's action at `now` (`speed`: the replays').
    pub fn act(&self, race: &Race, action: &Action, now: f64, speed: f64) -> Result<Result<After, Refused>, RaceError> {
        let _held = self.lock.lock().expect("races");
        let mut s = self.live(&race.name);
        let entries = self.entries(&race.name);
        let find = |id: &str| entries.iter().find(|e| e.id == id);
        let racing = entries.iter().find(|e| matches!(shown(e, now, speed), Shown::Evaluating | Shown::Racing { .. }));
        let refuse = |why: String| Ok(Err(Refused(why)));
        let mut after = After::default();
        if s.phase == Phase::Completed && !matches!(action, Action::Submissions(_) | Action::Autolaunch(_)) {
            return refuse(format!("race '{}' is completed: its winner is declared", race.name));
        }
        match action {
            Action::Launch => {
                if let Some(e) = racing {
                    return refuse(format!("{} ({}) is racing: launch the next when it ends", e.racer, e.model));
                }
                if s.phase == Phase::Scheduled && now < race.closes {
                    return refuse("the event has not started: launch at its time".into());
                }
                if s.phase == Phase::Scheduled && s.submissions_open {
                    return refuse("close submissions before the first launch".into());
                }
                let next = s.queue.iter().filter_map(|id| find(id)).find(|e| e.launched.is_none());
                let Some(next) = next else { return refuse("no entry is waiting in the queue".into()) };
                let mut e = next.clone();
                e.launched = Some(now);
                self.save_entry(&race.name, &e)?;
                s.phase = Phase::InProgress;
                tracing::info!(race = %race.name, entry = %e.id, racer = %e.racer, "launched");
            }
            Action::Autolaunch(on) => s.autolaunch = *on,
            Action::Submissions(open) => s.submissions_open = *open,
            Action::Move(id, to) => {
                let Some(at) = s.queue.iter().position(|q| q == id) else {
                    return refuse(format!("'{id}' is not in the queue"));
                };
                let id = s.queue.remove(at);
                let to = (*to).min(s.queue.len());
                s.queue.insert(to, id);
            }
            Action::Remove(id) => {
                if racing.is_some_and(|e| &e.id == id) {
                    return refuse(format!("'{id}' is racing: reset it, or wait for it to end"));
                }
                if !s.queue.contains(id) {
                    return refuse(format!("'{id}' is not in the queue"));
                }
                s.queue.retain(|q| q != id);
                self.remove_entry(&race.name, id)?;
            }
            Action::Reset(id) => {
                let Some(e) = find(id) else { return refuse(format!("'{id}' is not in the queue")) };
                if e.launched.is_none() {
                    return refuse(format!("'{id}' has not been launched"));
                }
                if e.resets >= race.max_resets {
                    return refuse(format!("'{id}' has been reset {} times, the race's most", e.resets));
                }
                let mut e = e.clone();
                e.resets += 1;
                e.launched = None;
                // Run again, seeded anew (a run still going is superseded: what it finds is
                // not kept).
                if let (Some(s), Some(f)) = (e.started, e.finished) {
                    e.spent_s += (f - s).max(0.0);
                } else if let Some(s) = e.started {
                    e.spent_s += (now - s).max(0.0);
                }
                e.status = EntryStatus::Queued;
                e.error = None;
                e.laps.clear();
                e.path.clear();
                e.started = None;
                e.finished = None;
                e.replay_s = None;
                after.evaluate.push(e.clone());
                self.save_entry(&race.name, &e)?;
            }
            Action::Clear => {
                s.cleared_at = now;
            }
            Action::Winner => {
                if let Some(e) = racing {
                    return refuse(format!("{} ({}) is racing: declare the winner when it ends", e.racer, e.model));
                }
                let board = crate::races::leaderboard(race, &ranked_entries(&s, &entries, now, speed));
                let Some(first) = board.into_iter().next() else {
                    return refuse("no entry is ranked yet".into());
                };
                s.winner = Some(first);
                s.phase = Phase::Completed;
                s.autolaunch = false;
            }
        }
        self.save_live(&race.name, &s)?;
        Ok(Ok(after))
    }

    /// Launch the next pending entry of each live race with autolaunch on, when none is racing.
    pub fn autolaunch(&self, now: f64, speed: f64) {
        for race in self.list().into_iter().filter(Race::live) {
            let s = self.live(&race.name);
            if !s.autolaunch || s.phase != Phase::InProgress {
                continue;
            }
            let entries = self.entries(&race.name);
            let idle =
                !entries.iter().any(|e| matches!(shown(e, now, speed), Shown::Evaluating | Shown::Racing { .. }));
            let waiting = s.queue.iter().any(|id| entries.iter().any(|e| &e.id == id && e.launched.is_none()));
            if idle && waiting {
                match self.act(&race, &Action::Launch, now, speed) {
                    Ok(Ok(_)) => {}
                    Ok(Err(Refused(why))) => tracing::debug!(race = %race.name, "autolaunch waits: {why}"),
                    Err(e) => tracing::error!("{e}"),
                }
            }
        }
    }
}

/// A live race as every viewer sees it at `now`: its phase, the entry racing (where its car
/// is, its lap, its laps' times so far), the queue, the progress, the leaderboard, the winner.
pub fn snapshot(races: &Races, race: &Race, now: f64, speed: f64) -> Value {
    let s = races.live(&race.name);
    let entries = races.entries(&race.name);
    let by_id = |id: &str| entries.iter().find(|e| e.id == id);
    let queue: Vec<Value> = s
        .queue
        .iter()
        .filter_map(|id| by_id(id))
        .enumerate()
        .map(|(i, e)| {
            json!({"place": i + 1, "entry": e.id, "racer": e.racer, "model": e.model, "status": shown(e, now, speed).name(),
                   "resets": e.resets})
        })
        .collect();
    let mut current = Value::Null;
    for e in &entries {
        let st = shown(e, now, speed);
        let (start, evaluating) = match st {
            Shown::Evaluating => (now, true),
            Shown::Racing { start } => (start, false),
            _ => continue,
        };
        let place = s.queue.iter().position(|q| q == &e.id).map_or(0, |p| p + 1);
        current = json!({"entry": e.id, "racer": e.racer, "model": e.model, "place": place, "evaluating": evaluating,
                         "laps": race.max_laps});
        if !evaluating && let Some(replay) = races.replay(&race.name, &e.id) {
            let t = (now - start) * speed;
            if let Some(m) = replay.at(t) {
                let done: Vec<Value> =
                    e.laps.iter().take(m.lap).map(|l| json!(crate::races::clock(l.time_ms))).collect();
                current["lap"] = json!(m.lap + 1);
                current["lap_s"] = json!(m.lap_s);
                current["pose"] = json!(m.pose);
                current["progress"] = json!(m.pose[3]);
                current["lap_times"] = json!(done);
                current["camera"] = json!(m.frame.is_some());
                if let Ok(w) = tracks::world(&race.track) {
                    let (px, py) = crate::pictures::to_picture(&w)(f64::from(m.pose[0]), f64::from(m.pose[1]));
                    current["at"] = json!([px, py]);
                }
            }
        }
    }
    let up_next = s
        .queue
        .iter()
        .filter_map(|id| by_id(id))
        .find(|e| e.launched.is_none())
        .map(|e| json!({"entry": e.id, "racer": e.racer, "model": e.model}));
    let shown_count = queue.iter().filter(|q| q["status"] == "completed" || q["status"] == "failed").count();
    let board = crate::race_api::board_json(race, &ranked_entries(&s, &entries, now, speed));
    json!({
        "race": race.name, "phase": s.phase, "submissions_open": s.submissions_open, "autolaunch": s.autolaunch,
        "event_time": race.closes, "current": current, "up_next": up_next, "queue": queue,
        "evaluated": shown_count, "total": queue.len(), "leaderboard": board, "winner": s.winner,
        "ranking": race.ranking.name(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::races::{Lap, check};

    const NOW: f64 = 1_800_000_000.0;

    fn entry(id: &str, racer: &str, lap_s: f64, created: f64) -> Entry {
        Entry {
            id: id.into(),
            racer: racer.into(),
            model: format!("{racer}-model"),
            policy_version: Some(1),
            created,
            finished: Some(created + 1.0),
            status: EntryStatus::Done,
            error: None,
            laps: vec![Lap {
                time_ms: (lap_s * 1000.0) as u64,
                completed: true,
                progress: 100.0,
                off_tracks: 0,
                crashes: 0,
            }],
            path: vec![],
            launched: None,
            resets: 0,
            replay_s: Some(lap_s),
            started: Some(created),
            spent_s: 0.0,
        }
    }

    /// Issue 52: a live race through its states: a launch before the event or with submissions
    /// open is refused; one entry races at a time, in queue order (as reordered); autolaunch
    /// runs the next as each ends; resets are limited; only entries shown to their end are
    /// ranked; clearing empties the leaderboard; the winner locks it.
    #[test]
    fn a_live_race_goes_through_its_states_in_queue_order() {
        let dir = tempfile::tempdir().unwrap();
        let races = Races::open(dir.path());
        let body = serde_json::json!({"name": "final", "mode": "live", "track": "reinvent_base", "ranking": "best_lap",
                                      "min_laps": 1, "max_laps": 1, "max_resets": 1, "closes": NOW + 600.0});
        let race = check(&body, None, NOW, Some("fay")).unwrap();
        races.create(&race).unwrap();
        let model = dir.path().join("model");
        std::fs::create_dir_all(&model).unwrap();
        for (i, (racer, lap)) in [("ann", 10.0), ("bob", 9.0), ("cat", 11.0)].into_iter().enumerate() {
            races.enter(&race, &entry(&format!("e{i}"), racer, lap, NOW + i as f64), &model).unwrap();
        }
        let dup = entry("e9", "ann", 8.0, NOW + 5.0);
        assert!(matches!(races.enter(&race, &dup, &model), Err(Ok(why)) if why.contains("already")));
        let act = |a: Action, now: f64| races.act(&race, &a, now, 1.0).unwrap();
        let refused = |a: Action, now: f64, says: &str| match act(a.clone(), now) {
            Err(Refused(why)) => assert!(why.contains(says), "{a:?}: {why}"),
            Ok(_) => panic!("{a:?} at {now} was not refused"),
        };
        refused(Action::Launch, NOW + 60.0, "has not started");
        let t = NOW + 600.0;
        refused(Action::Launch, t, "close submissions");
        act(Action::Submissions(false), t).unwrap();
        // Bob goes first.
        act(Action::Move("e1".into(), 0), t).unwrap();
        assert_eq!(races.live("final").queue, ["e1", "e0", "e2"]);
        act(Action::Launch, t).unwrap();
        let snap = snapshot(&races, &race, t + 5.0, 1.0);
        assert_eq!((snap["phase"].as_str(), snap["current"]["racer"].as_str()), (Some("in_progress"), Some("bob")));
        assert_eq!(snap["up_next"]["racer"], "ann");
        refused(Action::Launch, t + 5.0, "bob");
        refused(Action::Winner, t + 5.0, "bob");
        refused(Action::Remove("e1".into()), t + 5.0, "racing");
        // Bob ends at t + 9 (his 9 s lap replayed as driven): ranked; the queue moves on itself.
        act(Action::Autolaunch(true), t + 5.0).unwrap();
        races.autolaunch(t + 10.0, 1.0);
        let snap = snapshot(&races, &race, t + 10.5, 1.0);
        assert_eq!(snap["current"]["racer"], "ann");
        assert_eq!(snap["leaderboard"][0]["racer"], "bob");
        assert_eq!((snap["evaluated"].as_u64(), snap["total"].as_u64()), (Some(1), Some(3)));
        // Ann is reset once (the race allows one), so she races again later.
        let again = act(Action::Reset("e0".into()), t + 11.0).unwrap();
        // The reset entry is evaluated again (here: as if it had been).
        assert_eq!(again.evaluate.len(), 1);
        assert_eq!(races.entry("final", "e0").unwrap().status, EntryStatus::Queued);
        races.save_entry("final", &Entry { resets: 1, ..entry("e0", "ann", 10.0, NOW) }).unwrap();
        refused(Action::Reset("e2".into()), t + 11.0, "not been launched");
        races.autolaunch(t + 11.5, 1.0);
        let snap = snapshot(&races, &race, t + 12.0, 1.0);
        assert_eq!(snap["current"]["racer"], "ann", "ann is the first pending again");
        races.autolaunch(t + 30.0, 1.0);
        refused(Action::Reset("e0".into()), t + 30.0, "reset 1 times");
        races.autolaunch(t + 45.0, 1.0);
        let snap = snapshot(&races, &race, t + 60.0, 1.0);
        let board: Vec<&str> =
            snap["leaderboard"].as_array().unwrap().iter().map(|r| r["racer"].as_str().unwrap()).collect();
        assert_eq!(board, ["bob", "ann", "cat"]);
        assert_eq!(snap["evaluated"], 3);
        // Clearing empties the board; the winner needs a ranked entry, then locks the race.
        act(Action::Clear, t + 61.0).unwrap();
        assert_eq!(snapshot(&races, &race, t + 62.0, 1.0)["leaderboard"], serde_json::json!([]));
        refused(Action::Winner, t + 62.0, "no entry is ranked");
        let again = act(Action::Reset("e2".into()), t + 63.0).unwrap();
        races.save_entry("final", &Entry { resets: 1, ..entry("e2", "cat", 11.0, NOW + 2.0) }).unwrap();
        assert_eq!(again.evaluate[0].id, "e2");
        act(Action::Launch, t + 63.0).unwrap();
        act(Action::Winner, t + 80.0).unwrap();
        let snap = snapshot(&races, &race, t + 81.0, 1.0);
        assert_eq!((snap["phase"].as_str(), snap["winner"]["racer"].as_str()), (Some("completed"), Some("cat")));
        refused(Action::Launch, t + 82.0, "completed");
    }

    /// An evaluation that ends after the facilitator launched, reset or removed its entry keeps
    /// what the facilitator did: the launch stands, a superseded run is not kept, a removed
    /// entry stays removed.
    #[test]
    fn an_evaluation_ending_late_keeps_the_facilitators_launch_reset_and_removal() {
        let dir = tempfile::tempdir().unwrap();
        let races = Races::open(dir.path());
        let body = serde_json::json!({"name": "final", "mode": "live", "track": "reinvent_base", "max_laps": 1,
                                      "closes": NOW + 600.0});
        let race = check(&body, None, NOW, None).unwrap();
        races.create(&race).unwrap();
        let model = dir.path().join("model");
        std::fs::create_dir_all(&model).unwrap();
        let running = |id: &str, racer: &str| Entry {
            status: EntryStatus::Running,
            finished: None,
            laps: vec![],
            replay_s: None,
            ..entry(id, racer, 10.0, NOW)
        };
        races.enter(&race, &running("e0", "ann"), &model).unwrap();
        races.enter(&race, &running("e1", "bob"), &model).unwrap();
        let t = NOW + 600.0;
        races.act(&race, &Action::Submissions(false), t, 1.0).unwrap().unwrap();
        races.act(&race, &Action::Launch, t, 1.0).unwrap().unwrap();
        assert_eq!(races.entry("final", "e0").unwrap().launched, Some(t));
        // The evaluation (which began before the launch) ends: the launch stands.
        races.evaluated("final", &entry("e0", "ann", 10.0, NOW)).unwrap();
        let e0 = races.entry("final", "e0").unwrap();
        assert_eq!((e0.launched, e0.status), (Some(t), EntryStatus::Done));
        // Reset: a run of before the reset ending later is not kept.
        races.act(&race, &Action::Reset("e0".into()), t + 20.0, 1.0).unwrap().unwrap();
        races.evaluated("final", &entry("e0", "ann", 10.0, NOW)).unwrap();
        let e0 = races.entry("final", "e0").unwrap();
        assert_eq!((e0.resets, e0.status, e0.launched), (1, EntryStatus::Queued, None));
        // Removed while evaluated: it stays removed, its files too.
        races.act(&race, &Action::Remove("e1".into()), t + 21.0, 1.0).unwrap().unwrap();
        races.evaluated("final", &entry("e1", "bob", 9.0, NOW)).unwrap();
        assert!(races.entry("final", "e1").is_none());
        assert_eq!(races.entries("final").len(), 1);
        assert!(!races.entry_model("final", "e1").unwrap().exists());
    }

    /// A replay is where the car was at each moment, lap after lap, at the last step once over.
    #[test]
    fn a_replay_finds_each_moments_lap_and_frame() {
        let lap = |n: usize, first| ReplayLap {
            steps: (0..n).map(|i| [i as f32, 0.0, 0.0, i as f32]).collect(),
            first_frame: first,
            frames: n / 2,
        };
        let r = Replay { hz: 10.0, width: 2, height: 2, laps: vec![lap(10, 0), lap(20, 5)] };
        assert_eq!(r.duration_s(), 3.0);
        let at = |t: f64| r.at(t).map(|m| (m.lap, m.pose[0], m.frame));
        assert_eq!(at(0.0), Some((0, 0.0, Some(0))));
        assert_eq!(at(0.55), Some((0, 5.0, Some(2))));
        assert_eq!(at(1.0), Some((1, 0.0, Some(5))));
        assert_eq!(at(2.95), Some((1, 19.0, Some(14))));
        assert_eq!(at(99.0), Some((1, 19.0, Some(14))));
    }
}
