//! One environment: a car on a world, DeepRacer's step loop and episode rules.
//!
//! A step is split in two so that rewards computed elsewhere (Python, under one GIL for a
//! whole batch) fit in: [`Env::advance`] runs the physics, computes the params and applies
//! the reset rules; [`Env::finish`] takes the reward and closes the step. [`Env::step`]
//! does both with a built-in reward.
//!
//! Rules (simapp's `deepracer_racetrack_env.py` and `markov/reset/rules`): the first step
//! of an episode is DeepRacer's `prepare` step (the car is held where it starts, the action
//! is logged but not driven, reward 0, reward function not called); then `lap_complete` at
//! progress 100, `off_track` when all four wheels are off, `reversed` after 15 steps of
//! falling progress, `immobilized` after 15 steps of moving under 0.3 mm. Training ends an
//! episode on any of them and moves the next start 5 % along the track. Evaluation starts
//! each trial at the start line and may reset an off-track car instead of ending: the car
//! is put back in the lane nearer to where it was, at the previous step's progress, and
//! waits out the penalty in `pause` steps at the control rate (held, reward 0, the
//! remaining seconds in `pause_duration`), as DeepRacer's evaluation worker does. The clock
//! (`tstamp`, `sim_time`) runs on across episodes.
//!
//! Races with objects ([`crate::objects`]): obstacles are placed and bots started at every
//! reset, and a start within a metre of one moves to the other lane. `crashed`
//! (a car corner inside an obstacle, or inside a bot the car runs into from behind) comes
//! after `lap_complete` and before `off_track`, as DeepRacer's status order has it; training
//! ends there, evaluation pays `collision_penalty_s` and, after an obstacle, puts the car a
//! metre behind it in the other lane (an off-track reset that near an obstacle too).

use crate::car::Car;
use crate::config::{NoiseConfig, SimConfig};
use crate::objects::{Contact, Traffic};
use crate::params::{EpisodeClock, Pose, RewardParams, compute_params};
use crate::race_line::LineCell;
use crate::reward::{BuiltinReward, RewardError};
use policy::{Action, MAX_SPEED, MAX_STEERING_DEG, MIN_SPEED};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;
use tracks::Track;

pub use policy::EpisodeStatus;

/// Training or evaluation rules.
#[derive(Clone, Debug, PartialEq)]
pub enum Mode {
    /// First failure ends the episode; starts move round-robin along the track.
    Training,
    /// Trials from the start line.
    Evaluation(EvalRules),
}

/// Evaluation rules (DeepRacer's evaluation worker; defaults are its values).
#[derive(Clone, Debug, PartialEq)]
pub struct EvalRules {
    /// Off-track/reversed/immobilised events a trial survives: the car is put back in the
    /// nearer lane where it left and pays `penalty_s` (DeepRacer's `NUMBER_OF_RESETS`).
    pub max_resets: u32,
    /// Time penalty per reset (s) (`OFF_TRACK_PENALTY`), waited out in `pause` steps.
    pub penalty_s: f64,
    /// Time penalty per crash reset (s) (`COLLISION_PENALTY`).
    pub collision_penalty_s: f64,
    /// A race: keep lapping until this much time has passed (the 4-minute race is 240 s),
    /// counting laps; `None` ends each trial at its first lap.
    pub time_limit_s: Option<f64>,
}

impl Default for EvalRules {
    fn default() -> Self {
        EvalRules { max_resets: 0, penalty_s: 2.0, collision_penalty_s: 5.0, time_limit_s: None }
    }
}

