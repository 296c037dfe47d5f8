//! The vector environment: same seed, same bits (whatever the thread count), and the
//! observation layout.

use policy::Action;
use sim_agent::config::{ObservationKind, SimConfig};
use sim_agent::driver::PurePursuit;
use sim_agent::{BuiltinReward, EnvSpec, RewardFn, VecEnv};
use std::sync::Arc;
use tracks::Direction;

fn specs(n: usize) -> Vec<EnvSpec> {
    let worlds = ["reinvent_base", "reinvent_wood", "Oval_track"];
    (0..n).map(|i| EnvSpec::from_world(&tracks::world(worlds[i % 3]).unwrap(), Direction::Forward)).collect()
}

/// Run `steps` steps with the pure-pursuit driver (a bit of steering wobble so that some
/// cars leave the road); return every observation and reward bit.
fn trace(seed: u64, threads: usize, cfg: SimConfig, steps: usize) -> (Vec<u32>, Vec<u64>) {
    let mut v =
        VecEnv::new(specs(6), Arc::new(cfg), seed, RewardFn::Builtin(BuiltinReward::CenterLine), threads).unwrap();
    let driver = PurePursuit::default();
    let (mut obs, mut rewards) = (Vec::new(), Vec::new());
    for k in 0..steps {
        let actions: Vec<Action> = v
            .envs()
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let mut a = driver.act(e);
                a.steering_angle += if (k + i) % 40 < 3 { 25.0 } else { 0.0 };
                a
            })
            .collect();
        let out = v.step(&actions).unwrap();
        rewards.extend(out.iter().map(|o| o.reward.to_bits()));
        obs.extend(v.observations().iter().map(|x| x.to_bits()));
    }
    (obs, rewards)
}

#[test]
fn same_seed_same_bits_on_one_and_two_threads() {
    let a = trace(42, 1, SimConfig::default(), 300);
    let b = trace(42, 2, SimConfig::default(), 300);
    let c = trace(43, 2, SimConfig::default(), 300);
    assert!(a == b, "one thread and two threads must agree bit for bit");
    assert!(a != c, "another seed draws other noise");
}

#[test]
fn episodes_end_and_restart_inside_the_vector() {
    let mut v =
        VecEnv::new(specs(4), Arc::new(SimConfig::default()), 1, RewardFn::Builtin(BuiltinReward::CenterLine), 2)
            .unwrap();
    let mut done = 0;
    for _ in 0..200 {
        // Full left lock: every car leaves the road soon.
        let out = v.step(&[Action { steering_angle: 30.0, speed: 2.0 }; 4]).unwrap();
        done += out.iter().filter(|o| o.done).count();
    }
    assert!(done >= 8, "cars went off and restarted: {done}");
    assert!(v.envs().iter().all(|e| e.episode() >= 3));
}

#[test]
fn observation_layout_is_as_documented() {
    let mut cfg = SimConfig::default();
    cfg.noise.steering_deg = 0.0;
    cfg.noise.speed_fraction = 0.0;
    cfg.observation.kind = ObservationKind::StateLidar;
    let v = VecEnv::new(specs(1), Arc::new(cfg.clone()), 1, RewardFn::Builtin(BuiltinReward::CenterLine), 1).unwrap();
    let k = cfg.observation.lookahead_points;
    assert_eq!(v.obs_dim(), 7 + 2 * k + cfg.observation.lidar_rays);
    let o = v.observations();
    // At rest on the centre line, facing along it.
    assert!(o[0].abs() < 1e-3, "on the centre line: {}", o[0]);
    assert!(o[1].abs() < 0.05 && (o[2] - 1.0).abs() < 1e-3, "heading along the line");
    assert_eq!(o[3], 0.0, "at rest");
    // The first look-ahead point is 0.3 m ahead of the reference point, near x = (0.14 + 0.3) / (k * 0.3).
    let x1 = o[7] * (k as f32 * 0.3);
    assert!((x1 - 0.44).abs() < 0.03 && o[8].abs() < 0.05, "first point ahead at {x1} m");
    // Lidar: the borders are 0.38 m to either side; straight ahead is clear for 2 m on the start straight.
    let lidar = &o[7 + 2 * k..];
    let n = lidar.len();
    let side = |deg: f64| lidar[((deg + 150.0) / 300.0 * (n - 1) as f64).round() as usize] * 2.0;
    assert!((side(-90.0) - 0.38).abs() < 0.06 && (side(90.0) - 0.38).abs() < 0.06, "{} {}", side(-90.0), side(90.0));
    assert!(lidar.iter().all(|&d| (0.0..=1.0).contains(&d)));
}

/// Issue 55: an environment marked to stand still is not simulated or rendered (its pose,
/// episode and observation stay as they were, its outcome is empty), and the others step
/// the same bits as when every environment steps: evaluation trials that have ended stand
/// still while the rest finish. Table: the state vector, one camera and the stereo pair.
#[test]
fn environments_that_stand_still_are_not_simulated_and_the_others_are_the_same_bits() {
    for kind in [ObservationKind::State, ObservationKind::Camera, ObservationKind::Stereo] {
        let mut cfg = SimConfig::default();
        cfg.observation.kind = kind;
        let make = || {
            VecEnv::new(specs(4), Arc::new(cfg.clone()), 7, RewardFn::Builtin(BuiltinReward::CenterLine), 2).unwrap()
        };
        let (mut all, mut some) = (make(), make());
        let dim = all.obs_dim();
        let driver = PurePursuit::default();
        let mut still: Option<(Vec<u32>, f64, u64)> = None;
        for k in 0..60 {
            let actions: Vec<Action> = all.envs().iter().map(|e| driver.act(e)).collect();
            // Environment 1 stops after 20 steps.
            let active = [true, k < 20, true, true];
            let a: Vec<(u64, bool, u64)> =
                all.step(&actions).unwrap().iter().map(|o| (o.reward.to_bits(), o.done, o.steps)).collect();
            let s: Vec<(u64, bool, u64)> = some
                .step_some(&actions, Some(&active))
                .unwrap()
                .iter()
                .map(|o| (o.reward.to_bits(), o.done, o.steps))
                .collect();
            let bits = |v: &VecEnv, i: usize| -> Vec<u32> {
                v.observations()[i * dim..(i + 1) * dim].iter().map(|x| x.to_bits()).collect()
            };
            for i in [0, 2, 3] {
                assert_eq!(a[i], s[i], "{kind:?}: environment {i} at step {k}");
                assert!(bits(&all, i) == bits(&some, i), "{kind:?}: environment {i}'s observation at step {k}");
            }
            if k < 20 {
                assert_eq!(a[1], s[1], "{kind:?}: environment 1 at step {k}, while it steps");
            } else {
                assert_eq!((s[1].1, s[1].2), (false, 0), "{kind:?}: a standing environment's outcome is empty");
                let e = &some.envs()[1];
                let now = (bits(&some, 1), e.pose().x, e.episode());
                let then = still.get_or_insert_with(|| now.clone());
                assert!(*then == now, "{kind:?}: environment 1 moved at step {k}");
            }
        }
        assert!(all.envs()[1].pose().x != some.envs()[1].pose().x, "{kind:?}: the other vector's car drove on");
    }
}
