//! Where a sim agent's policy acts. On the GPU (lavapipe in the suite), collecting and in
//! evaluation trials, against the same on faer: the same seed gives the same episodes, actions
//! for actions, their log-probabilities to float tolerance (and no values: both act with the
//! policy tower alone), and the same trials. On faer, a camera network acts on the
//! environments' threads, and gives the episodes and trials it gives on one, bit for bit; and
//! several worlds' trials stepped as one batch are each world's trials alone.

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

/// Issue 33: a collection acted on the GPU is the one acted on faer.
#[test]
fn a_collection_acted_on_the_gpu_is_the_one_acted_on_faer() {
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
        for (p, q) in x.logp.iter().zip(&y.logp) {
            assert!((p - q).abs() <= 1e-4 * p.abs().max(1.0), "faer {p}, GPU {q}");
        }
        assert!(x.values.iter().chain(&y.values).all(|v| *v == 0.0), "values computed while acting");
    }
}

/// Issue 33: evaluation trials acted on the GPU (as a worker with `--device gpu` runs them) are the
/// trials acted on faer: the same progress, lap times and steps.
#[test]
fn evaluation_trials_on_the_gpu_are_the_ones_on_faer() {
    use sim_agent::rollout::{EvalPlan, evaluate};
    let gpu = Arc::new(gpu::Gpu::open(gpu::DeviceChoice::Gpu).unwrap().expect("`gpu` opens lavapipe"));
    let meta = ModelMetadata::default_state_vector();
    let spec = EnvSpec::from_world(&tracks::world("Oval_track").unwrap(), tracks::Direction::Forward);
    let cfg = Arc::new(SimConfig::default());
    let obs = collector(&meta).vec_env().obs_dim();
    let model = Arc::new(ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9)));
    let rules = sim_agent::EvalRules::default();
    let space = &meta.action_space;
    let plan =
        EvalPlan { rules, count: 3, seed: 4, threads: 1, all_frames: false, spread: false, give_up_after_misses: None };
    let cpu = evaluate(&model, space, &spec, &cfg, &plan, None).unwrap();
    let mut acting = gpu::Acting::new(gpu);
    let on_gpu = evaluate(&model, space, &spec, &cfg, &plan, Some(&mut acting)).unwrap();
    assert!(cpu.iter().map(|t| t.steps).sum::<u64>() > 30);
    for (a, b) in cpu.iter().zip(&on_gpu) {
        assert_eq!((a.progress, a.lap_time, a.steps, a.off_track), (b.progress, b.lap_time, b.steps, b.off_track));
    }
}

/// Issue 55: a camera policy collects, and evaluates when told to spread, on every thread the
/// environments have (its convolutions split the samples), and the episodes and trials are those
/// acted on one thread, bit for bit; the state vector's small network stays on one thread.
#[test]
fn a_camera_policy_acts_on_the_environments_threads_and_gives_the_same_episodes() {
    let meta = ModelMetadata::default_camera();
    let mut cfg = SimConfig::default();
    cfg.observation.kind = sim_agent::config::ObservationKind::Camera;
    let cfg = Arc::new(cfg);
    let spec = EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), tracks::Direction::Forward);
    let vec = |threads| {
        VecEnv::new(vec![spec.clone(); 4], cfg.clone(), 5, RewardFn::Builtin(BuiltinReward::CenterLine), threads)
            .expect("lavapipe or a GPU")
    };
    let (one, two) = (vec(1), vec(2));
    assert_eq!((one.acting_par().degree(), two.acting_par().degree()), (1, 2), "a camera network splits");
    let state = VecEnv::new(
        vec![spec.clone(); 4],
        Arc::new(SimConfig::default()),
        5,
        RewardFn::Builtin(BuiltinReward::CenterLine),
        2,
    )
    .unwrap();
    assert_eq!(state.acting_par().degree(), 1, "the state vector's network acts on one thread");
    let model = Arc::new(ActorCritic::new(&meta, one.obs_dim(), &mut rand_chacha::ChaCha8Rng::seed_from_u64(3)));
    let (mut a, mut b) =
        (Collector::new(one, meta.action_space.clone(), 5), Collector::new(two, meta.action_space.clone(), 5));
    let (x, y) = (a.collect(&model, 0, 6).unwrap(), b.collect(&model, 0, 6).unwrap());
    assert!(x.iter().map(|t| t.choices.len()).sum::<usize>() > 20);
    for (p, q) in x.iter().zip(&y) {
        assert_eq!(p.choices, q.choices, "the same actions");
        assert_eq!(p.logp, q.logp, "the same log-probabilities, bit for bit");
        assert_eq!(p.rewards, q.rewards, "the same episodes");
    }
    // Evaluation trials spread over the threads when nothing computes beside them: the same
    // trials as on one.
    use sim_agent::rollout::{EvalPlan, evaluate};
    let trials = |threads, spread| {
        let rules = sim_agent::EvalRules::default();
        let plan =
            EvalPlan { rules, count: 2, seed: 4, threads, all_frames: false, spread, give_up_after_misses: None };
        evaluate(&model, &meta.action_space, &spec, &cfg, &plan, None).unwrap()
    };
    let (t1, t2) = (trials(1, false), trials(2, true));
    assert!(t1.iter().map(|t| t.steps).sum::<u64>() > 10);
    for (p, q) in t1.iter().zip(&t2) {
        assert_eq!((p.progress, p.lap_time, p.steps, p.off_track), (q.progress, q.lap_time, q.steps, q.off_track));
    }
}

