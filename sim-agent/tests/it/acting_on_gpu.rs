//! A sim agent's policy acting with its forward passes on the GPU (lavapipe in the suite)
//! against the same collection on faer: the same seed gives the same episodes, actions
//! for actions, their log-probabilities and values to float tolerance.

use policy::{ActorCritic, ModelMetadata};
use rand::SeedableRng;
use sim_agent::rollout::Collector;
use sim_agent::{BuiltinReward, EnvSpec, RewardFn, SimConfig, VecEnv};
use std::sync::Arc;

fn collector(meta: &ModelMetadata) -> Collector {
    let specs: Vec<EnvSpec> = ["reinvent_base", "Oval_track", "reinvent_wood", "reinvent_base"]
        .iter()
        .map(|w| EnvSpec::from_world(&tracks::world(w).unwrap(), tracks::Direction::Forward))
        .collect();
    let vec =
        VecEnv::new(specs, Arc::new(SimConfig::default()), 5, RewardFn::Builtin(BuiltinReward::CenterLine), 1).unwrap();
    Collector::new(vec, meta.action_space.clone(), 5)
}

#[test]
fn issue_33_a_collection_acted_on_the_gpu_is_the_one_acted_on_faer() {
    let gpu = Arc::new(gpu::Gpu::open(gpu::DeviceChoice::Gpu).unwrap().expect("`gpu` opens lavapipe"));
    let meta = ModelMetadata::default_state_vector();
    let mut cpu = collector(&meta);
    let obs = cpu.vec_env().obs_dim();
    let model = Arc::new(ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(8)));
    let mut on_gpu = collector(&meta).with_gpu(gpu);
    let (a, b) = (cpu.collect(&model, 0, 6).unwrap(), on_gpu.collect(&model, 0, 6).unwrap());
    assert_eq!(a.len(), b.len());
    let steps: usize = a.iter().map(|t| t.choices.len()).sum();
    assert!(steps > 50, "{steps} steps");
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.choices, y.choices, "the same actions");
        assert_eq!(x.obs, y.obs, "the same observations");
        for (p, q) in x.logp.iter().zip(&y.logp).chain(x.values.iter().zip(&y.values)) {
            assert!((p - q).abs() <= 1e-4 * p.abs().max(1.0), "faer {p}, GPU {q}");
        }
    }
}
