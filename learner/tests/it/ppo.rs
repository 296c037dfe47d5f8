//! PPO's maths: the whole loss against finite differences, and learning a task whose answer
//! is known (it fails if the gradient's sign or the advantage is wrong).

use faer::Par;
use learner::ppo::{Batch, gae, logp_and_values, loss_and_grad, make_batch, make_batch_for, make_batch_in};
use learner::{Hyperparameters, LossType, Ppo};
use policy::{ActorCritic, Choice, ModelMetadata, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn meta(continuous: bool) -> ModelMetadata {
    let text = if continuous {
        r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":0.5,"high":2}},"action_space_type":"continuous","sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#
    } else {
        r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":0,"speed":1},{"steering_angle":30,"speed":1}],"sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#
    };
    ModelMetadata::parse(text, "meta").unwrap()
}

/// A random batch acted by `model` (so ratios start near 1) with random advantages.
fn random_batch(model: &ActorCritic, n: usize, rng: &mut ChaCha8Rng) -> Batch {
    let os = model.obs_size();
    let obs: Vec<f32> = (0..n * os).map(|_| rng.random_range(-1.0..1.0)).collect();
    let acts = model.act(&obs, n, false, rng, Par::Seq);
    Batch {
        obs_size: os,
        obs,
        choices: acts.iter().map(|a| a.choice).collect(),
        // Perturbed behaviour log-probs so that some ratios fall outside the clip range.
        logp_old: acts.iter().map(|a| a.logp + rng.random_range(-0.3..0.3)).collect(),
        adv: (0..n).map(|_| rng.random_range(-2.0..2.0)).collect(),
        returns: (0..n).map(|_| rng.random_range(-3.0..3.0)).collect(),
        values_old: acts.iter().map(|a| a.value).collect(),
    }
}

fn check_whole_loss(continuous: bool, loss_type: LossType) {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut model = ActorCritic::new(&meta(continuous), 6, &mut rng);
    // Larger head weights than the initialisation so the loss depends visibly on them.
    for p in model.pi.params.iter_mut() {
        *p *= 3.0;
    }
    if let policy::Head::Gaussian { log_std } = &mut model.head {
        *log_std = [-0.3, 0.2];
    }
    let batch = random_batch(&model, 32, &mut rng);
    let h = Hyperparameters { beta_entropy: 0.05, loss_type, ..Hyperparameters::default() };
    let idx: Vec<usize> = (0..32).collect();
    let lg = loss_and_grad(&model, &batch, &idx, &h, Par::Seq);
    let eps = 2e-3f32;
    let mut bad = Vec::new();
    let mut checked = 0;
    for tower in 0..2 {
        for _ in 0..60 {
            let len = if tower == 0 { model.pi.params.len() } else { model.v.params.len() };
            let i = rng.random_range(0..len);
            let analytic = if tower == 0 { lg.grad_pi[i] } else { lg.grad_v[i] } as f64;
            let mut m = model.clone();
            let p = if tower == 0 { &mut m.pi.params[i] } else { &mut m.v.params[i] };
            let orig = *p;
            *p = orig + eps;
            let up = loss_and_grad(&m, &batch, &idx, &h, Par::Seq).total;
            let p = if tower == 0 { &mut m.pi.params[i] } else { &mut m.v.params[i] };
            *p = orig - eps;
            let down = loss_and_grad(&m, &batch, &idx, &h, Par::Seq).total;
            let numeric = (up - down) / (2.0 * eps as f64);
            checked += 1;
            if (numeric - analytic).abs() > 2e-3 + 3e-2 * analytic.abs() {
                bad.push((tower, i, numeric, analytic));
            }
        }
    }
    if continuous {
        // log σ moves every sample's ratio at once; keep the ratios away from the clip edges
        // (behaviour = current policy) so the difference quotient crosses no kink.
        let mut batch = batch.clone();
        let acts_logp: Vec<f32> = {
            let probe = loss_and_grad(&model, &batch, &idx, &h, Par::Seq);
            assert!(probe.total.is_finite());
            let mut out = Vec::new();
            for i in 0..batch.len() {
                let os = batch.obs_size;
                let mut tape = policy::nn::Tape::default();
                model.pi.forward(&batch.obs[i * os..(i + 1) * os], 1, &mut tape, Par::Seq);
                let policy::Head::Gaussian { log_std } = &model.head else { unreachable!() };
                let Choice::Continuous(x) = batch.choices[i] else { unreachable!() };
                out.push(policy::model::gaussian_logp(tape.output(), log_std, &x));
            }
            out
        };
        batch.logp_old = acts_logp;
        let lg = loss_and_grad(&model, &batch, &idx, &h, Par::Seq);
        for d in 0..2 {
            let mut m = model.clone();
            let policy::Head::Gaussian { log_std } = &mut m.head else { unreachable!() };
            let orig = log_std[d];
            log_std[d] = orig + eps;
            let up = loss_and_grad(&m, &batch, &idx, &h, Par::Seq).total;
            let policy::Head::Gaussian { log_std } = &mut m.head else { unreachable!() };
            log_std[d] = orig - eps;
            let down = loss_and_grad(&m, &batch, &idx, &h, Par::Seq).total;
            let numeric = (up - down) / (2.0 * eps as f64);
            let analytic = lg.grad_log_std[d] as f64;
            assert!((numeric - analytic).abs() < 2e-3 + 3e-2 * analytic.abs(), "log_std[{d}]: {numeric} vs {analytic}");
        }
    }
    // Clip boundaries and ReLU kinks may spoil a rare quotient; a wrong gradient spoils most.
    assert!(bad.len() <= checked / 25, "{} of {checked} disagree: {:?}", bad.len(), &bad[..bad.len().min(6)]);
}

#[test]
fn whole_loss_gradient_categorical_huber() {
    check_whole_loss(false, LossType::Huber);
}

#[test]
fn whole_loss_gradient_gaussian_mse() {
    check_whole_loss(true, LossType::MeanSquaredError);
}

#[test]
fn gae_matches_a_hand_computation() {
    let t = Trajectory { rewards: vec![1.0, 0.0, 2.0], values: vec![0.5, 1.0, 1.5], ..Default::default() };
    let (g, l) = (0.9, 0.8);
    let (adv, ret) = gae(&t, g, l);
    // δ2 = 2 − 1.5 = 0.5; δ1 = 0 + 0.9·1.5 − 1 = 0.35; δ0 = 1 + 0.9·1 − 0.5 = 1.4
    let a2 = 0.5;
    let a1 = 0.35 + g * l * a2;
    let a0 = 1.4 + g * l * a1;
    for (x, y) in adv.iter().zip([a0, a1, a2]) {
        assert!((x - y).abs() < 1e-9, "{adv:?}");
    }
    assert!((ret[0] - (a0 + 0.5)).abs() < 1e-9);
    let b = make_batch(&[t.clone(), t], 0, 0.9);
    let mean: f32 = b.adv.iter().sum::<f32>() / 6.0;
    let var: f32 = b.adv.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / 6.0;
    assert!(mean.abs() < 1e-6 && (var - 1.0).abs() < 1e-4, "standardised: {mean} {var}");
}

/// A contextual bandit: the observation names the rewarded action (one-hot of 3).
fn bandit_episodes(model: &ActorCritic, version: u64, n: usize, rng: &mut ChaCha8Rng) -> (Vec<Trajectory>, f64) {
    let os = model.obs_size();
    let mut trajs = Vec::new();
    let mut total = 0.0;
    for _ in 0..n {
        let ctx = rng.random_range(0..3);
        let mut obs = vec![0.0f32; os];
        obs[ctx] = 1.0;
        let a = model.act(&obs, 1, false, rng, Par::Seq)[0];
        let Choice::Discrete(k) = a.choice else { unreachable!() };
        let r = if k == ctx { 1.0 } else { 0.0 };
        total += r as f64;
        trajs.push(Trajectory {
            obs,
            choices: vec![a.choice],
            logp: vec![a.logp],
            values: vec![a.value],
            rewards: vec![r],
            done: true,
            policy_version: version,
            ..Default::default()
        });
    }
    (trajs, total / n as f64)
}

#[test]
fn ppo_learns_a_bandit_and_would_not_with_a_wrong_sign() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let h = Hyperparameters { lr: 3e-3, num_epochs: 4, batch_size: 32, ..Hyperparameters::default() };
    let mut ppo = Ppo::new(model, h, 0, 1, Par::Seq);
    let (_, first) = bandit_episodes(&ppo.model, 0, 400, &mut rng);
    for _ in 0..25 {
        let (trajs, _) = bandit_episodes(&ppo.model, ppo.version, 128, &mut rng);
        ppo.update(&trajs).unwrap();
    }
    let (_, last) = bandit_episodes(&ppo.model, ppo.version, 400, &mut rng);
    assert!(first < 0.5, "a fresh policy guesses: {first}");
    assert!(last > 0.9, "PPO finds the rewarded action: {first} -> {last}");
    assert_eq!(ppo.version, 25);
}

