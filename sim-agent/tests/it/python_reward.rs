//! Unmodified DeepRacer reward files in embedded CPython: every key, every failure mode.

use policy::Action;
use sim_agent::config::SimConfig;
use sim_agent::driver::PurePursuit;
use sim_agent::{BuiltinReward, Env, EnvSpec, EvalRules, Mode, RewardError, RewardFn, VecEnv};
use std::path::PathBuf;
use std::sync::Arc;
use tracks::Direction;

fn data(name: &str) -> String {
    let p: PathBuf = [env!("CARGO_MANIFEST_DIR"), "..", "tests", "data", "rewards", name].iter().collect();
    p.display().to_string()
}

fn example(name: &str) -> String {
    let p: PathBuf = [env!("CARGO_MANIFEST_DIR"), "..", "examples", "rewards", name].iter().collect();
    p.display().to_string()
}

fn base() -> EnvSpec {
    EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), Direction::Forward)
}

/// Drive one evaluation lap with the pure-pursuit driver; return the rewards or the first error.
fn lap(reward: &str) -> Result<Vec<f64>, RewardError> {
    lap_with(RewardFn::from_spec(reward)?)
}

fn lap_with(mut r: RewardFn) -> Result<Vec<f64>, RewardError> {
    let mut env =
        Env::new(base(), Arc::new(SimConfig::default()), Mode::Evaluation(EvalRules::default()), 5, 0.0).unwrap();
    let driver = PurePursuit::default();
    let mut rewards = Vec::new();
    loop {
        let o = env.step_with(driver.act(&env), &mut r)?;
        rewards.push(o.reward);
        if o.done {
            return Ok(rewards);
        }
    }
}

#[test]
fn a_file_checking_every_key_and_type_runs_a_whole_lap() {
    let rewards = lap(&data("checks_every_key.py")).unwrap();
    assert!(rewards.len() > 100);
    assert_eq!(rewards[0], 0.0, "prepare step");
    assert!(rewards[1..].iter().all(|&r| r == 1.0));
}

#[test]
fn the_python_sample_and_the_builtin_give_the_same_rewards() {
    let py = lap(&example("follow_center_line.py")).unwrap();
    let rs = lap("builtin:center_line").unwrap();
    assert_eq!(py, rs);
}

#[test]
fn a_raising_reward_stops_with_its_traceback_and_the_params() {
    let err = lap(&data("raises_key_error.py")).unwrap_err();
    let RewardError::Raised { step, traceback, params } = &err else { panic!("{err}") };
    assert_eq!(*step, 2.0, "the first rewarded step");
    assert!(traceback.contains("Traceback (most recent call last)"), "{traceback}");
    assert!(traceback.contains("raises_key_error.py\", line 3"), "{traceback}");
    assert!(traceback.contains("KeyError: 'distance_from_centre'"), "{traceback}");
    assert!(params.contains("\"distance_from_center\":"), "{params}");
}

#[test]
fn bad_return_values_stop_the_run_naming_the_value() {
    for (file, want) in [
        ("returns_nan.py", "returned NaN"),
        ("returns_string.py", "returned '1.0' (str)"),
        ("returns_none.py", "returned None (NoneType)"),
        ("too_large.py", "outside DeepRacer's limit"),
    ] {
        let err = lap(&data(file)).unwrap_err();
        assert!(matches!(err, RewardError::BadValue { .. }), "{file}: {err}");
        assert!(err.to_string().contains(want), "{file}: {err}");
    }
}

#[test]
fn files_that_cannot_load_say_why() {
    for (file, want) in [
        ("syntax_error.py", "SyntaxError"),
        ("no_function.py", "defines no reward_function(params)"),
        ("does_not_exist.py", "does_not_exist.py"),
    ] {
        let err = RewardFn::from_spec(&data(file)).err().expect(file).to_string();
        assert!(err.contains(want), "{file}: {err}");
    }
    let err = RewardFn::from_spec("builtin:nope").err().unwrap().to_string();
    assert!(err.contains("center_line"), "{err}");
}

#[test]
fn waypoints_are_built_once_per_episode() {
    let mut r = RewardFn::from_spec(&data("waypoint_lists.py")).unwrap();
    let mut env = Env::new(base(), Arc::new(SimConfig::default()), Mode::Training, 5, 0.0).unwrap();
    let mut last_per_episode = Vec::new();
    for episode in 1..=3 {
        let mut last = 0.0;
        for _ in 0..40 {
            let o = env.step_with(Action { steering_angle: 0.0, speed: 1.0 }, &mut r).unwrap();
            if o.steps > 1 {
                last = o.reward;
                assert_eq!(o.reward, episode as f64, "one list for the whole episode");
            }
            if o.done {
                break;
            }
        }
        last_per_episode.push(last);
        env.reset();
    }
    assert_eq!(last_per_episode, vec![1.0, 2.0, 3.0]);
}

