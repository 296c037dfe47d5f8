//! DeepRacer's reward `params` (simapp's `agent_ctrl/constants.py::RewardParam`, filled in
//! `agent_ctrl/utils.py::set_reward_and_metrics`), computed from a car pose.
//!
//! Every key DeepRacer's `RewardParam` defines is here with its meaning: `x`/`y` are the
//! point 0.14 m ahead of the car origin, `speed`/`steering_angle` are the *commanded* action,
//! `steps` counts the `prepare` step, `progress` is relative to the episode's start.
//! [`object_params`] computes the object keys as the simapp does; [`compute_params`] leaves
//! DeepRacer's defaults in them, for the environment to fill when its race has objects.

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
    /// Crashed into an object: an obstacle, or a bot from behind.
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
    /// The `objects_*` keys and `closest_objects` (DeepRacer's defaults without objects).
    #[serde(flatten)]
    pub objects: ObjectParams,
    /// Whether the next object is in the camera's view (default false; see
    /// `objects::object_in_camera` for the simapp's off-by-one, kept).
    pub object_in_camera: bool,
    /// Distance along the centre line from the start line (m) (`ndist * track_length`).
    pub projection_distance: f64,
    /// Simulation time (s): the environment's clock, which runs on across its episodes as
    /// Gazebo's `/clock` does (DeepRacer's `sim_time` param and sim-trace `tstamp`).
    pub sim_time: f64,
}

/// An object on the track as the reward params see it: an obstacle or a bot car.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackObject {
    /// Its model position (m).
    pub position: P2,
    /// Its yaw (radians).
    pub heading: f64,
}

/// The params DeepRacer computes from the objects (`TrackData.get_object_reward_params`),
/// in its object order: obstacles, then bots.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct ObjectParams {
    /// `[x, y]` of each object.
    pub objects_location: Vec<[f64; 2]>,
    /// Each object's distance along the centre line from waypoint 0 of the driving direction
    /// (m, in [0, L]): not from the episode's start.
    pub objects_distance: Vec<f64>,
    /// `[previous, next]` object around the car's reference point (see
    /// `tracks::objects::closest_objects`).
    pub closest_objects: [usize; 2],
    /// Each object left of the centre line, in the driving direction.
    pub objects_left_of_center: Vec<bool>,
    /// Each object's distance from the centre line (m).
    pub objects_distance_from_center: Vec<f64>,
    /// Each object's yaw in **radians** (DeepRacer's documentation says degrees; its code
    /// gives radians); 0 for every object when there are no bots.
    pub objects_heading: Vec<f64>,
    /// The bots' speed for every object, obstacles included, when there are bots; else 0.
    pub objects_speed: Vec<f64>,
}

/// The object params for a car whose reference point is `front`, as the simapp computes
/// them: `bot_speed` is `Some(BOT_CAR_SPEED)` when the race has bots.
pub fn object_params(track: &Track, front: P2, objects: &[TrackObject], bot_speed: Option<f64>) -> ObjectParams {
    if objects.is_empty() {
        return ObjectParams::default();
    }
    let qs: Vec<tracks::TrackQuery> = objects.iter().map(|o| track.query(o.position)).collect();
    let objects_distance: Vec<f64> = objects.iter().map(|o| track.center().project(o.position).along).collect();
    let car = track.center().project(front).along;
    ObjectParams {
        objects_location: objects.iter().map(|o| [o.position.x, o.position.y]).collect(),
        closest_objects: tracks::objects::closest_objects(&objects_distance, car),
        objects_distance,
        objects_left_of_center: qs.iter().map(|q| q.is_left_of_center).collect(),
        objects_distance_from_center: qs.iter().map(|q| q.distance_from_center).collect(),
        objects_heading: objects.iter().map(|o| if bot_speed.is_some() { o.heading } else { 0.0 }).collect(),
        objects_speed: objects.iter().map(|_| bot_speed.unwrap_or(0.0)).collect(),
    }
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
        objects: ObjectParams::default(),
        object_in_camera: false,
        projection_distance: q.ndist * track.length(),
        sim_time: clock.sim_time,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 10 m square lap, counter-clockwise from (0, 0), 1 m wide: every figure below is
    /// worked out by hand.
    fn square() -> Track {
        let ring = |o: f64| -> Vec<P2> {
            [(0.0 - o, 0.0 - o), (10.0 + o, 0.0 - o), (10.0 + o, 10.0 + o), (0.0 - o, 10.0 + o), (0.0 - o, 0.0 - o)]
                .map(|(x, y)| P2::new(x, y))
                .to_vec()
        };
        // The inner border is inside the square (offset −0.5), the outer outside (+0.5).
        let rows = tracks::TrackRows { center: ring(0.0), inner: ring(-0.5), outer: ring(0.5) };
        Track::new("square", &rows, tracks::Direction::Forward)
    }

    /// Issue 31: object params are the simapp's on hand-computed states.
    #[test]
    fn object_params_are_the_simapps_on_hand_computed_states() {
        let t = square();
        let objects = [
            TrackObject { position: P2::new(5.0, 0.25), heading: 0.0 }, // edge 1, inside: left, 5 m along
            TrackObject { position: P2::new(10.25, 5.0), heading: 1.5 }, // edge 2, outside: right, 15 m
            TrackObject { position: P2::new(2.0, 9.8), heading: 3.1 },  // edge 3, inside: left, 28 m
        ];
        let p = object_params(&t, P2::new(10.0, 6.0), &objects, None);
        assert_eq!(p.objects_location, [[5.0, 0.25], [10.25, 5.0], [2.0, 9.8]]);
        for (got, want) in p.objects_distance.iter().zip([5.0, 15.0, 28.0]) {
            assert!((got - want).abs() < 1e-9, "{:?}", p.objects_distance);
        }
        assert_eq!(p.objects_left_of_center, [true, false, true]);
        for (got, want) in p.objects_distance_from_center.iter().zip([0.25, 0.25, 0.2]) {
            assert!((got - want).abs() < 1e-9, "{:?}", p.objects_distance_from_center);
        }
        // No bots: headings and speeds are 0 for every object.
        assert_eq!((p.objects_heading.clone(), p.objects_speed.clone()), (vec![0.0; 3], vec![0.0; 3]));
        // The car at 16 m (front (10, 6)): behind it the object at 15 m, ahead the one at 28 m.
        assert_eq!(p.closest_objects, [1, 2]);
        // At 32 m, past every object: the next is the first of the lap.
        assert_eq!(object_params(&t, P2::new(0.0, 8.0), &objects, None).closest_objects, [2, 0]);
        // With bots: their yaw in radians, and the bots' speed for every object.
        let b = object_params(&t, P2::new(1.0, 0.0), &objects, Some(0.5));
        assert_eq!(b.objects_heading, [0.0, 1.5, 3.1]);
        assert_eq!(b.objects_speed, [0.5; 3]);
        assert_eq!(b.closest_objects, [2, 0]);
        // No objects: DeepRacer's defaults.
        assert_eq!(object_params(&t, P2::new(1.0, 0.0), &[], None), ObjectParams::default());
    }
}