/// What a finished step reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepOutcome {
    /// This step's reward.
    pub reward: f64,
    /// The episode ended at this step (terminated or truncated).
    pub done: bool,
    /// Ended by the step cap, not by a rule.
    pub truncated: bool,
    /// The step's `episode_status`.
    pub status: EpisodeStatus,
    /// Progress (%) after the step.
    pub progress: f64,
    /// Steps in the episode so far (the `prepare` step included).
    pub steps: u64,
    /// Simulation time since the episode started, penalties included (s).
    pub sim_time: f64,
    /// A lap was completed at this step; its time (s, penalties included).
    pub lap_time: Option<f64>,
    /// Sum of rewards in the episode so far.
    pub episode_reward: f64,
    /// Off-track (and reversed/immobilised) and crash resets in the episode so far.
    pub resets: u32,
    /// Crashes in the episode so far (the step that ended it included).
    pub crashes: u32,
    /// Laps completed in the episode so far.
    pub laps: u32,
    /// Bots overtaken in the episode so far (see [`crate::objects::Traffic::overtakes`]), in
    /// a race with bots.
    pub overtakes: Option<u32>,
    /// The step's sim-trace fields (`wall_clock` is left 0: the caller stamps it).
    pub trace: policy::StepTrace,
}

impl StepOutcome {
    /// Times the car left the track in the episode so far: its off-track (and reversed or
    /// immobilised) resets, and this step if it ended off the track.
    pub fn off_track(&self) -> u32 {
        let crash_resets = self.crashes - u32::from(self.status == EpisodeStatus::Crashed);
        self.resets - crash_resets + u32::from(self.status == EpisodeStatus::OffTrack)
    }
}

/// The parts of a world an environment needs.
#[derive(Clone, Debug)]
pub struct EnvSpec {
    /// The world's name (tags the episodes driven on it).
    pub name: String,
    /// Track geometry for the driving direction.
    pub track: Arc<Track>,
    /// Tyre–surface friction.
    pub friction: f64,
    /// This world's actuator noise, overriding the configuration's.
    pub noise: Option<NoiseConfig>,
    /// The floor's look (for the camera).
    pub surface: tracks::Surface,
    /// The lighting (for the camera).
    pub lighting: tracks::Lighting,
    /// A generated world's seed (`generated:N`): training draws a new track every
    /// `generated.episodes_per_track` episodes.
    pub generated: Option<u64>,
}

impl EnvSpec {
    /// From a catalog world and a direction.
    pub fn from_world(world: &tracks::World, direction: tracks::Direction) -> EnvSpec {
        EnvSpec {
            name: world.name.clone(),
            track: Arc::new(world.track(direction)),
            friction: world.surface.friction(),
            noise: None,
            surface: world.surface,
            lighting: world.lighting,
            generated: tracks::generated_seed(&world.name),
        }
    }
}

/// One environment.
pub struct Env {
    spec: EnvSpec,
    cfg: Arc<SimConfig>,
    mode: Mode,
    car: Car,
    traffic: Option<Traffic>,
    rng: ChaCha8Rng,
    dt: f64,
    /// `clock.sim_time` (which runs on across episodes) when this episode started.
    episode_start: f64,
    /// A reset's penalty being waited out: `pause` steps left and the seconds they stand for.
    pause: Option<(u32, f64)>,
    episode: u64,
    next_start: f64,
    start_ndist: f64,
    clock: EpisodeClock,
    lap_start_time: f64,
    pose: Pose,
    executed_steer_deg: f64,
    reverse_count: u32,
    immobile_count: u32,
    resets: u32,
    crashes: u32,
    laps: u32,
    episode_reward: f64,
    pending: Option<Pending>,
    done: bool,
    /// DeepRacer's LiDAR: its noise, and the last scan (when the observation has one).
    lidar_rng: ChaCha8Rng,
    scan: Option<[f32; crate::lidar::RAYS]>,
    /// The track's racing line (for `builtin:race_line`), computed at its first use.
    line: LineCell,
}

struct Pending {
    params: RewardParams,
    status: EpisodeStatus,
    ends: bool,
    truncated: bool,
    lap_time: Option<f64>,
    prepare: bool,
    /// This step's `pause_duration` (s).
    pause_duration: f64,
    /// Where the car stood before this step (for the reset's lane).
    before: Pose,
    /// What the car touched.
    contact: Option<Contact>,
}

