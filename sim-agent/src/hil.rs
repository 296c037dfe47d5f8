//! `sim-agent car`: the simulator plays the physical car for `deploy` (hardware in the loop,
//! with no car).
//!
//! At 15 Hz it renders the front camera (or the stereo pair, when `car.toml`'s sensors say so)
//! at the car's pose and publishes it on the car's input key in the car's message layout
//! (`EvoSensorMsg`: JPEG for the community stack, raw bgr8 for the AWS one; the LiDAR's 64
//! ranges in `lidar_data` when the car has one, among the race's objects from `--set race.…`),
//! waits out the frame period for the `ServoCtrlMsg` that answers it, turns that
//! command back into an action through the inverse of `car.toml`'s mapping, and steps the
//! physics with DeepRacer's evaluation rules. Throttle 0 holds the car still (the physics is
//! not stepped): a stopped real car is not "immobilised". After `--laps` laps (or
//! `--seconds`) it stops sending frames, listens one more second to time the watchdog's stop,
//! and prints a JSON summary; every lap and episode end is a JSON line on stdout as it happens.

use anyhow::{Context, Result, bail};
use policy::car::{CarConfig, Layout, ServoMap};
use protocol::net::{self, NetCli, zenoh};
use protocol::ros::{self, CarKeys, CompressedImage, Header, Image, RawFrame, Servo, Time};
use serde_bytes::ByteBuf;
use sim_agent::BuiltinReward;
use sim_agent::camera::{Renderer, STEREO_OFFSET, View, beside};
use sim_agent::config::{CameraLidar, LidarSensor, ObservationKind, SimConfig};
use sim_agent::env::{EnvSpec, EvalRules, Mode};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};
use tracks::Direction;
use zenoh::Wait;

/// Options of `sim-agent car`.
#[derive(clap::Args, Debug)]
pub struct CarArgs {
    /// The world to drive.
    #[arg(long, default_value = "reinvent_base")]
    world: String,
    /// The car's configuration (the same file `deploy --car` reads); its mapping must pin
    /// `max_steering_deg` and `max_speed`, which the simulated car needs to invert it.
    #[arg(long)]
    car: PathBuf,
    /// Laps to complete before stopping.
    #[arg(long, default_value_t = 1)]
    laps: u32,
    /// Time limit (seconds).
    #[arg(long, default_value_t = 120.0)]
    seconds: f64,
    /// Frames per second (the physical car's camera feeds the model at 15).
    #[arg(long, default_value_t = 15.0)]
    hz: f64,
    /// Off-track resets a trial survives (DeepRacer's NUMBER_OF_RESETS).
    #[arg(long, default_value_t = 0)]
    resets: u32,
    /// The simulator's configuration (config/default.toml's keys), e.g. a race's.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override a configuration key (`key=value`, repeatable), e.g.
    /// `race.race_type=object_avoidance`.
    #[arg(long = "set")]
    sets: Vec<String>,
    #[command(flatten)]
    net: NetCli,
}

/// What the run did, printed as the last JSON line.
#[derive(serde::Serialize, Default)]
struct Summary {
    laps: u32,
    lap_times: Vec<f64>,
    frames_sent: u64,
    commands: u64,
    /// Frames sent after the first command that got no answer within their period.
    missed: u64,
    /// Which frames those were (their numbers, from 1).
    missed_frames: Vec<u64>,
    episodes: u64,
    /// Round trip: frame published → its command received (ms).
    round_trip_ms_p50: f64,
    round_trip_ms_p99: f64,
    /// Last frame → the watchdog's throttle-0 command (ms), when one came.
    watchdog_stop_ms: Option<f64>,
    max_throttle: f32,
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
}

