//! DeepRacer's step loop and episode rules, each exercised until it fires (issue 2).

use policy::Action;
use sim_agent::config::SimConfig;
use sim_agent::driver::PurePursuit;
use sim_agent::{BuiltinReward, Env, EnvSpec, EpisodeStatus, EvalRules, Mode, StepOutcome};
use std::sync::Arc;
use tracks::{Direction, P2, Track, TrackRows};

const REWARD: BuiltinReward = BuiltinReward::CenterLine;

/// A circular loop (CCW): centre radius `r`, width `w`, `n` segments.
fn circle(r: f64, w: f64, n: usize) -> TrackRows {
    let ring = |rad: f64| {
        (0..=n)
            .map(|i| {
                let a = std::f64::consts::TAU * (i % n) as f64 / n as f64;
                P2::new(rad * a.cos(), rad * a.sin())
            })
            .collect::<Vec<_>>()
    };
    TrackRows { center: ring(r), inner: ring(r - w / 2.0), outer: ring(r + w / 2.0) }
}

fn spec_of(track: Track, friction: f64) -> EnvSpec {
    EnvSpec {
        name: "test".into(),
        track: Arc::new(track),
        friction,
        noise: None,
        surface: tracks::Surface::Asphalt,
        lighting: Default::default(),
    }
}

fn quiet() -> SimConfig {
    let mut cfg = SimConfig::default();
    cfg.noise.steering_deg = 0.0;
    cfg.noise.speed_fraction = 0.0;
    cfg
}

fn run_until_done(env: &mut Env, mut act: impl FnMut(&Env) -> Action) -> Vec<StepOutcome> {
    let mut out = Vec::new();
    for _ in 0..20_000 {
        let o = env.step(act(env), REWARD).unwrap();
        out.push(o);
        if o.done {
            return out;
        }
    }
    panic!("episode did not end");
}

fn base() -> EnvSpec {
    EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), Direction::Forward)
}

#[test]
fn first_step_is_prepare_with_zero_reward_then_rewards_flow() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Training, 1, 0.0).unwrap();
    let a = Action { steering_angle: 0.0, speed: 1.0 };
    let first = env.step(a, REWARD).unwrap();
    assert_eq!((first.status, first.reward, first.steps), (EpisodeStatus::Prepare, 0.0, 1));
    let second = env.step(a, REWARD).unwrap();
    assert_eq!(second.status, EpisodeStatus::InProgress);
    assert_eq!(second.reward, 1.0, "on the centre line the sample reward is 1");
    assert_eq!(second.steps, 2);
}

#[test]
fn driving_straight_into_a_corner_ends_off_track_in_training() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Training, 1, 0.0).unwrap();
    let steps = run_until_done(&mut env, |_| Action { steering_angle: 0.0, speed: 2.0 });
    let last = steps.last().unwrap();
    assert_eq!(last.status, EpisodeStatus::OffTrack);
    assert!(last.progress > 5.0 && last.progress < 40.0, "{last:?}");
    assert_eq!(last.reward, 1e-3, "the off-track step is still rewarded, far from the centre");
}

#[test]
fn pure_pursuit_completes_a_lap_with_progress_100_and_a_lap_time() {
    let mut env =
        Env::new(base(), Arc::new(SimConfig::default()), Mode::Evaluation(EvalRules::default()), 3, 0.0).unwrap();
    let driver = PurePursuit::default();
    let steps = run_until_done(&mut env, |e| driver.act(e));
    let last = steps.last().unwrap();
    assert_eq!(last.status, EpisodeStatus::LapComplete);
    assert_eq!(last.progress, 100.0);
    let t = last.lap_time.unwrap();
    assert!((t - last.steps as f64 / 15.0).abs() < 1e-9, "lap time is sim time: {t}");
    assert!(steps[..steps.len() - 1].iter().all(|s| s.progress < 100.0 && s.status != EpisodeStatus::OffTrack));
    // Progress climbs: never falls by more than noise.
    assert!(steps.windows(2).skip(1).all(|w| w[1].progress >= w[0].progress - 0.5));
}

#[test]
fn turning_round_ends_the_episode_as_reversed() {
    // A wide circle leaves room for a U-turn.
    let spec = spec_of(Track::new("circle", &circle(4.0, 3.0, 64), Direction::Forward), 0.9);
    let mut env = Env::new(spec, Arc::new(quiet()), Mode::Training, 1, 0.0).unwrap();
    let steps = run_until_done(&mut env, |_| Action { steering_angle: -30.0, speed: 0.6 });
    let last = steps.last().unwrap();
    assert_eq!(last.status, EpisodeStatus::Reversed, "{last:?}");
    let falling = steps.iter().rev().skip(1).take(14).collect::<Vec<_>>();
    assert!(falling.windows(2).all(|w| w[0].progress < w[1].progress), "progress fell for 15 steps");
}