/// Why an environment could not be built.
#[derive(Debug, thiserror::Error)]
pub enum EnvError {
    /// The configuration asks for something that does not exist yet or is out of range.
    #[error("{0}")]
    Config(String),
}

impl Env {
    /// An environment seeded with `seed`; its first training start is at `first_start`
    /// (a fraction of the track) and moves round-robin from there.
    pub fn new(spec: EnvSpec, cfg: Arc<SimConfig>, mode: Mode, seed: u64, first_start: f64) -> Result<Env, EnvError> {
        // Negated so that NaN is refused too.
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        if !(cfg.control_hz > 0.0) || cfg.physics_substeps == 0 {
            return Err(EnvError::Config("control_hz must be positive and physics_substeps at least 1".into()));
        }
        if let Some(l) = cfg.observation.camera_lidar {
            if !cfg.observation.kind.is_camera() {
                return Err(EnvError::Config(format!(
                    "observation.camera_lidar goes beside a camera; observation.kind is {:?}",
                    cfg.observation.kind
                )));
            }
            if l.sectors == 0
                || !crate::lidar::RAYS.is_multiple_of(l.sectors)
                || l.values == 0
                || l.clip.is_nan()
                || l.clip <= 0.0
            {
                return Err(EnvError::Config(format!(
                    "observation.camera_lidar: {} sectors of {} values within {} m; sectors must divide 64 and values and the clip be positive",
                    l.sectors, l.values, l.clip
                )));
            }
        }
        let dt = 1.0 / cfg.control_hz;
        let car = Car::new(&cfg.car, spec.friction, dt / cfg.physics_substeps as f64);
        let traffic = Traffic::new(&spec.track, &cfg.race, "the simulator configuration").map_err(EnvError::Config)?;
        let line = LineCell::new(spec.track.clone(), cfg.car.clone(), spec.surface);
        let mut env = Env {
            spec,
            cfg,
            mode,
            car,
            traffic,
            rng: ChaCha8Rng::seed_from_u64(seed),
            dt,
            episode_start: 0.0,
            pause: None,
            episode: 0,
            next_start: first_start.rem_euclid(1.0),
            start_ndist: 0.0,
            clock: EpisodeClock { start_ndist: 0.0, prev_progress: 0.0, steps: 0, sim_time: 0.0 },
            lap_start_time: 0.0,
            pose: Pose { x: 0.0, y: 0.0, yaw: 0.0 },
            executed_steer_deg: 0.0,
            reverse_count: 0,
            immobile_count: 0,
            resets: 0,
            crashes: 0,
            laps: 0,
            episode_reward: 0.0,
            pending: None,
            done: true,
            lidar_rng: ChaCha8Rng::seed_from_u64(seed ^ 0x11DA_4000),
            scan: None,
            line,
        };
        env.reset();
        Ok(env)
    }

    /// Start a new episode.
    pub fn reset(&mut self) {
        self.next_generated_track();
        let start = match self.mode {
            Mode::Training => {
                let s = self.next_start;
                self.next_start = (self.next_start + self.cfg.episode.round_robin_advance).rem_euclid(1.0);
                s
            }
            Mode::Evaluation(_) => 0.0,
        };
        self.episode += 1;
        self.start_ndist = start;
        self.place_on_centre_line(start);
        if let Some(traffic) = self.traffic.as_mut() {
            let track = &self.spec.track;
            match self.mode {
                Mode::Training => traffic.reset(track, &mut self.rng),
                Mode::Evaluation(_) => traffic.reset_passable(track, &mut self.rng),
            }
            // DeepRacer's training start beside an object: the other lane. Evaluation too,
            // where DeepRacer starts on the centre line whatever stands there, so that a box
            // placed at random just past the start line makes the trial a crash at its first
            // step (docs/simulator.md).
            let poses: Vec<_> = traffic.objects().iter().map(|o| o.pose).collect();
            if let Some(lane) = tracks::objects::start_lane(track, start * track.length(), &poses) {
                let at = track.lane_pose(lane, start * track.length());
                self.place(at.position, at.heading);
            }
        }
        let now = self.clock.sim_time;
        self.episode_start = now;
        self.clock = EpisodeClock { start_ndist: start, prev_progress: 0.0, steps: 0, sim_time: now };
        self.lap_start_time = now;
        self.pause = None;
        self.reverse_count = 0;
        self.immobile_count = 0;
        self.resets = 0;
        self.crashes = 0;
        self.laps = 0;
        self.episode_reward = 0.0;
        self.pending = None;
        self.done = false;
        self.sense();
    }

