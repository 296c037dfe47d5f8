//! `coordinator keys new NAME` and `coordinator cars`: signing keys for learners, and the cars
//! on the network with their status (and the e-stop).

use crate::cli::CarsArgs;
use anyhow::{Result, bail};
use policy::signature::Signer;
use protocol::net::{self, DropCounters, try_next};
use protocol::{CarControl, CarStatus, PROTOCOL_VERSION, keys};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

/// Write a new key pair.
pub fn new_keys(name: &Path) -> Result<i32> {
    let (secret, public) = Signer::generate().write_pair(name)?;
    println!("secret key: {} (give it to `learner serve --signing-key`, `train`/`up --signing-key`)", secret.display());
    println!("public key: {} (give it to each car: `deploy --trust`)", public.display());
    Ok(0)
}

/// List the cars, or hold/release one's e-stop.
pub fn cars(args: CarsArgs) -> Result<i32> {
    let session = net::open(&args.net.args(true))?;
    if let Some((car, hold)) = args.estop.as_ref().map(|c| (c, true)).or(args.release.as_ref().map(|c| (c, false))) {
        // A new session hears the cars' tokens over a few hundred milliseconds: ask until the
        // car is there or 5 s have passed.
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let alive = net::alive(&session, keys::ALL_CARS_ALIVE, Duration::from_secs(1))?;
            if alive.iter().any(|k| keys::last(k) == car) {
                break;
            }
            if Instant::now() > deadline {
                bail!(
                    "no car '{car}' on the network (alive: {:?})",
                    alive.iter().map(|k| keys::last(k)).collect::<Vec<_>>()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        let m = CarControl { protocol_version: PROTOCOL_VERSION, car_id: car.clone(), estop: hold };
        // Sent a few times: a car that misses one still gets it.
        for _ in 0..3 {
            net::put(&session, &keys::car_control(car), &m)?;
            std::thread::sleep(Duration::from_millis(100));
        }
        println!("{car}: e-stop {}", if hold { "held (throttle 0 until --release)" } else { "released" });
        return Ok(0);
    }
    let sub = net::subscribe(&session, keys::ALL_CAR_STATUS)?;
    let drops = DropCounters::default();
    let mut seen: BTreeMap<String, CarStatus> = BTreeMap::new();
    let until = Instant::now() + Duration::from_secs_f64(args.seconds.max(1.1));
    while Instant::now() < until {
        while let Some((_, s)) = try_next::<CarStatus>(&sub, &drops) {
            seen.insert(s.car_id.clone(), s);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let alive = net::alive(&session, keys::ALL_CARS_ALIVE, Duration::from_secs(1))?;
    seen.retain(|id, _| alive.iter().any(|k| keys::last(k) == id));
    if args.json {
        for s in seen.values() {
            println!("{}", serde_json::to_string(&json(s))?);
        }
        return Ok(0);
    }
    if seen.is_empty() {
        println!("no cars");
        return Ok(0);
    }
    println!(
        "{:<12} {:<12} {:>8} {:<10} {:>7} {:>14} {:>16} {:>8}  state",
        "car", "job", "model", "from", "fps", "infer p50/p99", "frame→cmd p50/p99", "refused"
    );
    for s in seen.values() {
        let model = if s.has_model { format!("v{}", s.policy_version) } else { "-".into() };
        println!(
            "{:<12} {:<12} {:>8} {:<10} {:>7.1} {:>14} {:>16} {:>8}  {}{}",
            s.car_id,
            if s.job_id.is_empty() { "(offline)" } else { &s.job_id },
            model,
            s.model_source,
            s.frames_per_s,
            format!("{:.2}/{:.2} ms", s.inference_ms_p50, s.inference_ms_p99),
            format!("{:.2}/{:.2} ms", s.frame_to_command_ms_p50, s.frame_to_command_ms_p99),
            s.refused,
            s.watchdog,
            if s.last_refusal.is_empty() { String::new() } else { format!(" (last refusal: {})", s.last_refusal) }
        );
    }
    Ok(0)
}

fn json(s: &CarStatus) -> serde_json::Value {
    serde_json::json!({
        "car": s.car_id, "job": s.job_id, "follow": s.follow, "has_model": s.has_model,
        "policy_version": s.policy_version, "source": s.model_source, "key": s.model_key,
        "frames_per_s": s.frames_per_s, "inference_ms_p50": s.inference_ms_p50,
        "inference_ms_p99": s.inference_ms_p99, "frame_to_command_ms_p50": s.frame_to_command_ms_p50,
        "frame_to_command_ms_p99": s.frame_to_command_ms_p99, "refused": s.refused,
        "last_refusal": s.last_refusal, "state": s.watchdog, "frames": s.frames,
        "commands": s.commands, "swaps": s.swaps, "bad_frames": s.bad_frames,
        "skipped_frames": s.skipped_frames,
    })
}
