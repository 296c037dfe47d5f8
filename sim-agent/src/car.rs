//! The 1/18 car in rapier3d: a chassis body on four ray-cast wheels
//! (`DynamicRayCastVehicleController`), at DeepRacer's scale and limits.
//!
//! Geometry follows DeepRacer's URDF (wheelbase 0.164 m, rear wheels at ±0.08105 m, front
//! at ±0.079601 m, wheel radius 0.035 m, chassis 5 kg + 4 × 0.34 kg wheels). The world is
//! z-up, x forward, matching the track files. Steering is set directly (DeepRacer commands
//! the hinge position), with Ackermann geometry so that the front wheels share one turn
//! centre; speed is tracked by a proportional drive force on all four wheels (DeepRacer
//! commands each wheel's velocity).
//!
//! Traction: the drive force is limited by the tyres' grip, `μ·m·g` over the four wheels.
//! The controller's own limit lets a wheel push twice its grip forwards (its friction
//! ellipse is 2:1), so without this a full-throttle command from rest would push ≈5 g at the
//! contact patches, pitch the chassis past vertical and turn the car upside down. Limited,
//! the car pitches a few degrees, reaches 4 m/s and stops in the distance of a
//! friction-limited point mass, and slides wide at full lock as the grip limit says
//! ([`crate::handling`] measures all of it).
//!
//! The rapier trap: `DynamicRayCastVehicleController`'s side-friction effective mass uses
//! `|I⁻¹(r×n)|²` where the impulse maths needs `(r×n)·I⁻¹(r×n)`. For a light chassis with a
//! small inertia that makes lateral grip far too weak. [`Car::new`] computes, per wheel,
//! the ratio between the two and sets `side_friction_stiffness` to it (times
//! [`CarParams::side_grip`]), which restores the impulse the solver meant to apply. A test
//! checks turning against a kinematic bicycle model on every surface.

use rapier3d::control::{DynamicRayCastVehicleController, WheelTuning};
use rapier3d::prelude::*;

/// Physical parameters of the car. Defaults are DeepRacer's (simapp's
/// `bundle/urdf/deepracer/deepracer_single_cam.urdf` and `agent_ctrl/constants.py`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CarParams {
    /// Distance between front and rear axles (m).
    pub wheelbase: f64,
    /// Distance from the chassis origin forward to the front axle (m).
    pub front_axle_x: f64,
    /// Lateral distance between the front wheels (m).
    pub front_track: f64,
    /// Lateral distance between the rear wheels (m).
    pub rear_track: f64,
    /// Wheel radius (m).
    pub wheel_radius: f64,
    /// Total mass (kg).
    pub mass: f64,
    /// Chassis footprint length × width (m), for its inertia.
    pub footprint: [f64; 2],
    /// Steering limit (degrees either way).
    pub max_steering_deg: f64,
    /// Speed limits (m/s).
    pub min_speed: f64,
    /// Speed limits (m/s).
    pub max_speed: f64,
    /// Time constant of the speed controller (s).
    pub speed_time_constant: f64,
    /// Multiplier on the corrected side-friction impulse (1 = the solver's own 0.2 damping).
    pub side_grip: f64,
}

impl Default for CarParams {
    fn default() -> Self {
        CarParams {
            wheelbase: 0.082311 + 0.081663,
            front_axle_x: 0.082311,
            front_track: 2.0 * 0.079601,
            rear_track: 2.0 * 0.08105,
            wheel_radius: 0.035,
            mass: 5.0 + 4.0 * 0.34055,
            footprint: [0.32352, 0.1961],
            max_steering_deg: 30.0,
            min_speed: 0.1,
            max_speed: 4.0,
            speed_time_constant: 0.08,
            side_grip: 2.0,
        }
    }
}

/// Suspension rest length (m).
const REST_LENGTH: f32 = 0.03;
/// Mass-normalised suspension stiffness (the controller multiplies by the chassis mass).
const SUSPENSION_STIFFNESS: f32 = 200.0;

