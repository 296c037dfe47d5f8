//! PPO's update and SAC's steps with the network maths on the GPU, against the same on faer
//! from the same state: weights, Adam's moments and the figures agree to float tolerance,
//! for a discrete and a continuous head, a small camera network (conv layers) and a camera +
//! LiDAR network (two inputs); a refused update leaves the
//! GPU's state as it was; a restored state is what the GPU trains from next. On lavapipe in
//! the suite (`--device gpu` takes a software adapter), so no test needs a GPU.

use faer::Par;
use learner::{Alone, Hyperparameters, LossType, Ppo};
use policy::{ActorCritic, ModelMetadata, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

fn gpu() -> Arc<gpu::Gpu> {
    Arc::new(gpu::Gpu::open(gpu::DeviceChoice::Gpu).expect("an adapter (lavapipe)").expect("`gpu` opens one"))
}

fn state_meta(continuous: bool) -> ModelMetadata {
    let text = if continuous {
        r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":0.5,"high":2}},"action_space_type":"continuous","sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#
    } else {
        r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":0,"speed":1},{"steering_angle":30,"speed":1}],"sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#
    };
    ModelMetadata::parse(text, "meta").unwrap()
}

/// Episodes of `len` steps acted by `model` on random observations, with random rewards.
fn episodes(model: &ActorCritic, version: u64, count: usize, len: usize, rng: &mut ChaCha8Rng) -> Vec<Trajectory> {
    let os = model.obs_size();
    (0..count)
        .map(|_| {
            let obs: Vec<f32> = (0..len * os).map(|_| rng.random_range(0.0..255.0)).collect();
            let acts = model.act(&obs, len, false, rng, Par::Seq);
            Trajectory {
                obs,
                choices: acts.iter().map(|a| a.choice).collect(),
                logp: acts.iter().map(|a| a.logp).collect(),
                values: acts.iter().map(|a| a.value).collect(),
                rewards: (0..len).map(|_| rng.random_range(-1.0..2.0)).collect(),
                done: true,
                policy_version: version,
                ..Default::default()
            }
        })
        .collect()
}

fn close(what: &str, a: &[f32], b: &[f32], tol: f32) {
    assert_eq!(a.len(), b.len(), "{what}");
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
    let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(worst <= tol * scale, "{what}: GPU and faer differ by {worst} (scale {scale})");
}

fn same_learner(what: &str, g: &Ppo, c: &Ppo) {
    assert_eq!(g.version, c.version, "{what}");
    // The old policy's figures and GAE's values come from each side's own forward pass (1e-6
    // apart), so a sample at the clip range's edge can fall on either side of it: a step's
    // worth (lr) on a few weights, not more.
    close(&format!("{what}: policy tower"), &g.model.pi.params, &c.model.pi.params, 1e-3);
    close(&format!("{what}: value tower"), &g.model.v.params, &c.model.v.params, 1e-3);
    assert_eq!(g.model.pi.params.len(), c.model.pi.params.len());
    let (sg, sc) = (g.state(), c.state());
    for ((name, a), (_, b)) in sg.tensors.iter().zip(&sc.tensors) {
        // Adam's second moments are squares of gradients: compared on their own scale.
        close(&format!("{what}: {name}"), a, b, 1e-3);
    }
}

/// Issue 33: a PPO update on the GPU matches faer.
#[test]
fn a_ppo_update_on_the_gpu_matches_faer() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    // The last column: `value_epochs` (the value tower in the first epoch alone, or in both).
    let cases = [
        ("discrete state", state_meta(false), 13, 96, 32, LossType::Huber, Some(1)),
        ("continuous state", state_meta(true), 13, 96, 32, LossType::MeanSquaredError, None),
        // A camera network, DeepRacer's layer kinds at a size lavapipe runs in moments.
        ("camera", state_meta(false), 30 * 40, 48, 16, LossType::Huber, Some(1)),
        // A camera + LiDAR network: an embedder per input, then the rest.
        ("camera + lidar", state_meta(true), 12 * 16 + 8, 48, 16, LossType::MeanSquaredError, None),
    ];
    for (name, meta, obs, samples, batch_size, loss_type, value_epochs) in cases {
        let mut model = ActorCritic::new(&meta, obs, &mut rng);
        if name == "camera" {
            use policy::nn::{InputShape::Image, LayerSpec::*, Net};
            let tower = [Scale(1.0 / 255.0), Conv(8, 6, 3), Relu, Conv(12, 3, 2), Relu, Dense(24), Relu];
            let head = |n: usize| [&tower[..], &[Dense(n)]].concat();
            model.pi = Net::new(Image(30, 40, 1), &head(3), Some(0.01), &mut rng);
            model.v = Net::new(Image(30, 40, 1), &head(1), None, &mut rng);
        }
        if name == "camera + lidar" {
            use policy::nn::{InputShape::*, LayerSpec::*, Net};
            let camera = [Scale(1.0 / 255.0), Conv(4, 3, 2), Relu];
            let lidar = [Dense(6), Relu];
            let tower = |n: usize, std: Option<f32>, rng: &mut ChaCha8Rng| {
                let inputs: [(&str, _, &[_]); 2] = [("camera", Image(12, 16, 1), &camera), ("lidar", Flat(8), &lidar)];
                Net::new_multi(&inputs, &[Dense(16), Relu, Dense(n)], std, rng)
            };
            model.pi = tower(2, Some(0.01), &mut rng);
            model.v = tower(1, None, &mut rng);
        }
        let h = Hyperparameters {
            lr: 1e-3,
            num_epochs: 2,
            batch_size,
            loss_type,
            target_kl: None,
            value_warmup_updates: 1,
            value_epochs,
            ..Hyperparameters::default()
        };
        let mut cpu = Ppo::new(model.clone(), h.clone(), 0, 9, Par::Seq);
        let mut on_gpu = Ppo::new(model.clone(), h, 0, 9, Par::Seq).with_gpu(gpu.clone());
        assert!(on_gpu.device().is_some());
        // The first update holds the policy (the value tower's warm-up) and trains the value
        // tower in both epochs; two more train both, the value tower in `value_epochs`.
        for u in 0..3 {
            let trajs = episodes(&cpu.model, cpu.version, samples / 8, 8, &mut rng);
            let (a, b) = (cpu.update(&trajs).unwrap(), on_gpu.update(&trajs).unwrap());
            assert_eq!((a.gradient_steps, a.samples), (b.gradient_steps, b.samples), "{name} {u}");
            assert_eq!(a.value_steps, b.value_steps, "{name} {u}");
            let value_share = if u > 0 && value_epochs == Some(1) { 2 } else { 1 };
            assert_eq!(a.value_steps * value_share, a.gradient_steps, "{name} {u}");
            for (x, y, f) in [
                (a.policy_loss, b.policy_loss, "policy loss"),
                (a.value_loss, b.value_loss, "value loss"),
                (a.entropy, b.entropy, "entropy"),
                (a.approx_kl, b.approx_kl, "KL"),
            ] {
                assert!((x - y).abs() <= 1e-4 * x.abs().max(1e-2), "{name} update {u} {f}: faer {x}, GPU {y}");
            }
            same_learner(&format!("{name} update {u}"), &on_gpu, &cpu);
            if u == 0 {
                assert_eq!(on_gpu.model.pi.params, model.pi.params, "{name}: the warm-up holds the policy");
            }
        }
    }
}