#[test]
fn a_car_that_hardly_moves_is_immobilized() {
    let mut cfg = quiet();
    cfg.episode.immobilized_distance = 0.01; // the slowest speed covers 6.7 mm per step
    let mut env = Env::new(base(), Arc::new(cfg), Mode::Training, 1, 0.0).unwrap();
    let steps = run_until_done(&mut env, |_| Action { steering_angle: 0.0, speed: 0.1 });
    let last = steps.last().unwrap();
    assert_eq!(last.status, EpisodeStatus::Immobilized);
    assert!(last.steps >= 16 && last.steps < 60, "{last:?}");
}

#[test]
fn training_starts_move_round_robin_and_evaluation_starts_at_the_line() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Training, 1, 0.1).unwrap();
    let mut starts = vec![env.start_ndist()];
    for _ in 0..3 {
        env.reset();
        starts.push(env.start_ndist());
    }
    for (k, s) in starts.iter().enumerate() {
        assert!((s - (0.1 + 0.05 * k as f64)).abs() < 1e-12, "{starts:?}");
    }
    let mut eval = Env::new(base(), Arc::new(quiet()), Mode::Evaluation(EvalRules::default()), 1, 0.4).unwrap();
    eval.reset();
    assert_eq!(eval.start_ndist(), 0.0);
    // The car starts on the centre line facing along it.
    let pose = eval.pose();
    let q = eval.track().query(P2::new(pose.x, pose.y));
    assert!(q.distance_from_center < 1e-6 && q.ndist < 1e-9);
}

#[test]
fn evaluation_resets_an_off_track_car_with_a_penalty_until_resets_run_out() {
    let rules = EvalRules { max_resets: 2, penalty_s: 5.0, time_limit_s: None };
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Evaluation(rules), 1, 0.0).unwrap();
    let steps = run_until_done(&mut env, |_| Action { steering_angle: 0.0, speed: 2.0 });
    let off: Vec<&StepOutcome> = steps.iter().filter(|s| s.status == EpisodeStatus::OffTrack).collect();
    assert_eq!(off.len(), 3, "two resets, then the episode ends");
    assert!(!off[0].done && !off[1].done && off[2].done);
    assert_eq!(off[2].resets, 2);
    let last = steps.last().unwrap();
    assert!((last.sim_time - (last.steps as f64 / 15.0 + 10.0)).abs() < 1e-9, "two 5 s penalties: {last:?}");
}

#[test]
fn the_timed_race_keeps_lapping_until_time_is_up() {
    let rules = EvalRules { max_resets: 100, penalty_s: 2.0, time_limit_s: Some(25.0) };
    let mut env = Env::new(base(), Arc::new(SimConfig::default()), Mode::Evaluation(rules), 1, 0.0).unwrap();
    let driver = PurePursuit::default();
    let steps = run_until_done(&mut env, |e| driver.act(e));
    let last = steps.last().unwrap();
    assert_eq!(last.status, EpisodeStatus::TimeUp);
    assert!(last.laps >= 2, "{last:?}");
    let laps: Vec<f64> = steps.iter().filter_map(|s| s.lap_time).collect();
    assert_eq!(laps.len() as u32, last.laps);
    assert!(laps.iter().all(|&t| t > 5.0 && t < 15.0), "{laps:?}");
}

#[test]
fn the_step_cap_truncates() {
    let mut cfg = quiet();
    cfg.episode.max_steps = 20;
    let mut env = Env::new(base(), Arc::new(cfg), Mode::Training, 1, 0.0).unwrap();
    let driver = PurePursuit::default();
    let steps = run_until_done(&mut env, |e| driver.act(e));
    let last = steps.last().unwrap();
    assert!(last.truncated && last.done && last.steps == 20 && last.status == EpisodeStatus::InProgress);
}

