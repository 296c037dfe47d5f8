//! DeepRacer's step loop and episode rules, each exercised until it fires.

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
        generated: None,
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

/// Issue 12: an evaluation reset as DeepRacer's evaluation worker does it, checked row
/// by row: the `off_track` row carries the whole penalty in `pause_duration`; the car is put
/// back at the previous row's progress in the lane nearer to where it stood; it waits there
/// for `penalty × 15` `pause` rows (reward 0, steps and clock running at 15 Hz, the remaining
/// seconds counting down to 0); driving resumes with `in_progress`. When the resets run out
/// the `off_track` row ends the trial.
#[test]
fn an_evaluation_reset_waits_out_its_penalty_in_pause_rows_in_the_nearer_lane() {
    let rules = EvalRules { max_resets: 2, penalty_s: 2.0, time_limit_s: None, ..EvalRules::default() };
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Evaluation(rules), 1, 0.0).unwrap();
    let dt = 1.0 / 15.0;
    let (mut rows, mut poses) = (Vec::new(), vec![env.pose()]);
    while rows.last().is_none_or(|o: &StepOutcome| !o.done) {
        rows.push(env.step(Action { steering_angle: 0.0, speed: 2.0 }, REWARD).unwrap());
        poses.push(env.pose());
        assert!(rows.len() < 5000);
    }
    // The clock and the step counter run on through the pauses.
    for (i, w) in rows.windows(2).enumerate() {
        assert_eq!(w[1].steps, w[0].steps + 1, "row {i}");
        assert!(
            (w[1].trace.tstamp - w[0].trace.tstamp - dt).abs() < 1e-9,
            "row {i}: {} then {}",
            w[0].trace.tstamp,
            w[1].trace.tstamp
        );
    }
    let last = rows.last().unwrap();
    assert!((last.sim_time - last.steps as f64 * dt).abs() < 1e-9, "no jump in the clock: {last:?}");
    let off: Vec<usize> = (0..rows.len()).filter(|&i| rows[i].status == EpisodeStatus::OffTrack).collect();
    assert_eq!(off.len(), 3, "two resets, then the trial ends");
    assert_eq!(*off.last().unwrap(), rows.len() - 1);
    assert_eq!((last.done, last.resets, last.trace.pause_duration), (true, 2, 0.0));
    let track = env.track().clone();
    for &i in &off[..2] {
        let o = &rows[i];
        assert!(!o.done && o.trace.pause_duration == 2.0, "row {i}: {o:?}");
        // Put back at the previous row's progress, in the lane nearer to the pose before.
        let held = poses[i + 1];
        let along = rows[i - 1].progress / 100.0 * track.length();
        let (at, heading) = track.reset_pose(along, P2::new(poses[i].x, poses[i].y));
        assert!((held.x - at.x).abs() < 1e-6 && (held.y - at.y).abs() < 1e-6 && (held.yaw - heading).abs() < 1e-6);
        let q = track.query(P2::new(held.x, held.y));
        assert!((q.ndist * track.length() - along).abs() < 0.02, "at the previous row's progress");
        assert!((q.distance_from_center - q.track_width / 4.0).abs() < 0.01, "in a lane: {q:?}");
        let before = track.query(P2::new(poses[i].x, poses[i].y));
        assert_eq!(q.is_left_of_center, before.is_left_of_center, "the nearer lane");
        // 30 pause rows, held, reward 0, counting down to 0.
        for k in 1..=30 {
            let r = &rows[i + k];
            assert_eq!((r.status, r.reward, r.done), (EpisodeStatus::Pause, 0.0, false), "row {}", i + k);
            let want = (2.0 - k as f64 * dt).max(0.0);
            assert!((r.trace.pause_duration as f64 - want).abs() < 1e-5, "pause row {k}: {}", r.trace.pause_duration);
            assert_eq!(poses[i + k + 1], held, "the car is held during the pause");
        }
        let resumed = &rows[i + 31];
        assert_eq!((resumed.status, resumed.trace.pause_duration), (EpisodeStatus::InProgress, 0.0));
        assert!(resumed.reward > 0.0, "the reward function runs again");
        assert_ne!(poses[i + 32], held, "and the car drives on");
    }
}

/// Issue 12: DeepRacer holds the car in the `prepare` step (it sends zero speed and pins the
/// model), so the first row is where the car starts; Gazebo's clock runs on from one trial
/// to the next, so `tstamp` does too.
#[test]
fn the_prepare_step_holds_the_car_and_the_clock_runs_on_across_trials() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Evaluation(EvalRules::default()), 1, 0.0).unwrap();
    let driver = PurePursuit::default();
    let mut last_tstamp: Option<f64> = None;
    for trial in 0..2 {
        let start = env.pose();
        let first = env.step(Action { steering_angle: 30.0, speed: 4.0 }, REWARD).unwrap();
        assert_eq!(first.status, EpisodeStatus::Prepare);
        assert_eq!(env.pose(), start, "trial {trial}: held in prepare");
        assert!(env.car_state().forward_speed.abs() < 1e-9);
        let front = P2::new(start.x + 0.14 * start.yaw.cos(), start.y + 0.14 * start.yaw.sin());
        let want = env.track().query(front).ndist * 100.0;
        assert!(
            (first.progress - want).abs() < 1e-9,
            "trial {trial}: progress {} vs the start's {want}",
            first.progress
        );
        if let Some(t) = last_tstamp {
            assert!(
                (first.trace.tstamp - t - 1.0 / 15.0).abs() < 1e-9,
                "trial {trial}: {} after {t}",
                first.trace.tstamp
            );
        }
        let rows = run_until_done(&mut env, |e| driver.act(e));
        last_tstamp = Some(rows.last().unwrap().trace.tstamp);
        env.reset();
    }
    assert!(last_tstamp.unwrap() > 20.0, "two laps of sim time");
}