/// The car's planar state, as the simulator reads it each step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CarState {
    /// Chassis origin x (m).
    pub x: f64,
    /// Chassis origin y (m).
    pub y: f64,
    /// Yaw (radians, 0 = +x, counter-clockwise positive).
    pub yaw: f64,
    /// Velocity along the car's forward axis (m/s).
    pub forward_speed: f64,
    /// Velocity across (m/s, + = left).
    pub lateral_speed: f64,
    /// Yaw rate (rad/s).
    pub yaw_rate: f64,
}

/// One car in its own small physics world (ground plane + chassis).
pub struct Car {
    world: PhysicsWorld,
    chassis: RigidBodyHandle,
    vehicle: DynamicRayCastVehicleController,
    params: CarParams,
    friction: f64,
    /// Wheel centres in the chassis frame (x, y): left rear, left front, right rear, right front.
    wheel_xy: [[f64; 2]; 4],
    ride_height: f32,
}

impl Car {
    /// A car with tyre–surface friction `friction`, physics step `dt` (s).
    pub fn new(params: &CarParams, friction: f64, dt: f64) -> Car {
        let mut world = PhysicsWorld::new();
        world.gravity = Vector::new(0.0, 0.0, -9.81);
        world.integration_parameters.dt = dt as f32;
        world.insert_collider(
            ColliderBuilder::cuboid(1000.0, 1000.0, 0.5)
                .translation(Vector::new(0.0, 0.0, -0.5))
                .friction(friction as f32),
            None,
        );
        let m = params.mass as f32;
        let (l, w, h) = (params.footprint[0] as f32, params.footprint[1] as f32, 0.08f32);
        let inertia = Vector::new(m * (w * w + h * h) / 12.0, m * (l * l + h * h) / 12.0, m * (l * l + w * w) / 12.0);
        let ride_height = REST_LENGTH + params.wheel_radius as f32 - 9.81 / (4.0 * SUSPENSION_STIFFNESS);
        let chassis = world.insert_body(
            RigidBodyBuilder::dynamic()
                .translation(Vector::new(0.0, 0.0, ride_height))
                .additional_mass_properties(MassProperties::new(Vector::ZERO, m, inertia))
                .can_sleep(false),
        );
        let wheel_xy = wheel_layout(params);
        let mut vehicle = DynamicRayCastVehicleController::new(chassis);
        vehicle.index_up_axis = 2;
        vehicle.index_forward_axis = 0;
        let radius = params.wheel_radius as f32;
        for [x, y] in wheel_xy {
            let connection = Vector::new(x as f32, y as f32, 0.0);
            // Undo the controller's effective-mass error for this wheel (see the module doc).
            let contact = connection + Vector::new(0.0, 0.0, -(REST_LENGTH + radius));
            let axle = Vector::new(0.0, -1.0, 0.0);
            let aj = contact.cross(axle);
            let iaj = Vector::new(aj.x / inertia.x, aj.y / inertia.y, aj.z / inertia.z);
            let inv_mass = 1.0 / m;
            let correction = (inv_mass + iaj.dot(iaj)) / (inv_mass + aj.dot(iaj));
            let tuning = WheelTuning {
                suspension_stiffness: SUSPENSION_STIFFNESS,
                suspension_compression: 12.0,
                suspension_damping: 14.0,
                max_suspension_travel: 0.02,
                side_friction_stiffness: correction * params.side_grip as f32,
                friction_slip: friction as f32,
                max_suspension_force: 1.0e4,
            };
            vehicle.add_wheel(connection, Vector::new(0.0, 0.0, -1.0), axle, REST_LENGTH, radius, &tuning);
        }
        Car { world, chassis, vehicle, params: params.clone(), friction, wheel_xy, ride_height }
    }

    /// Place the car at rest at (x, y) facing `yaw`.
    pub fn reset(&mut self, x: f64, y: f64, yaw: f64) {
        let body = &mut self.world.bodies[self.chassis];
        let pose =
            Pose::from_parts(Vector::new(x as f32, y as f32, self.ride_height), Rotation::from_rotation_z(yaw as f32));
        body.set_position(pose, true);
        body.set_linvel(Vector::ZERO, true);
        body.set_angvel(Vector::ZERO, true);
        for w in self.vehicle.wheels_mut() {
            w.steering = 0.0;
            w.engine_force = 0.0;
        }
    }

