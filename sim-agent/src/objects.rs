//! The objects of a race in one environment: obstacles placed anew every episode, bot cars
//! driven along the lanes, and what the car touching one of them means (the simapp's
//! `ObstaclesCtrl`, `BotCarsCtrl` and `TrackData.get_collided_object_name`).
//!
//! Bots are kinematic, as in DeepRacer: posed every step at `s(t) = d₀ + v·t` metres of
//! centre-line progress (less the time they stood still after being hit), beside that
//! centre-line point in their lane. DeepRacer fits a cubic spline through each lane's
//! vertices; here the lane is the quarter-width polyline itself, which the spline passes
//! through. A lane change blends from one lane to the other over `lane_change_distance`
//! metres of progress, ending at a time drawn between the lower and upper lane-change times
//! (plus the change's own duration) after the previous change; the blend is a smoothstep
//! where DeepRacer's is a spline through the two lanes' vertices.

use crate::params::{Pose, RewardParams, TrackObject, object_params};
use crate::race::{RaceConfig, RaceType};
use rand::Rng;
use tracks::objects::{self, BOX_FOOTPRINT, CAR_FOOTPRINT, Lane, ObjectPose, Placement};
use tracks::{P2, Track};

/// Metres behind an obstacle that evaluation puts a car that hit it, in the other lane
/// (`RESET_BEHIND_DIST`); an off-track reset this near an obstacle goes there too.
pub const RESET_BEHIND: f64 = 1.0;

/// What an object is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A box (or a bot car standing still, `is_obstacle_bot_car`).
    Obstacle,
    /// A bot car driving its lane.
    Bot,
}

/// One object this step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Object {
    /// Obstacle or bot.
    pub kind: Kind,
    /// Where it stands.
    pub pose: ObjectPose,
    /// Its footprint, across × along (m).
    pub footprint: (f64, f64),
    /// Drawn as a car (bots, and obstacles when `is_obstacle_bot_car`), else as a box.
    pub car: bool,
}

/// What the car touched this step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Contact {
    /// An obstacle (index into [`Traffic::objects`]): a crash.
    Obstacle(usize),
    /// A bot, from behind: a crash.
    RearEnded(usize),
    /// A bot ran into the car from behind: no crash for the car; the bots stand still for
    /// `bot_car_penalty` seconds.
    HitByBot(usize),
}

impl Contact {
    /// Whether the car crashed (DeepRacer's `is_crashed`).
    pub fn is_crash(self) -> bool {
        !matches!(self, Contact::HitByBot(_))
    }

    /// The object's index.
    pub fn index(self) -> usize {
        match self {
            Contact::Obstacle(i) | Contact::RearEnded(i) | Contact::HitByBot(i) => i,
        }
    }
}

#[derive(Clone, Debug)]
struct Bot {
    /// Centre-line metres at the episode's start.
    start: f64,
    /// The lane it drives (or leaves, during a change).
    lane: Lane,
    /// When its current lane change ends (episode seconds); `None` before the first draw.
    change_end: Option<f64>,
    /// The car's centre-line metres ahead of this bot at the last step (wrapped to half a
    /// lap either way); `None` before the first.
    lead: Option<f64>,
    /// Times the car went past this bot less times this bot went past the car.
    passes: i32,
}

/// Draws of a random layout an evaluation trial makes at most to find one a car can pass (the
/// last is kept: a crowded race may have none).
pub const REDRAWS: usize = 64;

/// The most the car's lead on a bot may change in one step and still count as driving past
/// it (m): more is a jump (the car put back after a reset, or half a lap away, where the
/// lead wraps from one side to the other).
const PASS_JUMP: f64 = 1.0;

/// The obstacles and bots of one environment.
#[derive(Clone, Debug)]
pub struct Traffic {
    obstacles: Option<Placement>,
    obstacle_footprint: (f64, f64),
    obstacle_is_car: bool,
    bot_placement: Option<Placement>,
    speed: f64,
    lane_change: Option<(f64, f64, f64)>,
    penalty: f64,
    bots: Vec<Bot>,
    /// Times a car ran into the bots this episode, and until when they stand still.
    bot_hits: u32,
    pause_until: f64,
    objects: Vec<Object>,
}