    /// A fresh LiDAR scan, when the observation has the LiDAR (a scan a step, where
    /// DeepRacer's 10 Hz sensor is read at the 15 Hz step).
    fn sense(&mut self) {
        if self.cfg.observation.camera_lidar.is_some() {
            let objects = self.traffic.as_ref().map_or(&[][..], |t| t.objects());
            let at = tracks::P2::new(self.pose.x, self.pose.y);
            self.scan = Some(crate::lidar::scan(at, self.pose.yaw, objects, &mut self.lidar_rng));
        }
    }

    /// The last LiDAR scan (m; infinity where nothing is in range), when the observation
    /// has the LiDAR.
    pub fn lidar_scan(&self) -> Option<&[f32; crate::lidar::RAYS]> {
        self.scan.as_ref()
    }

    fn place_on_centre_line(&mut self, ndist: f64) {
        let track = &self.spec.track;
        let (p, heading) = track.pose_at(ndist * track.length());
        self.place(p, heading);
    }

    fn place(&mut self, p: tracks::P2, heading: f64) {
        self.car.reset(p.x, p.y, heading);
        self.pose = Pose { x: p.x, y: p.y, yaw: heading };
        self.executed_steer_deg = 0.0;
    }

    /// Run the physics for one control step and judge it. Call [`Env::finish`] next.
    pub fn advance(&mut self, action: Action) {
        assert!(!self.done, "advance() on a finished episode: call reset()");
        let noise = self.spec.noise.as_ref().unwrap_or(&self.cfg.noise);
        let n1: f64 = StandardNormal.sample(&mut self.rng);
        let n2: f64 = StandardNormal.sample(&mut self.rng);
        // DeepRacer's send_action clamps to the car's limits; noise is Paddock's actuator model.
        let steer = (action.steering_angle + noise.steering_deg * n1).clamp(-MAX_STEERING_DEG, MAX_STEERING_DEG);
        let speed = (action.speed * (1.0 + noise.speed_fraction * n2)).clamp(MIN_SPEED, MAX_SPEED);
        let prepare = self.clock.steps == 0;
        // DeepRacer's prepare and pause phases send zero speed and pin the car where it
        // stands; the model's action is only logged.
        let held = prepare || self.pause.is_some();
        let last = self.pose;
        if held {
            self.car.reset(last.x, last.y, last.yaw);
            self.executed_steer_deg = 0.0;
        } else {
            let steer_rad = steer.to_radians();
            for _ in 0..self.cfg.physics_substeps {
                self.car.step(steer_rad, speed);
            }
            self.executed_steer_deg = steer;
        }
        let state = self.car.state();
        if !held {
            self.pose = Pose { x: state.x, y: state.y, yaw: state.yaw };
        }
        self.clock.steps += 1;
        self.clock.sim_time += self.dt;
        let wheels = self.car.wheel_points(&state);
        let mut params = compute_params(&self.spec.track, &self.pose, &wheels, action, &self.clock);
        let mut contact = None;
        if let Some(traffic) = self.traffic.as_mut() {
            let track = &self.spec.track;
            let t = self.clock.sim_time - self.episode_start;
            traffic.update(track, t, &mut self.rng);
            let lap_progress = (params.progress + self.start_ndist * 100.0).rem_euclid(100.0);
            // Every step, held ones too: bots drive on past a car that waits out a penalty.
            traffic.track_passes(track, lap_progress / 100.0 * track.length());
            if !held {
                let car = tracks::P2::new(self.pose.x, self.pose.y);
                contact = traffic.contact(track, car, self.pose.yaw, lap_progress);
                if let Some(Contact::HitByBot(_)) = contact {
                    traffic.bots_hit(t);
                }
            }
            traffic.fill_params(track, &self.pose, contact, &mut params);
        }

        let ep = &self.cfg.episode;
        let mut pause_duration = 0.0;
        let mut status = if prepare {
            EpisodeStatus::Prepare
        } else if let Some((rows, seconds)) = self.pause {
            // The penalty counts down by the step's sim time; the row that reaches 0 is the
            // last `pause` row (DeepRacer's `TrackerManager`).
            self.pause = (rows > 1).then(|| (rows - 1, seconds - self.dt));
            pause_duration = (seconds - self.dt).max(0.0);
            EpisodeStatus::Pause
        } else {
            let moved = ((self.pose.x - last.x).powi(2) + (self.pose.y - last.y).powi(2)).sqrt();
            self.immobile_count = if moved <= ep.immobilized_distance { self.immobile_count + 1 } else { 0 };
            self.reverse_count = if params.progress < self.clock.prev_progress { self.reverse_count + 1 } else { 0 };
            if params.progress >= 100.0 {
                EpisodeStatus::LapComplete
            } else if params.is_crashed {
                EpisodeStatus::Crashed
            } else if params.is_offtrack {
                EpisodeStatus::OffTrack
            } else if self.immobile_count >= ep.immobilized_steps {
                EpisodeStatus::Immobilized
            } else if self.reverse_count >= ep.reverse_steps {
                EpisodeStatus::Reversed
            } else {
                EpisodeStatus::InProgress
            }
        };
        let lap_time = (status == EpisodeStatus::LapComplete).then_some(self.clock.sim_time - self.lap_start_time);
        let mut ends = match status {
            EpisodeStatus::Prepare | EpisodeStatus::InProgress | EpisodeStatus::Pause => false,
            EpisodeStatus::LapComplete => !matches!(&self.mode, Mode::Evaluation(r) if r.time_limit_s.is_some()),
            EpisodeStatus::OffTrack | EpisodeStatus::Reversed | EpisodeStatus::Immobilized | EpisodeStatus::Crashed => {
                match &self.mode {
                    Mode::Training => true,
                    Mode::Evaluation(r) => self.resets >= r.max_resets,
                }
            }
            EpisodeStatus::TimeUp => true,
        };
        if let Mode::Evaluation(EvalRules { time_limit_s: Some(limit), .. }) = self.mode
            && !ends
            && self.clock.sim_time - self.episode_start >= limit
        {
            status = EpisodeStatus::TimeUp;
            ends = true;
        }
        let truncated = !ends && self.clock.steps >= ep.max_steps;
        self.pending = Some(Pending {
            params,
            status,
            ends: ends || truncated,
            truncated,
            lap_time,
            prepare,
            pause_duration,
            before: last,
            contact,
        });
    }

