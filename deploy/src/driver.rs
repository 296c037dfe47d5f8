//! The car's loop without its transport: frames in, servo commands out, models swapped in
//! between two frames, a watchdog and an e-stop.
//!
//! [`ModelSlot`] holds the model that drives (`arc-swap`): a loader verifies a new model on
//! its own thread and stores it in one atomic swap; a frame takes the model that is there when
//! it starts and keeps it to its end, so no frame ever sees half of a model, and frames keep
//! flowing while one loads. [`Driver`] turns each frame into a command: throttle 0 (and
//! straight wheels) while no verified model is loaded or the e-stop is held; the watchdog's
//! [`Driver::tick`] sends throttle 0 when frames stop for `watchdog_ms`, again every period,
//! until they return. Every state change is logged.

use crate::frame::{FrameError, add_lidar, preprocess};
use crate::infer::Scratch;
use crate::verify::{Refusal, VerifiedModel, verify};
use arc_swap::ArcSwapOption;
use policy::car::{CarConfig, Layout};
use policy::signature::TrustedKeys;
use policy::{Choice, ModelParts};
use protocol::ros::{self, Header, Servo};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Which models the car takes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Follow {
    /// Every newer published version.
    Latest,
    /// The learner's best model (by evaluation) as it changes.
    Best,
    /// This version only.
    Version(u64),
}

impl std::str::FromStr for Follow {
    type Err = String;
    fn from_str(s: &str) -> Result<Follow, String> {
        match s {
            "latest" => Ok(Follow::Latest),
            "best" => Ok(Follow::Best),
            v => {
                v.parse().map(Follow::Version).map_err(|_| format!("'{v}': expected latest, best or a version number"))
            }
        }
    }
}

impl std::fmt::Display for Follow {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Follow::Latest => write!(f, "latest"),
            Follow::Best => write!(f, "best"),
            Follow::Version(v) => write!(f, "{v}"),
        }
    }
}

/// What became of an offered model.
#[derive(Debug, PartialEq)]
pub enum Offer {
    /// It drives from the next frame on.
    Taken(u64),
    /// It passed the checks but is not one to drive (older, or not the followed version).
    Skipped(u64),
    /// It failed a check; the car keeps the model it has.
    Refused(String),
}

/// The model that drives, and what was refused.
#[derive(Default)]
pub struct ModelSlot {
    current: ArcSwapOption<VerifiedModel>,
    refused: AtomicU64,
    swaps: AtomicU64,
    last_refusal: Mutex<String>,
}

/// Make the calling thread a background one (Linux niceness 19): a model's decode, checksum
/// and load take about 200 ms of CPU, and on a car's few cores they must never hold back the
/// thread that answers frames (the frame period is 66 ms). The kernel still gives the loader
/// every cycle the drive loop leaves idle.
pub fn background_thread() -> Result<(), PriorityError> {
    thread_priority::set_current_thread_priority(thread_priority::ThreadPriority::Min).map_err(PriorityError)
}

/// The loader thread's priority could not be lowered (the system's reason).
#[derive(Debug, thiserror::Error)]
#[error("lowering the loader thread's priority: {0:?}")]
pub struct PriorityError(thread_priority::Error);