/// Issue 55: the dual clip binds alike on the GPU and on faer: a third of a batch's samples
/// acted with e^-2.5 of their probability now (a ratio of 12), their advantages negative.
#[test]
fn the_dual_clip_binds_alike_on_the_gpu_and_on_faer() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(55);
    let model = ActorCritic::new(&state_meta(false), 13, &mut rng);
    let trajs = episodes(&model, 0, 8, 8, &mut rng);
    let mut batch = learner::ppo::make_batch_for(&trajs, &model, 0.99, Par::Seq);
    for i in (0..batch.len()).step_by(3) {
        batch.logp_old[i] -= 2.5;
        batch.adv[i] = -batch.adv[i].abs() - 0.5;
    }
    let h = |dual_clip| Hyperparameters {
        batch_size: 16,
        num_epochs: 2,
        target_kl: None,
        dual_clip,
        ..Hyperparameters::default()
    };
    let mut after = Vec::new();
    for dual in [Some(3.0), None] {
        let mut cpu = Ppo::new(model.clone(), h(dual), 0, 3, Par::Seq);
        let mut on_gpu = Ppo::new(model.clone(), h(dual), 0, 3, Par::Seq).with_gpu(gpu.clone());
        let (a, b) = (cpu.update_on_batch(&batch, 5).unwrap(), on_gpu.update_on_batch(&batch, 5).unwrap());
        let (x, y) = (a.policy_loss, b.policy_loss);
        assert!((x - y).abs() <= 1e-4 * x.abs().max(1e-2), "dual clip {dual:?}: faer {x}, GPU {y}");
        same_learner(&format!("dual clip {dual:?}"), &on_gpu, &cpu);
        after.push((cpu.model.pi.params.clone(), x));
    }
    assert_ne!(after[0].0, after[1].0, "the bound changed the steps");
    // A floored sample's loss is 3 × |A|, not its ratio (≈ 12) × |A|.
    assert!(after[0].1 < after[1].1, "the bounded loss is the smaller: {} vs {}", after[0].1, after[1].1);
}