    /// The params of the step [`Env::advance`] just ran.
    pub fn params(&self) -> &RewardParams {
        &self.pending.as_ref().expect("advance() first").params
    }

    /// Whether that step calls the reward function (every step but `prepare` and `pause`).
    pub fn needs_reward(&self) -> bool {
        let p = self.pending.as_ref().expect("advance() first");
        !(p.prepare || p.status == EpisodeStatus::Pause)
    }

    /// Close the step with its reward (ignored on `prepare` and `pause` steps: reward 0).
    pub fn finish(&mut self, reward: f64) -> StepOutcome {
        let p = self.pending.take().expect("advance() first");
        let reward = if p.prepare || p.status == EpisodeStatus::Pause { 0.0 } else { reward };
        self.episode_reward += reward;
        let progress = p.params.progress;
        // The previous step's progress, before this step's replaces it (a reset goes there).
        let before_progress = self.clock.prev_progress;
        // DeepRacer: prev_progress = 0 after a completed lap, else this step's progress.
        self.clock.prev_progress = if progress >= 100.0 { 0.0 } else { progress };
        if p.status == EpisodeStatus::LapComplete {
            self.laps += 1;
            self.lap_start_time = self.clock.sim_time;
        }
        let crashed = p.status == EpisodeStatus::Crashed;
        self.crashes += u32::from(crashed);
        let failed = crashed
            || matches!(p.status, EpisodeStatus::OffTrack | EpisodeStatus::Reversed | EpisodeStatus::Immobilized);
        let mut pause_duration = p.pause_duration;
        if failed && !p.ends {
            // Evaluation reset (DeepRacer's `_judge_action_at_run_phase`): back at the previous
            // step's progress in the lane nearer to where the car stood, or behind the obstacle
            // hit (or near) in the other lane, then the penalty waited out in `pause` steps at
            // the control rate.
            let penalty = match &self.mode {
                Mode::Evaluation(r) if crashed => r.collision_penalty_s,
                Mode::Evaluation(r) => r.penalty_s,
                Mode::Training => 0.0,
            };
            self.resets += 1;
            let track = self.spec.track.clone();
            let along = (self.start_ndist + before_progress.max(0.0) / 100.0) * track.length();
            let obstacle = self.traffic.as_ref().and_then(|t| match p.contact {
                Some(Contact::Obstacle(i)) => t.objects().get(i).copied(),
                _ => t.obstacle_near(&track, along).copied(),
            });
            match obstacle {
                Some(o) => {
                    let at = crate::objects::behind(&track, &o);
                    self.place(at.position, at.heading);
                }
                None => {
                    let (at, heading) = track.reset_pose(along, tracks::P2::new(p.before.x, p.before.y));
                    self.place(at, heading);
                }
            }
            let rows = (penalty / self.dt - 1e-9).ceil().max(0.0) as u32;
            self.pause = (rows > 0).then_some((rows, penalty));
            pause_duration = penalty;
            self.reverse_count = 0;
            self.immobile_count = 0;
        }
        self.done = p.ends;
        self.sense();
        let q = &p.params;
        let [prev, next] = q.closest_waypoints;
        let wp = self.spec.track.waypoints();
        let here = tracks::P2::new(q.x, q.y);
        let trace = policy::StepTrace {
            x: q.x,
            y: q.y,
            yaw: q.heading as f32,
            steer: q.steering_angle as f32,
            throttle: q.speed as f32,
            progress: progress as f32,
            closest_waypoint: if (wp[next] - here).norm() < (wp[prev] - here).norm() { next } else { prev } as u32,
            all_wheels_on_track: q.all_wheels_on_track,
            status: p.status,
            tstamp: q.sim_time,
            pause_duration: pause_duration as f32,
            wall_clock: 0.0,
        };
        StepOutcome {
            reward,
            done: p.ends,
            truncated: p.truncated,
            status: p.status,
            progress,
            steps: self.clock.steps,
            sim_time: self.clock.sim_time - self.episode_start,
            lap_time: p.lap_time,
            episode_reward: self.episode_reward,
            resets: self.resets,
            crashes: self.crashes,
            laps: self.laps,
            overtakes: self.traffic.as_ref().and_then(Traffic::overtakes),
            trace,
        }
    }