/// Why a frame got no command (the car keeps its last one until the watchdog's).
#[derive(Debug, thiserror::Error)]
pub enum BadFrame {
    /// The message is not an `EvoSensorMsg` in the car's layout.
    #[error(transparent)]
    Message(#[from] ros::CdrError),
    /// Its images or LiDAR values are not what the model takes (the message names which).
    #[error(transparent)]
    Input(#[from] FrameError),
    /// The model chose an action outside its action space.
    #[error("model v{version} chose {choice:?} outside its action space")]
    OutsideActions {
        /// The model's policy version.
        version: u64,
        /// What it chose.
        choice: Choice,
    },
}

impl ModelSlot {
    /// The model driving now.
    pub fn current(&self) -> Option<Arc<VerifiedModel>> {
        self.current.load_full()
    }

    /// Drive no model (throttle 0) until the next is taken: the car was assigned another job.
    pub fn clear(&self) {
        self.current.store(None);
    }

    /// Verify a model and, when it is one to follow, make it the one that drives.
    pub fn offer(
        &self,
        parts: ModelParts,
        trust: &TrustedKeys,
        car: &CarConfig,
        source: &str,
        follow: &Follow,
    ) -> Offer {
        self.consider(verify(parts, trust, car, source), source, follow)
    }

    /// Offer a model imported from DeepRacer's archive named `name` (unsigned: taken only if
    /// `car.toml` trusts the name), as [`ModelSlot::offer`] does.
    pub fn offer_import(&self, parts: ModelParts, name: &str, car: &CarConfig, source: &str) -> Offer {
        self.consider(crate::verify::verify_import(parts, name, car, source), source, &Follow::Latest)
    }

    fn consider(&self, verified: Result<VerifiedModel, Refusal>, source: &str, follow: &Follow) -> Offer {
        let m = match verified {
            Ok(m) => m,
            Err(why) => {
                let why = why.to_string();
                self.refused.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(source, "model refused: {why}");
                if let Ok(mut l) = self.last_refusal.lock() {
                    *l = why.clone();
                }
                return Offer::Refused(why);
            }
        };
        let v = m.version;
        let now = self.current().map(|c| c.version);
        let take = match follow {
            Follow::Latest => now.is_none_or(|n| v > n),
            Follow::Best => now != Some(v),
            Follow::Version(want) => v == *want && now != Some(v),
        };
        if !take {
            return Offer::Skipped(v);
        }
        tracing::info!(version = v, source, key = %m.key, previous = ?now, "model verified; driving it from the next frame");
        self.current.store(Some(Arc::new(m)));
        self.swaps.fetch_add(1, Ordering::Relaxed);
        Offer::Taken(v)
    }

    /// Models refused so far, and the latest reason.
    pub fn refusals(&self) -> (u64, String) {
        (self.refused.load(Ordering::Relaxed), self.last_refusal.lock().map(|l| l.clone()).unwrap_or_default())
    }

    /// Models taken so far.
    pub fn swaps(&self) -> u64 {
        self.swaps.load(Ordering::Relaxed)
    }
}

/// The car's state, as status and logs name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CarState {
    /// No verified model yet: throttle 0.
    NoModel,
    /// A model, but no camera frame yet.
    WaitingForFrames,
    /// Driving with a model.
    Driving,
    /// Frames stopped for longer than the watchdog allows: throttle 0.
    FramesStopped,
    /// The e-stop is held: throttle 0.
    EStop,
}

impl CarState {
    /// The name in status messages.
    pub fn name(self) -> &'static str {
        match self {
            CarState::NoModel => "no model",
            CarState::WaitingForFrames => "waiting for frames",
            CarState::Driving => "driving",
            CarState::FramesStopped => "frames stopped",
            CarState::EStop => "e-stop",
        }
    }
}

/// One command for the car.
#[derive(Clone, Debug, PartialEq)]
pub struct Command {
    /// The ratios.
    pub servo: Servo,
    /// The header of the frame it answers (empty for the watchdog's).
    pub correlation: Header,
    /// The model version that chose it (`None`: a stop).
    pub version: Option<u64>,
}

impl Command {
    fn stop(correlation: Header) -> Command {
        Command { servo: Servo { angle: 0.0, throttle: 0.0 }, correlation, version: None }
    }
}

/// Latency samples (the last 1024) and their percentiles.
#[derive(Default)]
struct Samples(VecDeque<f64>);

impl Samples {
    fn push(&mut self, ms: f64) {
        if self.0.len() == 1024 {
            self.0.pop_front();
        }
        self.0.push_back(ms);
    }
    fn percentile(&self, p: f64) -> f64 {
        if self.0.is_empty() {
            return 0.0;
        }
        let mut v: Vec<f64> = self.0.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
    }
}

/// The figures of a car's status message.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Figures {
    /// Frames handled in the last second.
    pub frames_per_s: f64,
    /// Inference latency percentiles (ms).
    pub inference_ms: (f64, f64),
    /// Frame-to-command percentiles (ms).
    pub frame_to_command_ms: (f64, f64),
    /// Frames handled.
    pub frames: u64,
    /// Frames that did not decode.
    pub bad_frames: u64,
    /// Commands made.
    pub commands: u64,
}

/// The car's loop (see the module documentation).
pub struct Driver {
    car: CarConfig,
    slot: Arc<ModelSlot>,
    scratch: Scratch,
    obs: Vec<f32>,
    last_frame: Option<Instant>,
    last_stop: Option<Instant>,
    state: CarState,
    estop: bool,
    inference: Samples,
    f2c: Samples,
    recent: VecDeque<Instant>,
    figures: Figures,
}

impl Driver {
    /// A driver for `car` taking its models from `slot`.
    pub fn new(car: CarConfig, slot: Arc<ModelSlot>) -> Driver {
        if slot.current().is_none() {
            tracing::info!(car = %car.id, "no verified model yet: throttle 0 until one is loaded");
        }
        Driver {
            car,
            slot,
            scratch: Scratch::default(),
            obs: Vec::new(),
            last_frame: None,
            last_stop: None,
            state: CarState::NoModel,
            estop: false,
            inference: Samples::default(),
            f2c: Samples::default(),
            recent: VecDeque::new(),
            figures: Figures::default(),
        }
    }

