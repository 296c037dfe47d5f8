//! PPO on the simulator learns to drive: sampled-action progress climbs from a
//! random policy's to most of a lap within a few seconds of training.

use faer::Par;
use learner::{Hyperparameters, Ppo};
use policy::{ActorCritic, ModelMetadata};
use rand::SeedableRng;
use sim_agent::config::SimConfig;
use sim_agent::obs::obs_dim;
use sim_agent::rollout::Collector;
use sim_agent::{BuiltinReward, EnvSpec, RewardFn, VecEnv};
use std::sync::Arc;
use tracks::Direction;

/// Issue 3: PPO learns to drive reinvent_base.
#[test]
fn ppo_learns_to_drive_reinvent_base() {
    let meta = ModelMetadata::default_state_vector();
    let cfg = Arc::new(SimConfig::default());
    let spec = EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), Direction::Forward);
    let vec = VecEnv::new(vec![spec; 16], cfg.clone(), 5, RewardFn::Builtin(BuiltinReward::CenterLine), 2).unwrap();
    let mut collector = Collector::new(vec, meta.action_space.clone(), 5);
    let model = ActorCritic::new(&meta, obs_dim(&cfg.observation), &mut rand_chacha::ChaCha8Rng::seed_from_u64(5));
    let mut ppo = Ppo::new(model, Hyperparameters::default(), 0, 5, Par::Seq);
    let mut progress = Vec::new();
    for _ in 0..14 {
        let trajs = collector.collect(&Arc::new(ppo.model.clone()), ppo.version, 20).unwrap();
        progress.push(trajs.iter().map(|t| t.progress).sum::<f64>() / trajs.len() as f64);
        ppo.update(&trajs).unwrap();
    }
    println!("mean progress per iteration: {progress:?}");
    let first = progress[0];
    let last = progress[progress.len() - 3..].iter().sum::<f64>() / 3.0;
    assert!(first < 30.0, "a random policy leaves the road early: {progress:?}");
    assert!(last > 55.0 && last > 2.0 * first, "PPO learns to follow the track: {progress:?}");
}