    /// `advance` + a built-in reward + `finish`.
    pub fn step(&mut self, action: Action, reward: BuiltinReward) -> Result<StepOutcome, RewardError> {
        self.advance(action);
        let r = if self.needs_reward() { reward.reward(self.params(), &self.line)? } else { 0.0 };
        Ok(self.finish(r))
    }

    /// Drive another world from the episode that has just begun (after a reset, before its
    /// first step): the same episode, started again on `spec`'s track from the same fraction
    /// of it. Counters and seeds carry on, so episodes stay numbered without a gap.
    pub fn set_world(&mut self, spec: EnvSpec) -> Result<(), EnvError> {
        self.take_world(spec)?;
        self.episode -= 1;
        self.next_start = self.start_ndist;
        self.reset();
        Ok(())
    }

    /// Make `spec` this environment's world (the car, the objects, the racing line).
    fn take_world(&mut self, spec: EnvSpec) -> Result<(), EnvError> {
        let traffic =
            Traffic::new(&spec.track, &self.cfg.race, "the simulator configuration").map_err(EnvError::Config)?;
        self.car = Car::new(&self.cfg.car, spec.friction, self.dt / self.cfg.physics_substeps as f64);
        self.line = LineCell::new(spec.track.clone(), self.cfg.car.clone(), spec.surface);
        self.traffic = traffic;
        self.spec = spec;
        Ok(())
    }