/// Issue 33: a refused update leaves the GPU state and a restored one is trained from.
#[test]
fn a_refused_update_leaves_the_gpu_state_and_a_restored_one_is_trained_from() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(34);
    let model = ActorCritic::new(&state_meta(false), 13, &mut rng);
    let h = Hyperparameters { batch_size: 16, num_epochs: 2, target_kl: None, ..Hyperparameters::default() };
    let mut cpu = Ppo::new(model.clone(), h.clone(), 0, 3, Par::Seq);
    let mut on_gpu = Ppo::new(model.clone(), h, 0, 3, Par::Seq).with_gpu(gpu.clone());
    let trajs = episodes(&model, 0, 8, 8, &mut rng);
    cpu.update(&trajs).unwrap();
    on_gpu.update(&trajs).unwrap();
    // A NaN reward: refused, nothing changed on either side.
    let mut bad = episodes(&cpu.model, 1, 8, 8, &mut rng);
    bad[3].rewards[2] = f32::NAN;
    let before = on_gpu.state();
    let refused = on_gpu.update(&bad).unwrap_err();
    assert!(refused.to_string().contains("non-finite"), "{refused}");
    assert_eq!(on_gpu.state(), before, "the GPU's weights and moments are as they were");
    assert!(cpu.update(&bad).is_err());
    // Training goes on from there, as on faer.
    let good = episodes(&cpu.model, 1, 8, 8, &mut rng);
    cpu.update(&good).unwrap();
    on_gpu.update(&good).unwrap();
    same_learner("after a refusal", &on_gpu, &cpu);
    // A restored state (a joiner's, a resumed run's) is what the next GPU update starts from.
    let h = Hyperparameters { batch_size: 16, num_epochs: 2, target_kl: None, ..Hyperparameters::default() };
    let mut other = Ppo::new(ActorCritic::new(&state_meta(false), 13, &mut rng), h, 0, 3, Par::Seq).with_gpu(gpu);
    other.update(&good).unwrap();
    other.restore(cpu.state()).unwrap();
    let next = episodes(&cpu.model, cpu.version, 8, 8, &mut rng);
    cpu.update_planned(&next, 42, &mut Alone).unwrap();
    other.update_planned(&next, 42, &mut Alone).unwrap();
    same_learner("after a restore", &other, &cpu);
}