#[test]
fn a_nan_never_reaches_the_weights() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let mut ppo = Ppo::new(model, Hyperparameters { batch_size: 8, ..Hyperparameters::default() }, 3, 1, Par::Seq);
    let (mut trajs, _) = bandit_episodes(&ppo.model, 3, 64, &mut rng);
    let before = ppo.model.clone();
    trajs[5].rewards[0] = f32::NAN;
    let refused = ppo.update(&trajs).unwrap_err();
    assert!(!refused.is_group() && refused.to_string().contains("non-finite"), "{refused:?}");
    assert_eq!(ppo.model, before, "weights untouched");
    assert_eq!(ppo.version, 3, "no new version");
    // And training goes on from the good weights.
    let (good, _) = bandit_episodes(&ppo.model, 3, 64, &mut rng);
    ppo.update(&good).unwrap();
    assert_eq!(ppo.version, 4);
    assert_ne!(ppo.model, before);
}

/// Issue 55: with `"precision": "bf16"` PPO still learns the bandit; its batch's figures come
/// from the same bf16 products as its gradient steps, so the first minibatch's ratios are 1;
/// and on a CPU with AVX-512 BF16 it is not the f32 update (elsewhere it is, bit for bit).
#[test]
fn a_bf16_update_learns_and_clips_around_its_own_figures() {
    use policy::nn::Precision;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let h = Hyperparameters {
        lr: 3e-3,
        num_epochs: 4,
        batch_size: 32,
        precision: Precision::Bf16,
        ..Hyperparameters::default()
    };
    let (trajs, first) = bandit_episodes(&model, 0, 128, &mut rng);
    let batch = make_batch_in(&trajs, &model, h.discount_factor, Par::Seq, Precision::Bf16);
    let lg = loss_and_grad(&model, &batch, &(0..32).collect::<Vec<_>>(), &h, Par::Seq);
    assert!(lg.approx_kl.abs() < 1e-6 && lg.clip_fraction == 0.0, "{} {}", lg.approx_kl, lg.clip_fraction);
    let mut ppo = Ppo::new(model.clone(), h.clone(), 0, 1, Par::Seq);
    let mut in_f32 = Ppo::new(model, Hyperparameters { precision: Precision::F32, ..h }, 0, 1, Par::Seq);
    ppo.update(&trajs).unwrap();
    in_f32.update(&trajs).unwrap();
    if Precision::bf16_available() {
        assert_ne!(ppo.model, in_f32.model, "the bf16 update made the f32 products");
    } else {
        assert_eq!(ppo.model, in_f32.model);
    }
    for _ in 0..24 {
        let (trajs, _) = bandit_episodes(&ppo.model, ppo.version, 128, &mut rng);
        ppo.update(&trajs).unwrap();
    }
    let (_, last) = bandit_episodes(&ppo.model, ppo.version, 400, &mut rng);
    assert!(first < 0.5 && last > 0.9, "PPO in bf16 finds the rewarded action: {first} -> {last}");
}