    /// A generated world in training: every `generated.episodes_per_track` episodes, the next
    /// track of this environment's own draw, driven either way round at random (the world
    /// keeps its name, `generated:N`).
    fn next_generated_track(&mut self) {
        let every = self.cfg.generated.episodes_per_track;
        let due = self.spec.generated.is_some()
            && self.mode == Mode::Training
            && every > 0
            && self.episode > 0
            && self.episode.is_multiple_of(every);
        if !due {
            return;
        }
        use rand::Rng;
        let seed: u64 = self.rng.random();
        // Either way round: a generated loop turns mostly one way, its reverse the other.
        let direction =
            if self.rng.random_bool(0.5) { tracks::Direction::Reversed } else { tracks::Direction::Forward };
        // A name of its own: the renderer keeps a track's mesh by its name.
        let name = format!("{}#{seed:016x}", self.spec.name);
        match tracks::generated_world(&name, seed) {
            Ok(world) => {
                let mut spec = self.spec.clone();
                spec.track = Arc::new(world.track(direction));
                if let Err(e) = self.take_world(spec) {
                    tracing::warn!("{}: the next generated track is refused, this one stays: {e}", self.spec.name);
                }
            }
            Err(e) => tracing::warn!("{}: no next generated track, this one stays: {e}", self.spec.name),
        }
    }

    /// The track's racing line, as `builtin:race_line` sees it.
    pub fn line(&self) -> &LineCell {
        &self.line
    }

    /// Whether the episode has ended (call [`Env::reset`]).
    pub fn is_done(&self) -> bool {
        self.done
    }

    /// The world's parts.
    pub fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    /// The track.
    pub fn track(&self) -> &Arc<Track> {
        &self.spec.track
    }

    /// Episode counter (1 for the first episode); the key reward hosts cache per-episode data by.
    pub fn episode(&self) -> u64 {
        self.episode
    }

    /// The race's obstacles and bots now (none in a time trial).
    pub fn objects(&self) -> &[crate::objects::Object] {
        self.traffic.as_ref().map(|t| t.objects()).unwrap_or_default()
    }

    /// The car origin's pose.
    pub fn pose(&self) -> Pose {
        self.pose
    }

    /// The car's full planar state.
    pub fn car_state(&self) -> crate::car::CarState {
        self.car.state()
    }

    /// The steering (degrees) the car executed last step (after noise and clamping).
    pub fn executed_steering_deg(&self) -> f64 {
        self.executed_steer_deg
    }

    /// Progress at the end of the last finished step.
    pub fn progress(&self) -> f64 {
        self.clock.prev_progress
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Normalised distance of this episode's start.
    pub fn start_ndist(&self) -> f64 {
        self.start_ndist
    }
}