impl Traffic {
    /// The traffic of `race` on `track` (`None`: a time trial); refused when the track cannot
    /// hold what the race asks for, naming the key.
    pub fn new(track: &Track, race: &RaceConfig, origin: &str) -> Result<Option<Traffic>, String> {
        race.check(origin).map_err(|e| e.0)?;
        let obstacles = race.placement(origin).map_err(|e| e.0)?;
        let bot_placement =
            (race.race_type == RaceType::HeadToBot && race.number_of_bot_cars > 0).then(|| Placement::Spaced {
                count: race.number_of_bot_cars,
                min_gap_percent: 100.0 * race.min_distance_between_bot_cars / track.length(),
                random: race.randomize_bot_car_locations,
            });
        if obstacles.is_none() && bot_placement.is_none() {
            return Ok(None);
        }
        // Whether a placement fits does not depend on the draw; any seed tells.
        let mut probe = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
        if let Some(p) = &obstacles {
            objects::place(track, p, &mut probe).map_err(|e| format!("{origin}: {}: {e}", track.name()))?;
        }
        if let Some(p) = &bot_placement {
            objects::place(track, p, &mut probe).map_err(|e| {
                format!(
                    "{origin}: {}: race.number_of_bot_cars (NUMBER_OF_BOT_CARS) {} with \
                     race.min_distance_between_bot_cars {} m: {}",
                    track.name(),
                    race.number_of_bot_cars,
                    race.min_distance_between_bot_cars,
                    e.0.replace("NUMBER_OF_OBSTACLES", "the count")
                        .replace("MIN_DISTANCE_BETWEEN_OBSTACLES", "the gap")
                )
            })?;
        }
        let obstacle_is_car = race.is_obstacle_bot_car;
        Ok(Some(Traffic {
            obstacles,
            obstacle_footprint: if obstacle_is_car { CAR_FOOTPRINT } else { BOX_FOOTPRINT },
            obstacle_is_car,
            bot_placement,
            speed: race.bot_car_speed,
            lane_change: race.is_lane_change.then_some((
                race.lower_lane_change_time,
                race.upper_lane_change_time,
                race.lane_change_distance,
            )),
            penalty: race.bot_car_penalty,
            bots: vec![],
            bot_hits: 0,
            pause_until: 0.0,
            objects: vec![],
        }))
    }

    /// A new episode: obstacles placed (anew, when random), bots at their starts.
    pub fn reset(&mut self, track: &Track, rng: &mut impl Rng) {
        self.reset_drawn(track, rng, false);
    }

    /// A new evaluation trial: as [`Traffic::reset`], but obstacles placed at random are drawn
    /// again (up to [`REDRAWS`] times) while two in opposite lanes stand too near for any car
    /// to weave between them ([`objects::passable`]). A trial no model can finish tells
    /// nothing about the model; training still meets every draw.
    pub fn reset_passable(&mut self, track: &Track, rng: &mut impl Rng) {
        self.reset_drawn(track, rng, true);
    }

    fn reset_drawn(&mut self, track: &Track, rng: &mut impl Rng, passable: bool) {
        let place = |p: &Placement, rng: &mut _| objects::place(track, p, rng).expect("checked by Traffic::new");
        let mut obstacles = self.obstacles.as_ref().map(|p| place(p, rng)).unwrap_or_default();
        if let Some(p @ Placement::Spaced { random: true, .. }) = self.obstacles.as_ref().filter(|_| passable) {
            for _ in 0..REDRAWS {
                if objects::passable(track, &obstacles) {
                    break;
                }
                obstacles = place(p, rng);
            }
        }
        self.bots = match &self.bot_placement {
            Some(p) => place(p, rng)
                .into_iter()
                .map(|o| Bot { start: o.along, lane: o.lane, change_end: None, lead: None, passes: 0 })
                .collect(),
            None => vec![],
        };
        self.bot_hits = 0;
        self.pause_until = 0.0;
        self.objects = obstacles
            .into_iter()
            .map(|pose| Object {
                kind: Kind::Obstacle,
                pose,
                footprint: self.obstacle_footprint,
                car: self.obstacle_is_car,
            })
            .collect();
        let n = self.objects.len();
        self.objects.extend(self.bots.iter().map(|b| Object {
            kind: Kind::Bot,
            pose: track.lane_pose(b.lane, b.start),
            footprint: CAR_FOOTPRINT,
            car: true,
        }));
        self.update(track, 0.0, rng);
        debug_assert_eq!(self.objects.len(), n + self.bots.len());
    }