    /// The state now.
    pub fn state(&self) -> CarState {
        if self.estop {
            CarState::EStop
        } else if self.last_frame.is_none() {
            if self.slot.current().is_some() { CarState::WaitingForFrames } else { CarState::NoModel }
        } else {
            self.state
        }
    }

    fn set_state(&mut self, s: CarState) {
        if s != self.state {
            tracing::info!(car = %self.car.id, from = self.state.name(), to = s.name(), "car state");
            self.state = s;
        }
    }

    /// Hold (true) or release (false) the e-stop.
    pub fn set_estop(&mut self, on: bool) {
        if on != self.estop {
            tracing::warn!(car = %self.car.id, held = on, "e-stop");
        }
        self.estop = on;
        if on {
            self.set_state(CarState::EStop);
        }
    }

    /// One `EvoSensorMsg` (CDR bytes, the car's layout): the command that answers it.
    pub fn frame(&mut self, bytes: &[u8], now: Instant) -> Result<Command, BadFrame> {
        let layout = match self.car.layout {
            Layout::Community => ros::Layout::Community,
            Layout::Aws => ros::Layout::Aws,
        };
        let sensors = match ros::decode_sensor(bytes, layout) {
            Ok(f) => f,
            Err(e) => {
                self.figures.bad_frames += 1;
                return Err(e.into());
            }
        };
        self.last_frame = Some(now);
        self.figures.frames += 1;
        self.recent.push_back(now);
        while self.recent.front().is_some_and(|t| now.duration_since(*t) > Duration::from_secs(1)) {
            self.recent.pop_front();
        }
        let correlation = sensors.frames.first().map(|f| f.header().clone()).unwrap_or_default();
        let model = self.slot.current();
        let command = match (&model, self.estop) {
            (_, true) => Command::stop(correlation),
            (None, false) => {
                self.set_state(CarState::NoModel);
                Command::stop(correlation)
            }
            (Some(m), false) => {
                let (h, w, c) = m.input;
                if let Err(e) = preprocess(&sensors.frames, h, w, c, &mut self.obs)
                    .and_then(|()| add_lidar(m.lidar, &sensors.lidar, &mut self.obs))
                {
                    self.figures.bad_frames += 1;
                    return Err(e.into());
                }
                let t0 = Instant::now();
                let choice = m.policy.mode(&self.obs, &mut self.scratch);
                self.inference.push(t0.elapsed().as_secs_f64() * 1e3);
                let action = match choice {
                    Choice::Discrete(i) => m.metadata.action_space.discrete(i),
                    Choice::Continuous(u) => m.metadata.action_space.scale([u[0] as f64, u[1] as f64]),
                };
                let Some(action) = action else {
                    return Err(BadFrame::OutsideActions { version: m.version, choice });
                };
                let (angle, throttle) = m.servo.to_servo(action);
                self.set_state(CarState::Driving);
                Command { servo: Servo { angle, throttle }, correlation, version: Some(m.version) }
            }
        };
        self.figures.commands += 1;
        Ok(command)
    }

    /// The watchdog, called often (every few milliseconds): throttle 0 when frames stopped for
    /// longer than `watchdog_ms` (and again every `watchdog_ms` while they stay away).
    pub fn tick(&mut self, now: Instant) -> Option<Command> {
        let limit = Duration::from_millis(self.car.watchdog_ms);
        let last = self.last_frame?;
        if now.duration_since(last) < limit {
            if self.state == CarState::FramesStopped {
                self.set_state(if self.slot.current().is_some() { CarState::Driving } else { CarState::NoModel });
            }
            return None;
        }
        if self.state != CarState::FramesStopped && !self.estop {
            self.set_state(CarState::FramesStopped);
            self.last_stop = None;
        }
        if self.last_stop.is_none_or(|t| now.duration_since(t) >= limit) {
            self.last_stop = Some(now);
            self.figures.commands += 1;
            return Some(Command::stop(Header::default()));
        }
        None
    }

    /// Record a frame's arrival-to-publication time (the shell measures it).
    pub fn record_frame_to_command(&mut self, d: Duration) {
        self.f2c.push(d.as_secs_f64() * 1e3);
    }

    /// The figures for a status message.
    pub fn figures(&self) -> Figures {
        Figures {
            frames_per_s: self.recent.len() as f64,
            inference_ms: (self.inference.percentile(0.5), self.inference.percentile(0.99)),
            frame_to_command_ms: (self.f2c.percentile(0.5), self.f2c.percentile(0.99)),
            ..self.figures.clone()
        }
    }
}