/// Issue 8: the old policy is the network as the update begins.
#[test]
fn the_old_policy_is_the_network_as_the_update_begins() {
    // DeepRacer's PPO clips around the network as the update begins and computes GAE from its
    // values, whichever version acted (flow control lets experience lag two versions): the
    // acting-time log-probabilities and values do not enter the update at all.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let (trajs, _) = bandit_episodes(&model, 0, 128, &mut rng);
    let mut acted_elsewhere = trajs.clone();
    for t in &mut acted_elsewhere {
        t.logp[0] -= 1.5;
        t.values[0] += 4.0;
    }
    let h = Hyperparameters { lr: 3e-3, num_epochs: 4, batch_size: 32, target_kl: None, ..Hyperparameters::default() };
    let mut a = Ppo::new(model.clone(), h.clone(), 0, 1, Par::Seq);
    let mut b = Ppo::new(model.clone(), h.clone(), 0, 1, Par::Seq);
    let (sa, sb) = (a.update(&trajs).unwrap(), b.update(&acted_elsewhere).unwrap());
    assert_eq!(a.model, b.model, "the same update");
    assert_eq!((sa.approx_kl, sa.policy_loss), (sb.approx_kl, sb.policy_loss));
    // The batch's figures are the model's own: the first minibatch's ratios are 1.
    let batch = make_batch_for(&acted_elsewhere, &model, h.discount_factor, Par::Seq);
    let lg = loss_and_grad(&model, &batch, &(0..32).collect::<Vec<_>>(), &h, Par::Seq);
    assert!(lg.approx_kl.abs() < 1e-6 && lg.clip_fraction == 0.0, "{} {}", lg.approx_kl, lg.clip_fraction);
    // Against the acting-time figures they would not be.
    let stale = make_batch(&acted_elsewhere, 6, h.discount_factor);
    assert!(loss_and_grad(&model, &stale, &(0..32).collect::<Vec<_>>(), &h, Par::Seq).clip_fraction > 0.5);
}