/// Issue 33: SAC's gradient steps on the GPU against the same steps on faer from the same state:
/// the losses of every step, then every network, optimiser moment and the temperature, for the
/// state vector (no embedder, squared error, the temperature tuned, V's target copied), a small
/// camera (a conv embedder shared by the heads, Huber, the target moved by τ = 0.25) and a
/// camera + LiDAR (networks of two inputs).
#[test]
fn sac_steps_on_the_gpu_match_faer() {
    use learner::sac::{Batch, Sac, SacGpu, SacNets, SacSettings, Tapes, TwinQ};
    use policy::nn::{InputShape, LayerSpec::*, Net};
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(332);
    let meta = ModelMetadata::parse(
        r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":1,"high":2}},"action_space_type":"continuous","training_algorithm":"sac","sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#,
        "meta",
    )
    .unwrap();
    let base = SacSettings { lr: 1e-3, ..SacSettings::for_space(&meta.action_space).unwrap() };
    let camera = |rng: &mut ChaCha8Rng| {
        let image = InputShape::Image(12, 16, 1);
        let embed = [Scale(1.0 / 255.0), Conv(4, 3, 2), Relu];
        let tower = |out: usize, rng: &mut ChaCha8Rng| {
            Net::new(image, &[&embed[..], &[Dense(16), Relu, Dense(out)]].concat(), Some(0.1), rng)
        };
        let e = Net::new(image, &embed, None, rng);
        let head = |rng: &mut ChaCha8Rng| {
            Net::new(InputShape::Flat(e.out_size() + 2), &[Dense(12), Relu, Dense(1)], None, rng)
        };
        let (q1, q2, v) = (head(rng), head(rng), tower(1, rng));
        SacNets { policy: tower(4, rng), q: TwinQ { embed: Some(e.clone()), q1, q2 }, v_target: v.clone(), v }
    };
    // Camera + LiDAR: the policy and V an embedder per input and then the rest, the critics'
    // embedder the two embedders alone (the LiDAR's values going through as they are).
    let camera_lidar = |rng: &mut ChaCha8Rng| {
        let (cam, lidar) = ([Scale(1.0 / 255.0), Conv(3, 3, 2), Relu], [Dense(6), Relu]);
        let inputs: [(&str, _, &[_]); 2] =
            [("camera", InputShape::Image(10, 12, 1), &cam), ("lidar", InputShape::Flat(5), &lidar)];
        let tower =
            |out: usize, rng: &mut ChaCha8Rng| Net::new_multi(&inputs, &[Dense(12), Relu, Dense(out)], Some(0.1), rng);
        let e = Net::new_multi(&[inputs[0], ("lidar", InputShape::Flat(5), &[])], &[], None, rng);
        let head = |rng: &mut ChaCha8Rng| {
            Net::new(InputShape::Flat(e.out_size() + 2), &[Dense(12), Relu, Dense(1)], None, rng)
        };
        let (q1, q2, v) = (head(rng), head(rng), tower(1, rng));
        SacNets { policy: tower(4, rng), q: TwinQ { embed: Some(e.clone()), q1, q2 }, v_target: v.clone(), v }
    };
    let cases = [
        ("state vector", SacNets::new(&meta, 9, &mut rng), SacSettings { target_entropy: Some(-1.0), ..base.clone() }),
        ("camera", camera(&mut rng), SacSettings { huber: true, tau: 0.25, ..base.clone() }),
        ("camera + lidar", camera_lidar(&mut rng), base.clone()),
    ];
    for (name, nets, settings) in cases {
        // Grey levels for a camera's values, LiDAR distances and state values below 1.
        let pixels = match name {
            "camera" => nets.obs_size(),
            "camera + lidar" => 10 * 12,
            _ => 0,
        };
        let per = nets.obs_size();
        let mut cpu = Sac::new(nets.clone(), settings.clone(), 5);
        let mut on_gpu = Sac::new(nets, settings, 5);
        let mut session = SacGpu::new(gpu.clone()).begin(&on_gpu, 24).unwrap();
        let mut tapes = Tapes::default();
        for step in 0..4 {
            let n = if step == 3 { 17 } else { 24 };
            let value = |k: usize, rng: &mut ChaCha8Rng| {
                if k % per < pixels { rng.random_range(0..256) as f32 } else { rng.random_range(-1.0..1.0) }
            };
            let batch = Batch {
                obs: (0..n * per).map(|k| value(k, &mut rng)).collect(),
                next_obs: (0..n * per).map(|k| value(k, &mut rng)).collect(),
                action: (0..2 * n).map(|_| rng.random_range(-0.95..0.95)).collect(),
                reward: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
                done: (0..n).map(|i| if i % 4 == 0 { 1.0 } else { 0.0 }).collect(),
            };
            let a = cpu.step(&batch, Par::Seq, &mut tapes);
            let (b, finite) = session.step(&mut on_gpu, &batch).unwrap();
            assert!(finite, "{name} step {step}");
            for (x, y, f) in [
                (a.policy, b.policy, "policy loss"),
                (a.q, b.q, "Q loss"),
                (a.v, b.v, "V loss"),
                (a.entropy, b.entropy, "entropy"),
                (a.q_mean, b.q_mean, "min Q"),
            ] {
                assert!((x - y).abs() <= 1e-4 * x.abs().max(1e-1), "{name} step {step} {f}: faer {x}, GPU {y}");
            }
            if step == 0 {
                cpu.update_target();
                session.update_target(on_gpu.settings.tau);
            }
        }
        session.finish(&mut on_gpu).unwrap();
        assert_eq!(on_gpu.steps, cpu.steps, "{name}");
        for ((what, g), (_, c)) in on_gpu.tensors().iter().zip(&cpu.tensors()) {
            close(&format!("{name}: {what}"), g, c, 1e-3);
        }
    }
}

