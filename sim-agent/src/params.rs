//! DeepRacer's reward `params` (simapp's `agent_ctrl/constants.py::RewardParam`, filled in
//! `agent_ctrl/utils.py::set_reward_and_metrics`), computed from a car pose.
//!
//! Every key DeepRacer's `RewardParam` defines is here with its meaning: `x`/`y` are the
//! point 0.14 m ahead of the car origin, `speed`/`steering_angle` are the *commanded* action,
//! `steps` counts the `prepare` step, `progress` is relative to the episode's start.
//! The object keys keep DeepRacer's defaults: Paddock has no obstacles or bot cars yet.

use policy::Action;
use tracks::{P2, Track, compute_progress, wrap_degrees};

/// The reference point's offset ahead of the car origin (`RELATIVE_POSITION_OF_FRONT_OF_CAR`).
pub const FRONT_OFFSET: f64 = 0.14;

/// One step's reward `params`. `waypoints` is not stored here: it is the track's centre line,
/// handed to reward functions once per episode.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RewardParams {
    /// All four wheel centres inside the road polygon.
    pub all_wheels_on_track: bool,
    /// Reference point x (m).
    pub x: f64,
    /// Reference point y (m).
    pub y: f64,
    /// Car yaw in degrees, (-180, 180], 0 = +x, counter-clockwise positive.
    pub heading: f64,
    /// Distance from the reference point to the centre line (m).
    pub distance_from_center: f64,
    /// Left of the centre line relative to the driving direction.
    pub is_left_of_center: bool,
    /// All four wheels off the road (the off-track rule fired).
    pub is_offtrack: bool,
    /// Crashed into an object (always false: no objects yet).
    pub is_crashed: bool,
    /// Driving the track in reverse direction (`REVERSE_DIR`), not "going backwards".
    pub is_reversed: bool,
    /// Percentage of the lap done since the episode's start.
    pub progress: f64,
    /// Commanded speed (m/s).
    pub speed: f64,
    /// Commanded steering angle (degrees, + = left).
    pub steering_angle: f64,
    /// Steps so far in the episode, the `prepare` step included (a float, as in DeepRacer).
    pub steps: f64,
    /// Local track width (m).
    pub track_width: f64,
    /// Centre-line length (m).
    pub track_length: f64,
    /// `[prev, next]` waypoint indices.
    pub closest_waypoints: [usize; 2],
    /// `[prev, next]` object indices (default `[0, 0]`).
    pub closest_objects: [usize; 2],
    /// Whether the next object is in the camera's view (default false).
    pub object_in_camera: bool,
    /// Distance along the centre line from the start line (m) (`ndist * track_length`).
    pub projection_distance: f64,
    /// Simulation time (s): the environment's clock, which runs on across its episodes as
    /// Gazebo's `/clock` does (DeepRacer's `sim_time` param and sim-trace `tstamp`).
    pub sim_time: f64,
}

/// A car pose in the plane: the chassis origin and yaw (radians).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Origin x (m).
    pub x: f64,
    /// Origin y (m).
    pub y: f64,
    /// Yaw (radians).
    pub yaw: f64,
}

impl Pose {
    /// The reward reference point, 0.14 m ahead of the origin.
    pub fn front(&self) -> P2 {
        P2::new(self.x + FRONT_OFFSET * self.yaw.cos(), self.y + FRONT_OFFSET * self.yaw.sin())
    }
}

/// Where the episode stands, as the params need it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeClock {
    /// Normalised distance of the episode's start.
    pub start_ndist: f64,
    /// Progress at the previous step (0 after a lap completes).
    pub prev_progress: f64,
    /// Steps counted so far including this one.
    pub steps: u64,
    /// Simulation time (s): the environment's clock, which runs on across its episodes as
    /// Gazebo's `/clock` does (DeepRacer's `sim_time` param and sim-trace `tstamp`).
    pub sim_time: f64,
}

/// Compute every params key for a pose. `wheels` are the four wheel centres.
pub fn compute_params(
    track: &Track,
    pose: &Pose,
    wheels: &[[f64; 2]; 4],
    action: Action,
    clock: &EpisodeClock,
) -> RewardParams {
    let front = pose.front();
    let q = track.query(front);
    let progress = compute_progress(q.ndist - clock.start_ndist, clock.prev_progress);
    let on = wheels.iter().filter(|w| track.on_road(P2::new(w[0], w[1]))).count();
    RewardParams {
        all_wheels_on_track: on == 4,
        x: front.x,
        y: front.y,
        heading: wrap_degrees(pose.yaw.to_degrees()),
        distance_from_center: q.distance_from_center,
        is_left_of_center: q.is_left_of_center,
        is_offtrack: on == 0,
        is_crashed: false,
        is_reversed: track.direction() == tracks::Direction::Reversed,
        progress,
        speed: action.speed,
        steering_angle: action.steering_angle,
        steps: clock.steps as f64,
        track_width: q.track_width,
        track_length: track.length(),
        closest_waypoints: q.closest_waypoints,
        closest_objects: [0, 0],
        object_in_camera: false,
        projection_distance: q.ndist * track.length(),
        sim_time: clock.sim_time,
    }
}
