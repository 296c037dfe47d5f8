//! A scripted driver: pure pursuit along the centre line, with speed from the curvature
//! ahead: laps without a trained policy (`coordinator drive`, the fidelity checks) and is the
//! benchmark's load. With a race's objects near (within 2 m ahead, or beside the car), it
//! follows the lane away from the nearest one instead.

use crate::env::Env;
use policy::Action;

/// Pure-pursuit settings.
#[derive(Clone, Debug, PartialEq)]
pub struct PurePursuit {
    /// Top speed on straights (m/s).
    pub max_speed: f64,
    /// Lowest speed in the tightest corner (m/s).
    pub min_speed: f64,
    /// Lateral acceleration the speed plan allows (m/s²).
    pub lateral_accel: f64,
    /// Look-ahead distance at rest (m); grows with speed.
    pub lookahead: f64,
}

impl Default for PurePursuit {
    fn default() -> Self {
        PurePursuit { max_speed: 2.5, min_speed: 0.8, lateral_accel: 3.0, lookahead: 0.35 }
    }
}

impl PurePursuit {
    /// The command for the env's current state.
    pub fn act(&self, env: &Env) -> Action {
        let track = env.track();
        let car = env.car_state();
        let wheelbase = env.config().car.wheelbase;
        let rear_offset = wheelbase - env.config().car.front_axle_x;
        let (c, s) = (car.yaw.cos(), car.yaw.sin());
        let rear = tracks::P2::new(car.x - rear_offset * c, car.y - rear_offset * s);
        let along = track.center().project(rear).along;
        let ld = self.lookahead + 0.2 * car.forward_speed.max(0.0);
        let len = track.length();
        // The nearest object from half a metre behind to 2 m ahead: pass it in the other lane.
        let near = env
            .objects()
            .iter()
            .map(|o| ((o.pose.along - along + len / 2.0).rem_euclid(len) - len / 2.0, o))
            .filter(|(d, _)| (-0.5..2.0).contains(d))
            .min_by(|a, b| a.0.abs().total_cmp(&b.0.abs()));
        let target = match near {
            Some((_, o)) => track.lane_pose(o.pose.lane.other(), (along + ld).rem_euclid(len)).position,
            None => track.pose_at(along + ld).0,
        };
        let (dx, dy) = (target.x - rear.x, target.y - rear.y);
        let alpha = (-s * dx + c * dy).atan2(c * dx + s * dy);
        let dist = dx.hypot(dy).max(1e-6);
        let steer = (2.0 * wheelbase * alpha.sin() / dist).atan().to_degrees();
        // Slow for the sharpest curvature within the next 1.5 m.
        let mut kappa: f64 = 0.0;
        let step = 0.25;
        let mut prev_dir = track.pose_at(along).1;
        for k in 1..=6 {
            let dir = track.pose_at(along + k as f64 * step).1;
            let turn = tracks::wrap_degrees((dir - prev_dir).to_degrees()).to_radians();
            kappa = kappa.max(turn.abs() / step);
            prev_dir = dir;
        }
        let speed = if kappa > 1e-6 { (self.lateral_accel / kappa).sqrt() } else { self.max_speed };
        Action { steering_angle: steer, speed: speed.clamp(self.min_speed, self.max_speed) }
    }
}

/// One lap of the scripted driver on `world`, driven in `direction`, with `reward`: each
/// step's `[x, y, reward]`, and how the lap ended. The console's dry run of a reward file
/// draws it on the track.
pub fn lap_rewards(
    world: &tracks::World,
    direction: tracks::Direction,
    reward: &mut crate::RewardFn,
    cfg: std::sync::Arc<crate::SimConfig>,
) -> Result<(Vec<[f64; 3]>, crate::EpisodeStatus), crate::RewardError> {
    let spec = crate::EnvSpec::from_world(world, direction);
    let mut env = Env::new(spec, cfg, crate::Mode::Evaluation(crate::EvalRules::default()), 1, 0.0)
        .map_err(|e| crate::RewardError::Load { origin: world.name.clone(), msg: e.to_string() })?;
    let driver = PurePursuit::default();
    env.reset();
    let mut out = Vec::new();
    loop {
        let action = driver.act(&env);
        env.advance(action);
        let r = env.reward_with(reward)?;
        let o = env.finish(r);
        out.push([o.trace.x, o.trace.y, o.reward]);
        if o.done {
            return Ok((out, o.status));
        }
    }
}