    /// Advance one physics step holding steering `steer_rad` (+ = left) and target `speed` (m/s).
    pub fn step(&mut self, steer_rad: f64, speed: f64) {
        let state = self.state();
        let wanted = self.params.mass * (speed - state.forward_speed) / self.params.speed_time_constant;
        // The tyres cannot push harder than their grip (see the module doc).
        let limit = self.friction * self.params.mass * 9.81;
        let drive = wanted.clamp(-limit, limit);
        // Ackermann geometry: both front wheels point at the turn centre of a bicycle model
        // steered by `steer_rad`, so neither tyre scrubs against the other.
        let (left, right) = if steer_rad.abs() < 1e-9 {
            (0.0, 0.0)
        } else {
            let radius = self.params.wheelbase / steer_rad.tan(); // signed, + = left turn
            let half = self.params.front_track / 2.0;
            ((self.params.wheelbase / (radius - half)).atan(), (self.params.wheelbase / (radius + half)).atan())
        };
        for (i, w) in self.vehicle.wheels_mut().iter_mut().enumerate() {
            match i {
                1 => w.steering = left as f32,
                3 => w.steering = right as f32,
                _ => {}
            }
            w.engine_force = (drive / 4.0) as f32;
        }
        let q = self.world.broad_phase.as_query_pipeline_mut(
            self.world.narrow_phase.query_dispatcher(),
            &mut self.world.bodies,
            &mut self.world.colliders,
            QueryFilter::exclude_dynamic().exclude_rigid_body(self.chassis),
        );
        self.vehicle.update_vehicle(self.world.integration_parameters.dt, q);
        self.world.step();
    }

    /// Roll and pitch of the chassis (radians): the angles its up axis leans sideways and
    /// forwards. A car on its wheels keeps both small.
    pub fn tilt(&self) -> (f64, f64) {
        let rot = self.world.bodies[self.chassis].rotation();
        let (fwd, left) = (rot * Vector::X, rot * Vector::Y);
        ((left.z as f64).asin(), (-(fwd.z as f64)).asin())
    }

    /// Height of the chassis origin above the ground (m).
    pub fn height(&self) -> f64 {
        self.world.bodies[self.chassis].translation().z as f64
    }

    /// The planar state of the chassis.
    pub fn state(&self) -> CarState {
        let body = &self.world.bodies[self.chassis];
        let t = body.translation();
        let fwd = body.rotation() * Vector::X;
        let yaw = (fwd.y as f64).atan2(fwd.x as f64);
        let v = body.linvel();
        let (c, s) = (yaw.cos(), yaw.sin());
        CarState {
            x: t.x as f64,
            y: t.y as f64,
            yaw,
            forward_speed: v.x as f64 * c + v.y as f64 * s,
            lateral_speed: -(v.x as f64) * s + v.y as f64 * c,
            yaw_rate: body.angvel().z as f64,
        }
    }

    /// Wheel centres in the world plane: left rear, left front, right rear, right front
    /// (DeepRacer's `LINK_NAMES` order).
    pub fn wheel_points(&self, state: &CarState) -> [[f64; 2]; 4] {
        place(&self.wheel_xy, state.x, state.y, state.yaw)
    }

    /// The car's parameters.
    pub fn params(&self) -> &CarParams {
        &self.params
    }
}

/// Wheel centres in the chassis frame: left rear, left front, right rear, right front.
pub fn wheel_layout(params: &CarParams) -> [[f64; 2]; 4] {
    let rear_x = params.front_axle_x - params.wheelbase;
    let (front, rear) = (params.front_track / 2.0, params.rear_track / 2.0);
    [[rear_x, rear], [params.front_axle_x, front], [rear_x, -rear], [params.front_axle_x, -front]]
}

/// Wheel centres in the world plane for a car origin at (x, y) with yaw `yaw`.
pub fn wheel_points_at(params: &CarParams, x: f64, y: f64, yaw: f64) -> [[f64; 2]; 4] {
    place(&wheel_layout(params), x, y, yaw)
}

fn place(layout: &[[f64; 2]; 4], x: f64, y: f64, yaw: f64) -> [[f64; 2]; 4] {
    let (c, s) = (yaw.cos(), yaw.sin());
    layout.map(|[wx, wy]| [x + c * wx - s * wy, y + s * wx + c * wy])
}