#[test]
fn helper_modules_beside_the_reward_file_import() {
    let rewards = lap(&data("uses_helper.py")).unwrap();
    assert!(rewards[1..].contains(&1.0));
}

#[test]
fn python_rewards_in_the_vector_env_match_the_builtin_bit_for_bit() {
    let run = |reward: RewardFn| {
        let specs = vec![base(); 3];
        let mut v = VecEnv::new(specs, Arc::new(SimConfig::default()), 11, reward, 2).unwrap();
        let driver = PurePursuit::default();
        let mut all = Vec::new();
        for _ in 0..200 {
            let actions: Vec<Action> = v.envs().iter().map(|e| driver.act(e)).collect();
            all.extend(v.step(&actions).unwrap().iter().map(|o| o.reward.to_bits()));
        }
        all
    };
    let py = run(RewardFn::from_spec(&example("follow_center_line.py")).unwrap());
    let rs = run(RewardFn::Builtin(BuiltinReward::CenterLine));
    assert_eq!(py, rs);
}

/// Issue 8: a reward from a job compiles in memory and keeps its name.
#[test]
fn a_reward_from_a_job_compiles_in_memory_and_keeps_its_name() {
    // A job carries its reward file's text; agents and the coordinator compile it without
    // writing it anywhere, and tracebacks still name the user's file.
    let source = std::fs::read_to_string(data("raises_key_error.py")).unwrap();
    let before: Vec<_> = std::fs::read_dir(std::env::temp_dir()).unwrap().flatten().map(|e| e.file_name()).collect();
    let err = lap_with(RewardFn::from_source("raises_key_error.py", &source).unwrap()).unwrap_err();
    let RewardError::Raised { traceback, .. } = &err else { panic!("{err}") };
    assert!(traceback.contains("raises_key_error.py\", line 3"), "{traceback}");
    let after: Vec<_> = std::fs::read_dir(std::env::temp_dir()).unwrap().flatten().map(|e| e.file_name()).collect();
    assert!(after.iter().all(|f| before.contains(f) || !f.to_string_lossy().contains("paddock")), "nothing written");
    // The same rewards as the file itself.
    let sample = std::fs::read_to_string(example("follow_center_line.py")).unwrap();
    let from_text = lap_with(RewardFn::from_source("follow_center_line.py", &sample).unwrap()).unwrap();
    assert_eq!(from_text, lap(&example("follow_center_line.py")).unwrap());
    assert!(matches!(RewardFn::from_source("x.py", "builtin:center_line").unwrap(), RewardFn::Builtin(_)));
    let e = RewardFn::from_source("broken.py", "def reward_function(params)\n").err().unwrap().to_string();
    assert!(e.contains("broken.py"), "{e}");
}

/// Issue 10: a reward call has a time limit. The endless one fails with the file, the step and
/// where it was stuck; the thread then runs other rewards as before (nothing left pending).
#[test]
fn a_reward_that_never_returns_is_stopped_at_its_time_limit() {
    let limit = std::time::Duration::from_millis(200);
    let r = RewardFn::from_spec(&data("never_returns.py")).unwrap().with_time_limit(limit);
    let t = std::time::Instant::now();
    let err = lap_with(r).unwrap_err();
    assert!(t.elapsed() < std::time::Duration::from_secs(10), "took {:?}", t.elapsed());
    match &err {
        RewardError::TimedOut { file, step, limit: l, traceback, .. } => {
            assert!(file.ends_with("never_returns.py") && *l == limit && *step > 1.0, "{err}");
            assert!(
                traceback.contains("RewardTimeLimit") && traceback.contains("never_returns.py\", line"),
                "{traceback}"
            );
        }
        other => panic!("{other}"),
    }
    // Ordinary rewards on the same thread afterwards, the same as before.
    let after = lap(&example("follow_center_line.py")).unwrap();
    assert!(after.len() > 100 && after.iter().all(|r| r.is_finite()));
    // A slow but finishing reward within its limit is not disturbed.
    let slow = RewardFn::from_source(
        "slow.py",
        "import time\ndef reward_function(params):\n    time.sleep(0.002)\n    return 1.0\n",
    )
    .unwrap()
    .with_time_limit(limit);
    let rewards = lap_with(slow).unwrap();
    assert!(rewards.len() > 100 && rewards[1..].iter().all(|r| *r == 1.0), "{rewards:?}");
}

/// The same fold as `tests/data/rewards/objects_echo.py`, in Rust.
fn objects_fold(p: &sim_agent::params::RewardParams) -> f64 {
    let o = &p.objects;
    let [prev, next] = o.closest_objects;
    let mut total = 1.0
        + prev as f64
        + 10.0 * next as f64
        + 100.0 * f64::from(u8::from(p.is_crashed))
        + 1000.0 * f64::from(u8::from(p.object_in_camera));
    for i in 0..o.objects_location.len() {
        total += (i + 1) as f64
            * (o.objects_location[i][0]
                + 2.0 * o.objects_location[i][1]
                + 3.0 * o.objects_distance[i]
                + 4.0 * f64::from(u8::from(o.objects_left_of_center[i]))
                + 5.0 * o.objects_distance_from_center[i]
                + 6.0 * o.objects_heading[i]
                + 7.0 * o.objects_speed[i]);
    }
    total
}