/// Issue 55: with `value_epochs` the value tower trains in the update's first epochs alone:
/// its weights are those of an update of that many epochs, and the policy's those of an
/// update that trains the value tower in every epoch (the policy's loss does not read the
/// value tower within an update), bit for bit.
#[test]
fn the_value_tower_trains_in_the_first_value_epochs_and_the_policy_in_all() {
    let mut rng = ChaCha8Rng::seed_from_u64(55);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let (trajs, _) = bandit_episodes(&model, 0, 128, &mut rng);
    let h = |num_epochs, value_epochs| Hyperparameters {
        lr: 3e-3,
        num_epochs,
        value_epochs,
        batch_size: 32,
        target_kl: None,
        ..Hyperparameters::default()
    };
    let run = |num_epochs, value_epochs| {
        let mut p = Ppo::new(model.clone(), h(num_epochs, value_epochs), 0, 1, Par::Seq);
        let s = p.update(&trajs).unwrap();
        (p.model, s)
    };
    // 128 samples in minibatches of 32: 4 gradient steps an epoch.
    let (cut, s) = run(4, Some(1));
    let (all, s_all) = run(4, None);
    let (first, s_first) = run(1, None);
    assert_eq!((s.gradient_steps, s.value_steps), (16, 4), "{s:?}");
    assert_eq!((s_all.gradient_steps, s_all.value_steps), (16, 16), "{s_all:?}");
    assert_eq!(cut.v, first.v, "the value tower: one epoch's training");
    assert_eq!(cut.pi, all.pi, "the policy tower: every epoch's");
    assert_ne!(cut.v, all.v, "the later epochs would have moved the value tower");
    // The value loss is the mean over the steps that trained it.
    assert!((s.value_loss - s_first.value_loss).abs() < 1e-12, "{} vs {}", s.value_loss, s_first.value_loss);
    // More value epochs than epochs: every epoch.
    assert_eq!(run(2, Some(5)).0, run(2, None).0);
}