#[test]
fn the_timed_race_keeps_lapping_until_time_is_up() {
    let rules = EvalRules { max_resets: 100, penalty_s: 2.0, time_limit_s: Some(25.0), ..EvalRules::default() };
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
    env.step(a, REWARD).unwrap(); // prepare: the car is held
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
    assert_eq!(p.steps, 2.0);
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
    env.step(Action { steering_angle: 7.0, speed: 1.0 }, REWARD).unwrap(); // prepare: held
    env.advance(Action { steering_angle: 7.0, speed: 1.0 });
    assert_eq!(env.executed_steering_deg(), 7.0);
}

#[test]
fn commands_are_clamped_to_the_cars_limits() {
    let mut env = Env::new(base(), Arc::new(quiet()), Mode::Training, 1, 0.0).unwrap();
    env.step(Action { steering_angle: 80.0, speed: 9.0 }, REWARD).unwrap(); // prepare: held
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

/// Issue 31: the stereo observation is the two cameras interleaved left first.
#[test]
fn the_stereo_observation_is_the_two_cameras_interleaved_left_first() {
    use sim_agent::camera::{Renderer, STEREO_OFFSET, View, beside};
    let mut cfg = SimConfig::default();
    cfg.observation.kind = sim_agent::config::ObservationKind::Stereo;
    let reward = sim_agent::RewardFn::Builtin(REWARD);
    let v = sim_agent::VecEnv::with_mode(
        vec![base(); 2],
        Arc::new(cfg),
        1,
        reward,
        1,
        Mode::Evaluation(EvalRules::default()),
    )
    .expect("lavapipe or a GPU");
    assert_eq!(v.obs_dim(), 2 * 160 * 120);
    let world = tracks::world("reinvent_base").unwrap();
    fn view<'a>(world: &tracks::World, e: &'a sim_agent::Env, side: f64) -> View<'a> {
        let p = e.pose();
        View {
            track: e.track(),
            surface: world.surface,
            lighting: world.lighting,
            pose: beside([p.x, p.y, p.yaw], side),
            jitter: [0.0, 0.0],
            texture_seed: 0,
            objects: &[],
        }
    }
    // The same batch as the vector's (each view's place in the atlas as there).
    let e = v.envs();
    let mut r = Renderer::new().unwrap();
    let all = r.render(
        &[
            view(&world, &e[0], STEREO_OFFSET),
            view(&world, &e[0], -STEREO_OFFSET),
            view(&world, &e[1], STEREO_OFFSET),
            view(&world, &e[1], -STEREO_OFFSET),
        ],
        false,
    );
    let frames = &all[2 * 19200..];
    let obs = &v.observations()[2 * 19200..];
    let left: Vec<u8> = obs.iter().step_by(2).map(|&x| x as u8).collect();
    let right: Vec<u8> = obs.iter().skip(1).step_by(2).map(|&x| x as u8).collect();
    let differ = |a: &[u8], b: &[u8]| a.iter().zip(b).filter(|(x, y)| x != y).count();
    assert_eq!(differ(&left, &frames[..19200]), 0, "channel 0: the left camera, 0.03 m left of the axis");
    assert_eq!(differ(&right, &frames[19200..]), 0, "channel 1: the right camera");
    assert!(differ(&left, &right) > 100, "6 cm apart, the two views differ");
}

/// Issue 34: training on a generated world draws a new track every few episodes and evaluation
/// keeps to its own.
#[test]
fn training_on_a_generated_world_draws_a_new_track_every_few_episodes_and_evaluation_keeps_to_its_own() {
    let world = tracks::world("generated:3").unwrap();
    let spec = EnvSpec::from_world(&world, tracks::Direction::Forward);
    assert_eq!(spec.generated, Some(3));
    let mut cfg = SimConfig::default();
    cfg.generated.episodes_per_track = 2;
    let cfg = Arc::new(cfg);
    let mut env = Env::new(spec.clone(), cfg.clone(), Mode::Training, 1, 0.0).unwrap();
    let mut tracks_seen = vec![env.track().name().to_string()];
    for _ in 0..6 {
        env.reset();
        assert_eq!(env.spec().name, "generated:3", "the world keeps its name");
        assert!(env.track().length() > 20.0 && env.track().is_closed());
        tracks_seen.push(env.track().name().to_string());
    }
    // Episodes 1-2 on track 3, then a new track every two episodes.
    assert_eq!(tracks_seen[0], "generated:3");
    assert_eq!(tracks_seen[1], "generated:3");
    assert!(tracks_seen[2].starts_with("generated:3#") && tracks_seen[3] == tracks_seen[2], "{tracks_seen:?}");
    assert!(tracks_seen[4] != tracks_seen[2] && tracks_seen[5] == tracks_seen[4], "{tracks_seen:?}");
    // The same seed draws the same tracks.
    let mut again = Env::new(spec.clone(), cfg.clone(), Mode::Training, 1, 0.0).unwrap();
    for _ in 0..2 {
        again.reset();
    }
    assert_eq!(again.track().name(), tracks_seen[2]);
    // The new tracks are driven either way round (a generated loop turns mostly one way).
    let mut ways = std::collections::BTreeSet::new();
    for _ in 0..20 {
        again.reset();
        ways.insert(format!("{:?}", again.track().direction()));
    }
    assert_eq!(ways.len(), 2, "{ways:?}");
    // Evaluation drives track 3 every trial.
    let mut eval = Env::new(spec, cfg, Mode::Evaluation(EvalRules::default()), 1, 0.0).unwrap();
    for _ in 0..6 {
        eval.reset();
        assert_eq!(eval.track().name(), "generated:3");
    }
}