/// Issue 31: Python rewards get every object key as DeepRacer passes them.
#[test]
fn python_rewards_get_every_object_key_as_deepracer_passes_them() {
    use sim_agent::race::{RaceConfig, RaceType};
    for race in [
        RaceConfig { race_type: RaceType::ObjectAvoidance, number_of_obstacles: 3, ..RaceConfig::default() },
        RaceConfig {
            race_type: RaceType::HeadToBot,
            number_of_bot_cars: 2,
            bot_car_speed: 0.5,
            ..RaceConfig::default()
        },
    ] {
        let cfg = Arc::new(SimConfig { race, ..SimConfig::default() });
        let rules = EvalRules { max_resets: 20, ..EvalRules::default() };
        let mut env = Env::new(base(), cfg, Mode::Evaluation(rules), 5, 0.0).unwrap();
        let mut py = RewardFn::from_spec(&data("objects_echo.py")).unwrap();
        let driver = PurePursuit::default();
        let (mut steps, mut objects) = (0, 0);
        while steps < 600 {
            env.advance(driver.act(&env));
            if env.needs_reward() {
                let want = objects_fold(env.params());
                assert_eq!(env.reward_with(&mut py).unwrap(), want, "step {steps}");
                objects = env.params().objects.objects_location.len();
            }
            let o = env.finish(0.0);
            steps += 1;
            if o.done {
                break;
            }
        }
        assert!(steps > 100 && objects > 0, "{steps} steps with {objects} objects");
    }
    // DeepRacer's own object-avoidance sample runs unchanged on an object-avoidance lap.
    let cfg = SimConfig {
        race: RaceConfig { race_type: RaceType::ObjectAvoidance, number_of_obstacles: 3, ..RaceConfig::default() },
        ..SimConfig::default()
    };
    let mut env = Env::new(base(), Arc::new(cfg), Mode::Evaluation(EvalRules::default()), 5, 0.0).unwrap();
    let mut sample = RewardFn::from_spec(&example("object_avoidance.py")).unwrap();
    let o = env.step_with(PurePursuit::default().act(&env), &mut sample).unwrap();
    assert_eq!(o.reward, 0.0, "prepare");
    let o = env.step_with(PurePursuit::default().act(&env), &mut sample).unwrap();
    assert!(o.reward > 1.0, "{}", o.reward);
}

/// Issue 34: every builtin exported as Python gives the rewards the builtin gives.
#[test]
fn every_builtin_exported_as_python_gives_the_builtins_rewards() {
    use sim_agent::race::{RaceConfig, RaceType};
    use sim_agent::race_line::{LinePlan, python_source};
    use sim_agent::validate::validate_reward;
    let world = tracks::world("reinvent_base").unwrap();
    let car = SimConfig::default().car;
    let plan = |d| LinePlan::new(&world.track(d), &car, world.surface).unwrap();
    let race_line_py = python_source(&world.name, world.surface, &plan(Direction::Forward), &plan(Direction::Reversed));
    let obstacles =
        RaceConfig { race_type: RaceType::ObjectAvoidance, number_of_obstacles: 3, ..RaceConfig::default() };
    let space = policy::ModelMetadata::default_state_vector().action_space;
    for (b, name) in BuiltinReward::ALL {
        let source = b.python_source().map(str::to_string).unwrap_or_else(|| race_line_py.clone());
        let race = if matches!(b, BuiltinReward::ObjectAvoidance | BuiltinReward::Clearance) {
            obstacles.clone()
        } else {
            RaceConfig::default()
        };
        for d in [Direction::Forward, Direction::Reversed] {
            let track = world.track(d);
            let run = |mut r: RewardFn| validate_reward(&mut r, &track, world.surface, &space, 12, &race).unwrap();
            let want = run(RewardFn::Builtin(b));
            let got = run(RewardFn::from_source(&format!("{name}.py"), &source).unwrap());
            assert_eq!(want.rewards.len(), got.rewards.len());
            for (i, (w, g)) in want.rewards.iter().zip(&got.rewards).enumerate() {
                assert!((w - g).abs() <= 1e-12 * w.abs().max(1.0), "{name} {d:?}, call {i}: built-in {w}, Python {g}");
            }
            let distinct = want.rewards.iter().map(|r| r.to_bits()).collect::<std::collections::BTreeSet<_>>();
            assert!(distinct.len() > 1, "{name} {d:?}: the states must tell rewards apart");
        }
    }
}