#[test]
fn params_use_the_point_ahead_and_the_commanded_action() {
    let mut cfg = SimConfig::default();
    cfg.noise.steering_deg = 5.0;
    let mut env = Env::new(base(), Arc::new(cfg), Mode::Training, 9, 0.0).unwrap();
    let a = Action { steering_angle: 12.5, speed: 1.25 };
    env.advance(a);
    let p = env.params().clone();
    env.finish(0.0);
    let pose = env.pose();
    assert!((p.x - (pose.x + 0.14 * pose.yaw.cos())).abs() < 1e-12);
    assert!((p.y - (pose.y + 0.14 * pose.yaw.sin())).abs() < 1e-12);
    assert!((p.heading - pose.yaw.to_degrees()).abs() < 1e-9);
    assert_eq!((p.steering_angle, p.speed), (12.5, 1.25), "params report the command, not the noisy execution");
    assert_ne!(env.executed_steering_deg(), 12.5, "the car executed a noisy command");
    assert!(!p.is_reversed && p.all_wheels_on_track && !p.is_offtrack);
    assert_eq!(p.steps, 1.0);
    let rev = EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), Direction::Reversed);
    let mut env = Env::new(rev, Arc::new(quiet()), Mode::Training, 9, 0.0).unwrap();
    env.advance(a);
    assert!(env.params().is_reversed);
}

#[test]
fn a_world_can_carry_its_own_noise() {
    let mut spec = base();
    spec.noise = Some(sim_agent::config::NoiseConfig { steering_deg: 0.0, speed_fraction: 0.0 });
    // The configuration asks for a lot of noise; the world's own setting wins.
    let mut cfg = SimConfig::default();
    cfg.noise.steering_deg = 10.0;
    let mut env = Env::new(spec, Arc::new(cfg), Mode::Training, 3, 0.0).unwrap();
    env.advance(Action { steering_angle: 7.0, speed: 1.0 });
    assert_eq!(env.executed_steering_deg(), 7.0);
}

#[test]
fn commands_are_clamped_to_the_cars_limits() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Training, 1, 0.0).unwrap();
    env.advance(Action { steering_angle: 80.0, speed: 9.0 });
    assert_eq!(env.executed_steering_deg(), 30.0);
    assert_eq!(env.params().speed, 9.0, "params keep the command as given, as DeepRacer does");
}

#[test]
fn the_camera_observation_is_rendered_for_the_whole_vector() {
    let mut cfg = SimConfig::default();
    cfg.observation.kind = sim_agent::config::ObservationKind::Camera;
    let reward = sim_agent::RewardFn::Builtin(REWARD);
    let mut v = sim_agent::VecEnv::new(vec![base(); 3], Arc::new(cfg), 1, reward, 1).expect("lavapipe or a GPU");
    assert_eq!(v.obs_dim(), 160 * 120);
    let before = v.observations().to_vec();
    assert!(before.iter().all(|&p| (0.0..=255.0).contains(&p)) && before.iter().any(|&p| p > 100.0), "pixels 0-255");
    // Three starts at different places: three different pictures.
    assert_ne!(before[..19200], before[19200..38400]);
    v.step(&[Action { steering_angle: 0.0, speed: 2.0 }; 3]).unwrap();
    v.step(&[Action { steering_angle: 0.0, speed: 2.0 }; 3]).unwrap();
    assert_ne!(v.observations()[..19200], before[..19200], "the view moves with the car");
}

#[test]
fn camera_domain_randomisation_changes_the_view_between_episodes_and_only_when_asked() {
    let frames = |randomize: bool, seed: u64| {
        let mut cfg = SimConfig::default();
        cfg.observation.kind = sim_agent::config::ObservationKind::Camera;
        cfg.camera.randomize = randomize;
        let reward = sim_agent::RewardFn::Builtin(REWARD);
        let v = sim_agent::VecEnv::with_mode(
            vec![base(); 2],
            Arc::new(cfg),
            seed,
            reward,
            1,
            Mode::Evaluation(EvalRules::default()),
        )
        .unwrap();
        v.observations().to_vec()
    };
    // Evaluation: both environments sit at the start line, so only randomisation tells them apart.
    let plain = frames(false, 1);
    // The same picture, up to a few edge pixels: the two views sit in different cells of the
    // atlas, and lavapipe's rasteriser may round an edge differently per cell on some CPUs.
    let differing = plain[..19200].iter().zip(&plain[19200..]).filter(|(a, b)| a != b).count();
    assert!(differing <= 19, "no randomisation: the same picture ({differing} pixels differ)");
    let random = frames(true, 1);
    let diff: f32 = random[..19200].iter().zip(&random[19200..]).map(|(a, b)| (a - b).abs()).sum::<f32>() / 19200.0;
    assert!(diff > 2.0, "randomised environments differ: {diff}");
    assert_eq!(random, frames(true, 1), "same seed, same randomisation");
}