    /// Pose the bots for `t` seconds into the episode.
    pub fn update(&mut self, track: &Track, t: f64, rng: &mut impl Rng) {
        if self.bots.is_empty() || t < self.pause_until {
            return;
        }
        let len = track.length();
        let v = self.speed;
        let run = (t - self.bot_hits as f64 * self.penalty).max(0.0);
        let first = self.objects.len() - self.bots.len();
        for (bot, obj) in self.bots.iter_mut().zip(&mut self.objects[first..]) {
            let s = (bot.start + v * run).rem_euclid(len);
            let mut w = None;
            if let Some((lo, hi, dist)) = self.lane_change.filter(|_| v > 0.0) {
                let duration = dist / v;
                match bot.change_end {
                    Some(end) if t < end => {}
                    Some(_) => {
                        bot.lane = bot.lane.other();
                        bot.change_end = Some(t + rng.random_range(lo..=hi) + duration);
                    }
                    None => bot.change_end = Some(t + rng.random_range(lo..=hi) + duration),
                }
                let end = bot.change_end.expect("set above");
                let f = (t - (end - duration)) / duration;
                w = (f > 0.0).then_some((f, dist));
            }
            let at = |s: f64, w: f64| {
                let a = track.lane_pose(bot.lane, s.rem_euclid(len)).position;
                if w == 0.0 {
                    return a;
                }
                let b = track.lane_pose(bot.lane.other(), s.rem_euclid(len)).position;
                a + (b - a) * w
            };
            let smooth = |f: f64| {
                let f = f.clamp(0.0, 1.0);
                f * f * (3.0 - 2.0 * f)
            };
            let (here, ahead) = match w {
                Some((f, dist)) => (at(s, smooth(f)), at(s + 0.05, smooth(f + 0.05 / dist))),
                None => (at(s, 0.0), at(s + 0.05, 0.0)),
            };
            let d = ahead - here;
            obj.pose = ObjectPose { position: here, heading: d.y.atan2(d.x), along: s, lane: bot.lane };
        }
    }

    /// Count the car, at `car_along` centre-line metres, going past the bots (after
    /// [`Traffic::update`] each step): a bot the car passes counts one, one that passes the car
    /// takes it back.
    pub fn track_passes(&mut self, track: &Track, car_along: f64) {
        let len = track.length();
        let first = self.objects.len() - self.bots.len();
        for (bot, obj) in self.bots.iter_mut().zip(&self.objects[first..]) {
            let lead = (car_along - obj.pose.along + len / 2.0).rem_euclid(len) - len / 2.0;
            if let Some(before) = bot.lead
                && (lead - before).abs() < PASS_JUMP
            {
                if before < 0.0 && lead >= 0.0 {
                    bot.passes += 1;
                } else if before >= 0.0 && lead < 0.0 {
                    bot.passes -= 1;
                }
            }
            bot.lead = Some(lead);
        }
    }

    /// Bots the car overtook this episode (per bot, the times the car went past it less the
    /// times it went past the car, when more), when the race has bots.
    pub fn overtakes(&self) -> Option<u32> {
        (!self.bots.is_empty()).then(|| self.bots.iter().map(|b| b.passes.max(0) as u32).sum())
    }

    /// The objects now: obstacles, then bots (DeepRacer's object order).
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// The objects as the reward params see them.
    pub fn track_objects(&self) -> Vec<TrackObject> {
        self.objects.iter().map(|o| TrackObject { position: o.pose.position, heading: o.pose.heading }).collect()
    }

    /// The bots' speed, when the race has bots (DeepRacer fills `objects_speed` with it).
    pub fn bot_speed(&self) -> Option<f64> {
        (!self.bots.is_empty()).then_some(self.speed)
    }

    /// What a car at `car` (origin, yaw) touches. `car_progress` is its progress round the
    /// lap from the start line (`(progress + start_ndist·100) % 100`): a bot counts as hit
    /// from behind when the car's is smaller than the bot's, as the simapp compares them.
    pub fn contact(&self, track: &Track, car: P2, yaw: f64, car_progress: f64) -> Option<Contact> {
        let shapes: Vec<(P2, f64, (f64, f64))> =
            self.objects.iter().map(|o| (o.pose.position, o.pose.heading, o.footprint)).collect();
        let i = objects::crashed(car, yaw, &shapes)?;
        let o = &self.objects[i];
        Some(match o.kind {
            Kind::Obstacle => Contact::Obstacle(i),
            Kind::Bot => {
                let h = o.pose.heading;
                let front = o.pose.position + nalgebra::Vector2::new(h.cos(), h.sin()) * crate::params::FRONT_OFFSET;
                let bot_progress = 100.0 * track.center().project(front).along / track.length();
                if car_progress < bot_progress { Contact::RearEnded(i) } else { Contact::HitByBot(i) }
            }
        })
    }