/// Run the simulated car.
pub fn run(args: CarArgs) -> Result<()> {
    let car = CarConfig::load(&args.car)?;
    let (Some(steer), Some(speed)) = (car.mapping.max_steering_deg, car.mapping.max_speed) else {
        bail!(
            "{}: the simulated car needs mapping.max_steering_deg and mapping.max_speed pinned to invert the mapping",
            args.car.display()
        );
    };
    let map = ServoMap::with(&car.mapping, steer, speed);
    let world = tracks::world(&args.world)?;
    let spec = EnvSpec::from_world(&world, Direction::Forward);
    // The car's sensors (car.toml): the front camera or the stereo pair, and the LiDAR's 64
    // ranges when it has one (as the sensor-fusion node passes them on; `deploy` filters them
    // for the model).
    let stereo = car.sensors.iter().any(|s| s == "STEREO_CAMERAS");
    let lidar = car.sensors.iter().any(|s| s.contains("LIDAR"));
    let mut cfg: SimConfig = sim_agent::config::load_config(args.config.as_deref(), &args.sets)?;
    cfg.observation.kind = if stereo { ObservationKind::Stereo } else { ObservationKind::Camera };
    cfg.observation.camera_lidar =
        lidar.then_some(CameraLidar { sensor: LidarSensor::Lidar, sectors: 64, values: 1, clip: 1.0, first: false });
    let cfg = Arc::new(cfg);
    let rules = EvalRules { max_resets: args.resets, ..EvalRules::default() };
    let mut env = sim_agent::env::Env::new(spec.clone(), cfg, Mode::Evaluation(rules), 0, 0.0)?;
    env.reset();
    let mut renderer = Renderer::new().context("the camera renderer")?;
    let layout = match car.layout {
        Layout::Community => ros::Layout::Community,
        Layout::Aws => ros::Layout::Aws,
    };
    let keys = CarKeys::new(&car.namespace);
    let session = net::open_retrying(&args.net.args(true).as_role(protocol::secure::Role::Car))?;
    let (tx, rx) = channel::<(Servo, Option<Header>, Instant)>();
    let _sub = session
        .declare_subscriber(&keys.servo)
        .callback(move |s| {
            if let Ok((servo, corr)) = ros::decode_servo(&s.payload().to_bytes(), layout) {
                let _ = tx.send((servo, corr, Instant::now()));
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // Frames ahead of bulk data on a shared link, as a car's bridge is set to publish them
    // (zenoh-bridge-ros2dds `pub_priorities`).
    let publisher = session
        .declare_publisher(keys.sensor.clone())
        .priority(zenoh::qos::Priority::InteractiveHigh)
        .express(true)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    tracing::info!(world = %args.world, frames = %keys.sensor, commands = %keys.servo, "simulated car up");

    let period = Duration::from_secs_f64(1.0 / args.hz.max(1.0));
    let start = Instant::now();
    let mut s = Summary::default();
    let mut rtt: Vec<f64> = Vec::new();
    let mut command = Servo::default();
    let mut answered_once = false;
    let mut next = Instant::now();
    let mut k = 0u64;
    let mut last_sent = Instant::now();
    while s.laps < args.laps && start.elapsed().as_secs_f64() < args.seconds {
        k += 1;
        let p = env.pose();
        let sides: &[f64] = if stereo { &[STEREO_OFFSET, -STEREO_OFFSET] } else { &[0.0] };
        let views: Vec<View<'_>> = sides
            .iter()
            .map(|&side| View {
                track: env.track(),
                surface: spec.surface,
                lighting: spec.lighting,
                pose: beside([p.x, p.y, p.yaw], side),
                jitter: [0.0, 0.0],
                texture_seed: 0,
                objects: env.objects(),
            })
            .collect();
        let rgb = renderer.render(&views, true);
        let header = Header { stamp: Time::from_secs_f64(start.elapsed().as_secs_f64()), frame_id: k.to_string() };
        let mut frames = Vec::new();
        for rgb in rgb.chunks(rgb.len() / sides.len()) {
            frames.push(match layout {
                ros::Layout::Community => {
                    let mut jpeg = Vec::new();
                    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
                        .encode(rgb, 160, 120, image::ExtendedColorType::Rgb8)
                        .context("JPEG")?;
                    RawFrame::Compressed(CompressedImage {
                        header: header.clone(),
                        format: "jpeg".into(),
                        data: ByteBuf::from(jpeg),
                    })
                }
                ros::Layout::Aws => {
                    let bgr: Vec<u8> = rgb.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
                    RawFrame::Raw(Image {
                        header: header.clone(),
                        height: 120,
                        width: 160,
                        encoding: "bgr8".into(),
                        is_bigendian: 0,
                        step: 160 * 3,
                        data: ByteBuf::from(bgr),
                    })
                }
            });
        }
        let ranges: &[f32] = env.lidar_scan().map_or(&[], |s| &s[..]);
        let sent = Instant::now();
        last_sent = sent;
        publisher.put(ros::encode_sensor(frames, ranges, layout)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
        s.frames_sent += 1;
        // The frame period: take the commands that come; note the one that answers this frame.
        // A frame sent late (the renderer fell behind its schedule) still gets a whole period
        // for its answer: the car's lateness is not the driver's.
        next = (next + period).max(sent + period);
        let mut answered = false;
        loop {
            let left = next.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok((servo, corr, at)) => {
                    s.commands += 1;
                    command = servo;
                    let answers = match &corr {
                        Some(h) => h.frame_id == k.to_string(),
                        None => true, // the AWS layout carries no correlation: the next command answers
                    };
                    if answers && !answered {
                        answered = true;
                        answered_once = true;
                        rtt.push(at.duration_since(sent).as_secs_f64() * 1e3);
                    }
                }
                Err(_) => break,
            }
        }
        if !answered && answered_once {
            s.missed += 1;
            s.missed_frames.push(k);
            tracing::warn!(frame = k, "no command answered this frame within its period");
        }
        s.max_throttle = s.max_throttle.max(command.throttle);
        if command.throttle <= 0.0 {
            continue; // stopped: the car stands still
        }
        let action = map.to_action(command.angle, command.throttle);
        let o = env.step(action, BuiltinReward::CenterLine)?;
        if let Some(t) = o.lap_time {
            s.laps += 1;
            s.lap_times.push(t);
            println!("{}", serde_json::json!({"event": "lap", "lap": s.laps, "lap_time": t, "frame": k}));
        }
        if o.done {
            s.episodes += 1;
            println!(
                "{}",
                serde_json::json!({"event": "episode_end", "status": o.status.label(), "progress": o.progress, "frame": k})
            );
            env.reset();
        }
    }
    // Frames stop: time the watchdog from the last frame sent.
    let last = last_sent;
    let deadline = Instant::now() + Duration::from_secs(1);
    while let Ok((servo, _, at)) = rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
        if servo.throttle == 0.0 && s.watchdog_stop_ms.is_none() && at > last {
            s.watchdog_stop_ms = Some(at.duration_since(last).as_secs_f64() * 1e3);
        }
    }
    s.round_trip_ms_p50 = percentile(&mut rtt, 0.5);
    s.round_trip_ms_p99 = percentile(&mut rtt, 0.99);
    println!("{}", serde_json::to_string(&serde_json::json!({"event": "summary", "summary": s}))?);
    Ok(())
}