/// Issue 55: with `dual_clip` c, a sample whose advantage is negative and whose ratio is
/// above c (an action the policy has all but ruled out since it was acted) counts c × its
/// advantage in the loss and adds nothing to the gradient; without it, it adds the most.
#[test]
fn a_negative_advantage_far_above_the_dual_clip_adds_no_gradient() {
    let mut rng = ChaCha8Rng::seed_from_u64(56);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let mut batch = random_batch(&model, 32, &mut rng);
    // Samples 0..8: acted with e^-4 of the probability the policy gives them now (ratio ≈ 55),
    // advantage negative.
    let (fresh, _) = logp_and_values(&model, &batch.obs, &batch.choices, Par::Seq);
    for (i, lp) in fresh.iter().enumerate().take(8) {
        batch.logp_old[i] = lp - 4.0;
        batch.adv[i] = -1.0 - i as f32 * 0.1;
    }
    let h = |dual_clip| Hyperparameters { beta_entropy: 0.0, dual_clip, ..Hyperparameters::default() };
    let all: Vec<usize> = (0..32).collect();
    let rest: Vec<usize> = (8..32).collect();
    let dual = loss_and_grad(&model, &batch, &all, &h(Some(3.0)), Par::Seq);
    let plain = loss_and_grad(&model, &batch, &all, &h(None), Par::Seq);
    let others = loss_and_grad(&model, &batch, &rest, &h(Some(3.0)), Par::Seq);
    // The gradient is the other 24 samples' (their mean over 32, not 24).
    let scale = 24.0 / 32.0;
    let size = |g: &[f32]| g.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let diff: Vec<f32> = dual.grad_pi.iter().zip(&others.grad_pi).map(|(a, b)| a - b * scale).collect();
    assert!(size(&diff) <= 1e-5 * size(&dual.grad_pi), "{} of {}", size(&diff), size(&dual.grad_pi));
    // The loss: theirs, plus −3 × each floored advantage.
    let floored: f64 = (0..8).map(|i| -3.0 * batch.adv[i] as f64).sum::<f64>() / 32.0;
    let want = others.policy_loss * scale as f64 + floored;
    assert!((dual.policy_loss - want).abs() < 1e-5, "{} vs {want}", dual.policy_loss);
    // Without the bound those eight samples dominate the step.
    assert!(size(&plain.grad_pi) > 5.0 * size(&dual.grad_pi), "{} vs {}", size(&plain.grad_pi), size(&dual.grad_pi));
}

/// Issue 8: an update stops its epochs once the policy moved past the target KL.
#[test]
fn an_update_stops_its_epochs_once_the_policy_moved_past_target_kl() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let model = ActorCritic::new(&meta(false), 6, &mut rng);
    let (trajs, _) = bandit_episodes(&model, 0, 128, &mut rng);
    // 128 samples in minibatches of 32, 4 epochs: 16 gradient steps unless stopped.
    for (target_kl, stops) in [(None, false), (Some(10.0), false), (Some(1e-7), true)] {
        let h = Hyperparameters { lr: 3e-3, num_epochs: 4, batch_size: 32, target_kl, ..Hyperparameters::default() };
        let mut ppo = Ppo::new(model.clone(), h, 0, 1, Par::Seq);
        let s = ppo.update(&trajs).unwrap();
        assert_eq!(ppo.version, 1, "{target_kl:?}: {s:?}");
        if stops {
            // The first step starts from ratios of 1; the one after it sees the policy moved.
            let k = s.kl_stop.expect("stopped");
            assert!(k <= 2 && s.gradient_steps == k, "{target_kl:?}: {s:?}");
            assert_ne!(ppo.model, model, "the steps before the stop were taken");
        } else {
            assert_eq!((s.kl_stop, s.gradient_steps), (None, 16), "{target_kl:?}");
        }
    }
}