    /// Fill the object keys of `params` for a car at `pose` that touched `contact` this step:
    /// `is_crashed`, every `objects_*`, `closest_objects` and `object_in_camera`.
    pub fn fill_params(&self, track: &Track, pose: &Pose, contact: Option<Contact>, params: &mut RewardParams) {
        params.is_crashed = contact.is_some_and(Contact::is_crash);
        params.objects = object_params(track, pose.front(), &self.track_objects(), self.bot_speed());
        let car = P2::new(pose.x, pose.y);
        params.object_in_camera = object_in_camera(car, pose.yaw, &self.objects, params.objects.closest_objects[1]);
    }

    /// A car ran into the bots from behind at `t`: they all stand still for the penalty
    /// (once per penalty: a touch while they stand does not add to it).
    pub fn bots_hit(&mut self, t: f64) {
        if t < self.pause_until {
            return;
        }
        self.bot_hits += 1;
        self.pause_until = t + self.penalty;
        for b in &mut self.bots {
            if let Some(end) = b.change_end.as_mut() {
                *end += self.penalty;
            }
        }
    }

    /// The obstacle within [`RESET_BEHIND`] of centre-line distance `along` (either way,
    /// across the start line too), if any.
    pub fn obstacle_near(&self, track: &Track, along: f64) -> Option<&Object> {
        let len = track.length();
        self.objects.iter().filter(|o| o.kind == Kind::Obstacle).find(|o| {
            let d = (o.pose.along - along).rem_euclid(len);
            d.min(len - d) < RESET_BEHIND
        })
    }
}

/// The pose behind `obstacle` that evaluation puts a car at: [`RESET_BEHIND`] metres before
/// it along the centre line, in the other lane, facing along that lane.
pub fn behind(track: &Track, obstacle: &Object) -> ObjectPose {
    let along = (obstacle.pose.along - RESET_BEHIND).rem_euclid(track.length());
    track.lane_pose(obstacle.pose.lane.other(), along)
}

/// DeepRacer's `object_in_camera`, off by one as the simapp is: it asks whether the object
/// at position `next` of the list *with the car first* is in the front camera's frustum, so
/// it tests `objects[next - 1]` (and the car itself, never in view, for `next == 0`). An
/// object is in view when its centre or a footprint corner is inside the frustum (near
/// 0.2 m, far 300 m, horizontal field 1.13 rad, 4:3, from DeepRacer's camera mount).
pub fn object_in_camera(car: P2, yaw: f64, objects: &[Object], next: usize) -> bool {
    let Some(o) = next.checked_sub(1).and_then(|i| objects.get(i)) else { return false };
    let z = if o.car { 0.0 } else { 0.1 };
    let mut pts = objects::corners(o.pose.position, o.pose.heading, o.footprint).to_vec();
    pts.push(o.pose.position);
    pts.iter().any(|p| in_frustum(car, yaw, *p, z))
}

/// Whether a point at height `z` is inside the front camera's frustum.
fn in_frustum(car: P2, yaw: f64, p: P2, z: f64) -> bool {
    use crate::camera::{CAMERA_PITCH, HFOV};
    let (s, c) = yaw.sin_cos();
    let d = p - car;
    // In the car's frame, then the camera's (0.14529 ahead, 0.13033 up, pitched down).
    let (x, y, z) = (d.x * c + d.y * s - 0.14529, -d.x * s + d.y * c, z - 0.13033);
    let (ps, pc) = CAMERA_PITCH.sin_cos();
    let fwd = x * pc - z * ps;
    let up = x * ps + z * pc;
    let tan_h = (HFOV / 2.0).tan();
    let tan_v = tan_h * 480.0 / 640.0;
    (0.2..=300.0).contains(&fwd) && y.abs() <= fwd * tan_h && up.abs() <= fwd * tan_v
}