/// Issue 33: a SAC learner made with a GPU makes its iterations there, as one on faer does.
#[test]
fn a_sac_learner_with_a_gpu_trains_as_one_on_faer() {
    use learner::algorithm::Shared;
    use learner::sac::SacTrainer;
    let meta = ModelMetadata::parse(
        r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":1,"high":2}},"action_space_type":"continuous","training_algorithm":"sac","sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#,
        "meta",
    )
    .unwrap();
    let h = Hyperparameters { batch_size: 32, sac_gradient_steps_per_transition: 0.05, ..Default::default() };
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let model = ActorCritic::new(&meta, 6, &mut rng);
    let mut cpu = SacTrainer::new(model.clone(), &meta, 6, &h, 0, 1, Par::Seq).unwrap();
    let mut on_gpu = SacTrainer::new(model, &meta, 6, &h, 0, 1, Par::Seq).unwrap().with_gpu(gpu());
    assert!(on_gpu.device().is_some() && cpu.device().is_none());
    for u in 0..2 {
        let trajs: Vec<Trajectory> = (0..3)
            .map(|_| {
                let n = 60;
                let a = |rng: &mut ChaCha8Rng| rng.random_range(-0.9..0.9);
                Trajectory {
                    world: "w".into(),
                    obs: (0..n * 6).map(|_| rng.random_range(-1.0..1.0)).collect(),
                    choices: (0..n).map(|_| policy::Choice::Continuous([a(&mut rng), a(&mut rng)])).collect(),
                    rewards: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
                    done: true,
                    ..Default::default()
                }
            })
            .collect();
        let (a, b) = (cpu.update_alone(&trajs).unwrap(), on_gpu.update_alone(&trajs).unwrap());
        assert!(a.gradient_steps > 0 && a.gradient_steps == b.gradient_steps, "update {u}");
        assert_eq!(Shared::version(&on_gpu), Shared::version(&cpu));
        for ((what, g), (_, c)) in on_gpu.state().tensors.iter().zip(&cpu.state().tensors) {
            close(&format!("update {u}: {what}"), g, c, 1e-3);
        }
        close("the published policy", &on_gpu.model().pi.params, &cpu.model().pi.params, 1e-3);
    }
}