/// Issue 55: several worlds' evaluations stepped as one batch (a worker's checks of one
/// checkpoint, `coordinator evaluate` over its worlds) give each world the trials it gets
/// evaluated alone: every trial keeps its own seed, and the policy's forward pass gives each
/// row what it gives in a smaller batch. From the state vector, bit for bit; from the camera,
/// bit for bit where a trial keeps its place in the renderer's atlas (the first world's), and
/// elsewhere the rasteriser may round a few edge pixels differently, so the batch is held to
/// giving the same bits each time it runs.
#[test]
fn a_batch_of_evaluations_gives_each_world_the_trials_it_gets_alone() {
    use sim_agent::rollout::{EvalPlan, GroupTrials, TrialResult, evaluate, evaluate_groups};
    let spec = |w: &str| EnvSpec::from_world(&tracks::world(w).unwrap(), tracks::Direction::Forward);
    let plan = |count, seed| EvalPlan {
        rules: sim_agent::EvalRules::default(),
        count,
        seed,
        threads: 2,
        all_frames: false,
        spread: true,
        give_up_after_misses: None,
    };
    let groups =
        [(spec("reinvent_base"), plan(2, 4)), (spec("reinvent_wood"), plan(3, 9)), (spec("Oval_track"), plan(1, 4))];
    // Each step's wall clock aside: the same choices, trace, frames and outcome.
    let bare = |mut t: Vec<TrialResult>| {
        for s in t.iter_mut().flat_map(|t| &mut t.log.trace) {
            s.wall_clock = 0.0;
        }
        t
    };
    let fields = |t: &[TrialResult]| t.iter().map(|t| (t.steps, t.progress)).collect::<Vec<_>>();
    for (meta, camera) in [(ModelMetadata::default_state_vector(), false), (ModelMetadata::default_camera(), true)] {
        let mut cfg = SimConfig::default();
        if camera {
            cfg.observation.kind = sim_agent::config::ObservationKind::Camera;
            cfg.camera.randomize = true;
        }
        let cfg = Arc::new(cfg);
        let obs = sim_agent::obs::obs_dim(&cfg.observation);
        let model = Arc::new(ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(3)));
        let batch = || -> Vec<GroupTrials> {
            evaluate_groups(&model, &meta.action_space, &groups, &cfg, None, &mut || true).unwrap()
        };
        let first = batch();
        assert_eq!(first.len(), 3);
        let mut steps = Vec::new();
        for (k, ((spec, plan), got)) in groups.iter().zip(&first).enumerate() {
            assert!(got.complete, "{}: every trial ran", spec.name);
            let got = bare(got.trials.clone());
            assert!(got.iter().all(|t| !t.log.choices.is_empty()));
            assert_eq!(got[0].log.frames.is_empty(), !camera, "the first trial keeps what the car saw");
            steps.extend(got.iter().map(|t| t.steps));
            if !camera || k == 0 {
                let one = EvalPlan { threads: 1, ..plan.clone() };
                let alone = bare(evaluate(&model, &meta.action_space, spec, &cfg, &one, None).unwrap());
                assert!(got == alone, "{}: {:?} batched, {:?} alone", spec.name, fields(&got), fields(&alone));
            }
        }
        // Trials of different lengths: a batch whose rows stand still once ended.
        assert!(steps.iter().min() < steps.iter().max(), "trials of {steps:?} steps");
        let again = batch();
        for (a, b) in first.into_iter().zip(again) {
            assert!(bare(a.trials) == bare(b.trials), "the batch gives the same bits each time (camera {camera})");
        }
    }
}
