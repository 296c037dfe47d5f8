//! SAC's maths: each of its three losses against finite differences in every network it
//! trains, the replay memory's bookkeeping, and learning a task whose answer is known.

use faer::Par;
use learner::sac::{Batch, Losses, Replay, ReplayError, Sac, SacNets, SacSettings, Tapes, TwinQ, losses_and_grads};
use policy::ModelMetadata;
use policy::nn::{InputShape, LayerSpec, Net};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::support::Threads;

fn meta(obs: usize) -> (ModelMetadata, usize) {
    let text = r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":1,"high":2}},
        "action_space_type":"continuous","training_algorithm":"sac","sensor":["STATE_VECTOR"],
        "neural_network":"PADDOCK_MLP","version":"5"}"#;
    (ModelMetadata::parse(text, "meta").unwrap(), obs)
}

/// SAC's networks for a small camera: a conv embedder shared by the Q heads, as DeepRacer's
/// camera networks have, at a size finite differences can afford. Small output weights, as
/// SAC's policy starts: with |u| of 5 the tanh's curvature spoils quotients at this step size.
fn small_camera_nets(rng: &mut ChaCha8Rng) -> SacNets {
    use LayerSpec::*;
    let image = InputShape::Image(8, 10, 1);
    let embed = [Scale(1.0 / 255.0), Conv(3, 3, 2), Relu];
    let tower = |out: usize, rng: &mut ChaCha8Rng| {
        let mut specs = embed.to_vec();
        specs.extend([Dense(12), Relu]);
        if out == 4 {
            specs.extend([Dense(8), Relu]);
        }
        specs.push(Dense(out));
        Net::new(image, &specs, Some(0.1), rng)
    };
    let e = Net::new(image, &embed, None, rng);
    let w = e.out_size();
    let head = |rng: &mut ChaCha8Rng| {
        Net::new(InputShape::Flat(w + 2), &[Dense(8), Relu, Dense(6), Relu, Dense(1)], None, rng)
    };
    let v = tower(1, rng);
    SacNets { policy: tower(4, rng), q: TwinQ { embed: Some(e), q1: head(rng), q2: head(rng) }, v_target: v.clone(), v }
}

fn random_batch(nets: &SacNets, n: usize, pixels: bool, rng: &mut ChaCha8Rng) -> Batch {
    let per = nets.obs_size();
    let obs_value =
        |rng: &mut ChaCha8Rng| if pixels { rng.random_range(0..256) as f32 } else { rng.random_range(-1.0..1.0) };
    Batch {
        obs: (0..n * per).map(|_| obs_value(rng)).collect(),
        next_obs: (0..n * per).map(|_| obs_value(rng)).collect(),
        action: (0..2 * n).map(|_| rng.random_range(-0.95..0.95)).collect(),
        reward: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        done: (0..n).map(|i| if i % 3 == 0 { 1.0 } else { 0.0 }).collect(),
    }
}

/// Perturb each network's parameters so the losses depend visibly on all of them.
fn jitter(nets: &mut SacNets, rng: &mut ChaCha8Rng) {
    let mut all: Vec<&mut Net> =
        vec![&mut nets.policy, &mut nets.q.q1, &mut nets.q.q2, &mut nets.v, &mut nets.v_target];
    if let Some(e) = nets.q.embed.as_mut() {
        all.push(e);
    }
    for net in all {
        for p in net.params.iter_mut() {
            *p += rng.random_range(-0.05..0.05);
        }
    }
}

/// Which network a finite difference moves, the loss it reads and the gradient it checks.
type Pick =
    (&'static str, fn(&mut SacNets) -> &mut Vec<f32>, fn(&Losses) -> f64, fn(&learner::sac::Grads) -> &Vec<f32>);

fn check(mut nets: SacNets, settings: &SacSettings, pixels: bool, rng: &mut ChaCha8Rng, what: &str) {
    jitter(&mut nets, rng);
    let batch = random_batch(&nets, 5, pixels, rng);
    let eps: Vec<f32> = (0..10).map(|_| rng.random_range(-1.5..1.5)).collect();
    let alpha = 0.3;
    let mut tapes = Tapes::default();
    let (_, g) = losses_and_grads(&nets, settings, alpha, &batch, &eps, Par::Seq, &mut tapes);
    let mut picks: Vec<Pick> = vec![
        ("policy", |n| &mut n.policy.params, |l| l.policy, |g| &g.policy),
        ("q1", |n| &mut n.q.q1.params, |l| l.q, |g| &g.q1),
        ("q2", |n| &mut n.q.q2.params, |l| l.q, |g| &g.q2),
        ("v", |n| &mut n.v.params, |l| l.v, |g| &g.v),
    ];
    if nets.q.embed.is_some() {
        picks.push(("q embedder", |n| &mut n.q.embed.as_mut().unwrap().params, |l| l.q, |g| &g.q_embed));
    }
    for (name, params, loss, grad) in picks {
        let grad = grad(&g).clone();
        let h = 2e-3f32;
        let mut bad = Vec::new();
        let checks = 120;
        for _ in 0..checks {
            let i = rng.random_range(0..grad.len());
            let orig = params(&mut nets)[i];
            let mut at = |v: f32, nets: &mut SacNets| {
                params(nets)[i] = v;
                loss(&losses_and_grads(nets, settings, alpha, &batch, &eps, Par::Seq, &mut tapes).0)
            };
            let numeric = (at(orig + h, &mut nets) - at(orig - h, &mut nets)) / (2.0 * h as f64);
            params(&mut nets)[i] = orig;
            if (numeric - grad[i] as f64).abs() > 2e-3 + 3e-2 * (grad[i] as f64).abs() {
                bad.push((i, numeric, grad[i]));
            }
        }
        // A ReLU kink or a switch of min(q1, q2) within ±h spoils a rare quotient.
        assert!(
            bad.len() <= checks / 30,
            "{what}: {name}: {} of {checks} disagree: {:?}",
            bad.len(),
            &bad[..bad.len().min(5)]
        );
    }
}

/// Issue 32: the three SAC losses match finite differences.
#[test]
fn the_three_sac_losses_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    let (m, obs) = meta(7);
    let settings = SacSettings::for_space(&m.action_space).unwrap();
    assert_eq!(settings.scale, [30.0, 0.5], "half-ranges in the environment's units");
    let nets = SacNets::new(&m, obs, &mut rng);
    assert!(nets.q.embed.is_none(), "the state vector goes to the Q heads as it is");
    check(nets.clone(), &settings, false, &mut rng, "state vector, MSE");
    check(nets, &SacSettings { huber: true, ..settings.clone() }, false, &mut rng, "state vector, Huber");
    let cam = small_camera_nets(&mut rng);
    check(cam, &settings, true, &mut rng, "camera embedder");
}

/// Issue 32: the temperature follows the entropy target.
#[test]
fn the_temperature_follows_the_entropy_target() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (m, obs) = meta(4);
    let nets = SacNets::new(&m, obs, &mut rng);
    let s = SacSettings { target_entropy: Some(-2.0), ..SacSettings::for_space(&m.action_space).unwrap() };
    let batch = random_batch(&nets, 6, false, &mut rng);
    let eps: Vec<f32> = (0..12).map(|_| rng.random_range(-1.0..1.0)).collect();
    let (l, g) = losses_and_grads(&nets, &s, 0.2, &batch, &eps, Par::Seq, &mut Tapes::default());
    // d/d log α of −log α·(log π + H̄): −mean(log π) − H̄ = entropy − H̄, with H̄ = −2.
    assert!((g.log_alpha as f64 - (l.entropy + 2.0)).abs() < 1e-4, "{} vs {}", g.log_alpha, l.entropy);
    let fixed = SacSettings { target_entropy: None, ..s };
    assert_eq!(losses_and_grads(&nets, &fixed, 0.2, &batch, &eps, Par::Seq, &mut Tapes::default()).1.log_alpha, 0.0);
}

/// Issue 32: the replay memory keeps episodes in order and pixels as bytes.
#[test]
fn the_replay_memory_keeps_episodes_in_order_and_pixels_as_bytes() {
    // Two values a step: a float, then a pixel.
    let pixel = std::ops::Range { start: 1, end: 2 };
    let mut r = Replay::new(5, 2, vec![pixel]);
    let ep = |k: f32, n: usize| -> Vec<f32> { (0..n).flat_map(|i| [k + i as f32 * 0.5, (10 * i) as f32]).collect() };
    r.push_episode(&ep(1.0, 3), &[[0.1, 0.2]; 3], &[1.0, 2.0, 3.0], true).unwrap();
    assert_eq!((r.len(), r.usable()), (3, 3));
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let b = r.sample(200, &mut rng).unwrap();
    for i in 0..b.len() {
        let (s, s2) = (&b.obs[2 * i..2 * i + 2], &b.next_obs[2 * i..2 * i + 2]);
        let step = ((s[0] - 1.0) / 0.5).round() as usize;
        assert_eq!(b.reward[i], 1.0 + step as f32, "the step's own reward");
        assert_eq!(s[1], (10 * step) as f32, "the pixel back as it was");
        if step == 2 {
            assert_eq!(b.done[i], 1.0, "the episode ended there");
        } else {
            assert_eq!((b.done[i], s2[0]), (0.0, s[0] + 0.5), "the next slot is the next step");
        }
    }
    // A cut episode's last step has no successor: never sampled. The ring wraps over the oldest.
    r.push_episode(&ep(5.0, 3), &[[0.0, 0.0]; 3], &[7.0, 8.0, 9.0], false).unwrap();
    assert_eq!((r.len(), r.usable(), r.added()), (5, 4, 6));
    let b = r.sample(300, &mut rng).unwrap();
    assert!(!b.reward.contains(&9.0) && !b.reward.contains(&1.0), "the cut step and the overwritten one");
    assert!(b.reward.contains(&8.0) && b.reward.contains(&2.0));
    // A pixel that is not a byte is refused, and nothing of its episode is stored.
    let bad = [0.0, 12.0, 0.0, 300.0];
    assert_eq!(
        r.push_episode(&bad, &[[0.0, 0.0]; 2], &[0.0, 0.0], true),
        Err(ReplayError::NotAByte { step: 1, index: 1, value: 300.0 })
    );
    assert_eq!(r.added(), 6);
}

/// A bandit whose best action is known: each step draws x uniformly in [-1, 1]², shows the
/// policy `observe(x)`, and rewards the action by its squared distance to `answer(observation)`.
struct Bandit {
    observe: fn([f32; 2]) -> Vec<f32>,
    answer: fn(&[f32]) -> [f32; 2],
}

impl Bandit {
    /// The largest error of the mean action over 50 draws.
    fn worst_error(&self, sac: &Sac, rng: &mut ChaCha8Rng) -> f32 {
        let mut worst = 0.0f32;
        let mut tape = policy::nn::Tape::default();
        for _ in 0..50 {
            let obs = (self.observe)([rng.random_range(-1.0..1.0f32), rng.random_range(-1.0..1.0f32)]);
            sac.nets.policy.forward(&obs, 1, &mut tape, Par::Seq);
            let a = policy::model::squashed(tape.output(), [0.0; 2], sac.settings.scale).a;
            let b = (self.answer)(&obs);
            worst = worst.max((a[0] - b[0]).abs()).max((a[1] - b[1]).abs());
        }
        worst
    }

    /// 3,000 one-step episodes into the replay memory, a gradient step (and V's target
    /// copied) after each from the 64th on.
    fn train(&self, sac: &mut Sac, replay: &mut Replay, rng: &mut ChaCha8Rng, act_rng: &mut ChaCha8Rng) {
        let mut tapes = Tapes::default();
        let mut tape = policy::nn::Tape::default();
        for step in 0..3000 {
            let obs = (self.observe)([act_rng.random_range(-1.0..1.0f32), act_rng.random_range(-1.0..1.0f32)]);
            sac.nets.policy.forward(&obs, 1, &mut tape, Par::Seq);
            let eps = [act_rng.random::<f32>() * 2.0 - 1.0, act_rng.random::<f32>() * 2.0 - 1.0];
            let a = policy::model::squashed(tape.output(), eps, sac.settings.scale).a;
            let b = (self.answer)(&obs);
            let reward = -((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2));
            replay.push_episode(&obs, &[a], &[reward], true).unwrap();
            if step >= 64 {
                let batch = replay.sample(64, rng).unwrap();
                sac.step(&batch, Par::Seq, &mut tapes);
                sac.update_target();
            }
        }
    }
}

/// Issue 32: the bandit with a = (0.8 x₀, −0.4 x₁) for the observation x. SAC must find it (a wrong
/// sign in the policy's gradient through Q, or a wrong target, fails it).
#[test]
fn sac_learns_a_task_whose_answer_is_known() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (m, obs) = meta(2);
    let nets = SacNets::new(&m, obs, &mut rng);
    let settings = SacSettings { alpha: 0.01, lr: 1e-3, ..SacSettings::for_space(&m.action_space).unwrap() };
    let mut sac = Sac::new(nets, settings, 5);
    let mut replay = Replay::new(10_000, 2, vec![]);
    let mut act_rng = ChaCha8Rng::seed_from_u64(6);
    let bandit = Bandit { observe: |x| x.to_vec(), answer: |x| [x[0] * 0.8, -x[1] * 0.4] };
    let before = bandit.worst_error(&sac, &mut act_rng);
    bandit.train(&mut sac, &mut replay, &mut rng, &mut act_rng);
    let after = bandit.worst_error(&sac, &mut act_rng);
    assert!(after < 0.15 && after < before / 3.0, "largest action error {before:.3} → {after:.3}");
}

/// Issue 32: the same bandit from pixels: the two values are the brightness of an 8 × 10 image's
/// left and right halves, stored as bytes in the replay memory, and every network sees them through
/// its convolutions (the Q heads through their shared embedder). SAC must find the answer from the
/// image alone (a wrong gradient through a convolution, the embedder or the pixels' scale fails
/// it).
#[test]
fn sac_learns_the_bandit_from_pixels() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (m, _) = meta(80);
    let nets = small_camera_nets(&mut rng);
    let settings = SacSettings { alpha: 0.01, lr: 1e-3, ..SacSettings::for_space(&m.action_space).unwrap() };
    let mut sac = Sac::new(nets, settings, 5);
    let pixels = std::ops::Range { start: 0, end: 80 };
    let mut replay = Replay::new(10_000, 80, vec![pixels]);
    let mut act_rng = ChaCha8Rng::seed_from_u64(6);
    let bandit = Bandit {
        observe: |x| {
            (0..80)
                .map(|i| if i % 10 < 5 { ((x[0] + 1.0) * 127.0).round() } else { ((x[1] + 1.0) * 127.0).round() })
                .collect()
        },
        // What the image shows, then the answer to it.
        answer: |img| {
            let seen = [img[0] / 127.0 - 1.0, img[9] / 127.0 - 1.0];
            [seen[0] * 0.8, -seen[1] * 0.4]
        },
    };
    let before = bandit.worst_error(&sac, &mut act_rng);
    bandit.train(&mut sac, &mut replay, &mut rng, &mut act_rng);
    let after = bandit.worst_error(&sac, &mut act_rng);
    assert!(after < 0.2 && after < before / 3.0, "largest action error {before:.3} → {after:.3}");
}

/// Issue 32: the replay memory survives a save and a smaller capacity keeps the newest.
#[test]
fn the_replay_memory_survives_a_save_and_a_smaller_capacity_keeps_the_newest() {
    let dir = tempfile::tempdir().unwrap();
    let pixel = std::ops::Range { start: 0, end: 1 };
    let mut r = Replay::new(6, 3, vec![pixel]);
    for k in 0..3 {
        let obs: Vec<f32> = (0..3).flat_map(|i| [(10 * k + i) as f32, 0.25 * i as f32, -1.5]).collect();
        r.push_episode(&obs, &[[0.5, -0.5]; 3], &[k as f32; 3], k != 1).unwrap();
    }
    let path = dir.path().join("replay.safetensors");
    r.save(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let back = Replay::from_bytes(&bytes, 6).unwrap();
    assert_eq!((back.len(), back.added(), back.usable()), (6, 9, 5));
    // Oldest first from slot 0: saved and read again, the same memory.
    back.save(&dir.path().join("again.safetensors")).unwrap();
    let again = Replay::from_bytes(&std::fs::read(dir.path().join("again.safetensors")).unwrap(), 6).unwrap();
    assert!(again == back, "the same memory");
    let rewards = |r: &Replay| {
        let mut v = r.sample(200, &mut ChaCha8Rng::seed_from_u64(3)).unwrap().reward;
        v.sort_by(f32::total_cmp);
        v.dedup();
        v
    };
    assert_eq!(rewards(&back), rewards(&r), "the same episodes (the cut one's last step never drawn)");
    // Three slots: the newest episode only.
    let small = Replay::from_bytes(&bytes, 3).unwrap();
    assert_eq!((small.len(), small.added(), small.usable()), (3, 9, 3));
    let b = small.sample(50, &mut ChaCha8Rng::seed_from_u64(2)).unwrap();
    assert!(b.reward.iter().all(|&x| x == 2.0) && b.obs.chunks(3).all(|o| o[0] >= 20.0), "{:?}", b.reward);
    // A damaged file is refused, naming what is wrong.
    let e = Replay::from_bytes(&bytes[..bytes.len() / 2], 6).unwrap_err();
    assert!(e.0.contains("safetensors"), "{e}");
}

/// Issue 32: a replay memory larger than a quarter of the machine is capped.
#[test]
fn a_replay_memory_larger_than_a_quarter_of_the_machine_is_capped() {
    use learner::sac::trainer::replay_capacity;
    let camera = std::ops::Range { start: 0, end: 19_200 };
    // (wanted, values a step, pixels, machine's memory, capacity): 6 GiB / 19,213 bytes = 335,317.
    let table = [
        (1_000_000, 19_200, Some(camera.clone()), Some(24u64 << 30), 335_317),
        (1_000_000, 19_200, Some(camera), None, 1_000_000),
        (1_000_000, 29, None, Some(24u64 << 30), 1_000_000),
        (10, 29, None, Some(1000), 1),
    ];
    for (wanted, per, pixels, memory, want) in table {
        let pixels: Vec<_> = pixels.into_iter().collect();
        assert_eq!(replay_capacity(wanted, per, &pixels, memory), want, "{wanted} of {per} in {memory:?}");
    }
}

/// Issue 32: two and three learners, each with a share of every batch, make one learner's steps:
/// the members end each step with the same state, bit for bit, and that state is one learner's on
/// the whole batch (to the rounding of the sums' order). With 300 inputs and batches of 8 every
/// network's dense layers are big enough to travel as their factors (inputs and output gradients),
/// which every member multiplies out in rank order.
#[test]
fn a_team_of_learners_makes_one_learners_sac_steps() {
    for (inputs, batch) in [(6, 64), (300, 8)] {
        team_makes_one_learners_steps(inputs, batch);
    }
}

fn team_makes_one_learners_steps(inputs: usize, batch: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let (m, obs) = meta(inputs);
    let s = SacSettings { target_entropy: Some(-2.0), ..SacSettings::for_space(&m.action_space).unwrap() };
    let start = Sac::new(SacNets::new(&m, obs, &mut rng), s, 8);
    let mut replay = Replay::new(500, obs, vec![]);
    for _ in 0..10 {
        let n = 20;
        let x: Vec<f32> = (0..n * obs).map(|_| rng.random_range(-1.0..1.0)).collect();
        let a: Vec<[f32; 2]> = (0..n).map(|_| [rng.random_range(-0.9..0.9), rng.random_range(-0.9..0.9)]).collect();
        let r: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        replay.push_episode(&x, &a, &r, true).unwrap();
    }
    let batches: Vec<Batch> = (0..3).map(|_| replay.sample(batch, &mut rng).unwrap()).collect();
    let defer = learner::sac::Defer::for_batch(&start.nets, batch);
    let factored = [&defer.policy, &defer.q1, &defer.q2, &defer.v].iter().all(|d| !d.is_empty());
    assert_eq!(factored, inputs == 300, "{defer:?}");
    let mut alone = start.clone();
    let want: Vec<Losses> = batches.iter().map(|b| alone.step(b, Par::Seq, &mut Tapes::default())).collect();
    for size in [2, 3] {
        let mut members = vec![start.clone(); size];
        let got: Vec<Vec<Losses>> = std::thread::scope(|sc| {
            let handles: Vec<_> = members
                .iter_mut()
                .zip(Threads::team(size))
                .map(|(sac, mut group)| {
                    let batches = &batches;
                    sc.spawn(move || {
                        let mut tapes = Tapes::default();
                        let steps = batches.iter().enumerate();
                        steps
                            .map(|(k, b)| sac.step_in(b, &mut group, k as u64, Par::Seq, &mut tapes).unwrap())
                            .collect()
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        // Each member took its share only: the summed losses are the whole batch's (Adam
        // alone would not tell, as it forgets a gradient's scale).
        for (k, w) in want.iter().enumerate() {
            for l in &got {
                for (a, b) in [(l[k].policy, w.policy), (l[k].q, w.q), (l[k].v, w.v), (l[k].entropy, w.entropy)] {
                    assert!((a - b).abs() <= 1e-4 * b.abs().max(1.0), "size {size} step {k}: {a} vs {b}");
                }
            }
        }
        for other in &members[1..] {
            assert!(other.nets == members[0].nets && other.log_alpha == members[0].log_alpha, "size {size}");
        }
        let pairs = [
            (&members[0].nets.policy.params, &alone.nets.policy.params),
            (&members[0].nets.q.q1.params, &alone.nets.q.q1.params),
            (&members[0].nets.q.q2.params, &alone.nets.q.q2.params),
            (&members[0].nets.v.params, &alone.nets.v.params),
        ];
        for (team, one) in pairs {
            // Adam divides by the gradient's size: a near-zero gradient's rounding can move a
            // weight by up to lr; every other weight within 1e-6 of one learner's.
            let lr = start.settings.lr;
            let far = team.iter().zip(one.iter()).filter(|(a, b)| (**a - **b).abs() > 1e-6).count();
            let worst = team.iter().zip(one.iter()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(
                worst <= 3.0 * lr && far * 100 <= team.len(),
                "size {size}: {far} of {} differ, worst {worst}",
                team.len()
            );
        }
        assert!((members[0].log_alpha - alone.log_alpha).abs() < 1e-5, "size {size}");
    }
}

/// Issue 32: a learner team's joiner takes over a SAC learner's networks, optimisers and replay
/// memory (a ring that has wrapped round), and from then on makes the leader's updates bit for bit;
/// a state without its memory, or with a tensor missing, is refused with nothing changed.
#[test]
fn a_joiner_takes_over_a_sac_learner_and_its_memory_and_updates_as_it_does() {
    use learner::sac::SacTrainer;
    let (m, obs) = meta(6);
    let h =
        learner::Hyperparameters { sac_replay_size: 300, sac_gradient_steps_per_transition: 0.1, ..Default::default() };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let model = policy::ActorCritic::new(&m, obs, &mut rng);
    let episodes = |rng: &mut ChaCha8Rng| -> Vec<policy::Trajectory> {
        (0..3)
            .map(|_| {
                let n = 70;
                let a = |rng: &mut ChaCha8Rng| rng.random_range(-0.9..0.9);
                policy::Trajectory {
                    world: "w".into(),
                    obs: (0..n * obs).map(|_| rng.random_range(-1.0..1.0)).collect(),
                    choices: (0..n).map(|_| policy::Choice::Continuous([a(rng), a(rng)])).collect(),
                    rewards: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
                    done: true,
                    ..Default::default()
                }
            })
            .collect()
    };
    let mut leader = SacTrainer::new(model.clone(), &m, obs, &h, 0, 1, Par::Seq).unwrap();
    for _ in 0..2 {
        leader.update_alone(&episodes(&mut rng)).unwrap();
    }
    assert!(leader.replay().added() > 300, "the ring has wrapped round");
    let mut joiner = SacTrainer::new(model, &m, obs, &h, 0, 2, Par::Seq).unwrap();
    let before = joiner.state();
    let e = joiner.restore(leader.state(), None).unwrap_err().to_string();
    assert!(e.contains("replay memory"), "{e}");
    let mut torn = leader.state();
    torn.tensors.retain(|(n, _)| n != "adam.q1.v");
    let e = joiner.restore(torn, leader.memory().as_deref()).unwrap_err().to_string();
    assert!(e.contains("adam.q1.v"), "{e}");
    assert_eq!(joiner.state(), before, "a refused state changes nothing");
    joiner.restore(leader.state(), leader.memory().as_deref()).unwrap();
    assert!(joiner.replay() == leader.replay(), "the memory as it lay in the leader's ring");
    for k in 0..2 {
        let trajs = episodes(&mut rng);
        let a = leader.update_planned(&trajs, 40 + k, &mut learner::Alone).unwrap();
        let b = joiner.update_planned(&trajs, 40 + k, &mut learner::Alone).unwrap();
        assert!(a.gradient_steps > 0 && a == b, "update {k}");
        assert_eq!(joiner.state(), leader.state(), "update {k}");
        assert!(joiner.replay() == leader.replay(), "update {k}");
    }
}

/// Issue 32: the big dense layers' weight gradients a SAC step leaves as factors (what a learner
/// team sends, and what Adam multiplies out) are the full gradients, `dW = dᵀ·x`; the losses and
/// every other gradient value are the same.
#[test]
fn sac_gradients_left_as_factors_multiply_out_to_the_full_ones() {
    use learner::sac::{Defer, Share, losses_and_grads_share};
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (m, obs) = meta(300);
    let s = SacSettings::for_space(&m.action_space).unwrap();
    let mut nets = SacNets::new(&m, obs, &mut rng);
    jitter(&mut nets, &mut rng);
    let batch = random_batch(&nets, 8, false, &mut rng);
    let eps: Vec<f32> = (0..16).map(|_| rng.random_range(-1.5..1.5)).collect();
    let defer = Defer::for_batch(&nets, 8);
    let (l_full, full) = losses_and_grads(&nets, &s, 0.3, &batch, &eps, Par::Seq, &mut Tapes::default());
    let mut t = Tapes::default();
    let share = Share { batch: &batch, eps: &eps, weight: 1.0 / 8.0 };
    let (l_def, def) = losses_and_grads_share(&nets, &s, 0.3, share, &defer, Par::Seq, &mut t);
    assert_eq!(l_full, l_def);
    let f = &def.factors;
    for (name, full, part, factors) in [
        ("policy", &full.policy, &def.policy, &f.policy),
        ("q1", &full.q1, &def.q1, &f.q1),
        ("q2", &full.q2, &def.q2, &f.q2),
        ("v", &full.v, &def.v, &f.v),
    ] {
        assert!(!factors.is_empty(), "{name}: no layer deferred");
        let mut got = part.clone();
        for fa in factors {
            for o in 0..fa.n_out {
                for i in 0..fa.n_in {
                    let dw: f32 = (0..fa.batch).map(|b| fa.d[b * fa.n_out + o] * fa.x[b * fa.n_in + i]).sum();
                    got[fa.offset + o * fa.n_in + i] = dw;
                }
            }
        }
        let worst = got.iter().zip(full.iter()).map(|(a, b)| (a - b).abs() / b.abs().max(1e-3)).fold(0.0f32, f32::max);
        assert!(worst < 1e-3, "{name}: the multiplied-out factors differ from the full gradient by {worst}");
    }
    assert_eq!(full.q_embed, def.q_embed);
}

/// Issue 32: a SAC run keeps its replay memory at every checkpoint: the first writes it whole, each
/// later one the transitions stored since as a part, and parts grown as large as the memory
/// become the whole memory again; a run that crashed after a checkpoint resumes with the
/// memory as it was then (the ring's oldest gone as they were). A part that does not fit is
/// refused, naming its file.
#[test]
fn the_replay_memory_is_kept_at_every_checkpoint_and_survives_a_crash() {
    use learner::sac::SacTrainer;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (m, obs) = meta(6);
    let h = learner::Hyperparameters {
        sac_replay_size: 500,
        sac_gradient_steps_per_transition: 0.05,
        ..Default::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let model = policy::ActorCritic::new(&m, obs, &mut rng);
    let episodes = |rng: &mut ChaCha8Rng| -> Vec<policy::Trajectory> {
        (0..3)
            .map(|k| policy::Trajectory {
                world: "w".into(),
                obs: (0..70 * obs).map(|_| rng.random_range(-1.0..1.0)).collect(),
                choices: (0..70).map(|_| policy::Choice::Continuous([0.5, -0.25])).collect(),
                rewards: (0..70).map(|_| rng.random_range(-1.0..1.0)).collect(),
                done: k != 1,
                ..Default::default()
            })
            .collect()
    };
    let same = |a: &Replay, b: &Replay| {
        let draw = |r: &Replay| r.sample(300, &mut ChaCha8Rng::seed_from_u64(1)).unwrap();
        a.len() == b.len() && a.added() == b.added() && draw(a) == draw(b)
    };
    let parts = |root: &std::path::Path| std::fs::read_dir(root.join("replay")).map_or(0, |d| d.count());
    let mut t = SacTrainer::new(model.clone(), &m, obs, &h, 0, 1, Par::Seq).unwrap();
    t.update_alone(&episodes(&mut rng)).unwrap();
    t.save_memory_part(root).unwrap();
    assert!(root.join("replay.safetensors").exists() && parts(root) == 0, "the first checkpoint: the whole memory");
    for want in [1, 2] {
        t.update_alone(&episodes(&mut rng)).unwrap();
        t.save_memory_part(root).unwrap();
        assert_eq!(parts(root), want, "a part of 210 transitions a checkpoint");
    }
    assert_eq!((t.replay().added(), t.replay().len()), (630, 500), "the ring went round");
    // A crash now: a new learner takes the memory of the last checkpoint.
    let mut back = SacTrainer::new(model.clone(), &m, obs, &h, 0, 2, Par::Seq).unwrap();
    assert!(back.load_memory(root).unwrap());
    assert!(same(back.replay(), t.replay()), "the memory and its parts, in order");
    // A third part would hold more than the memory: the whole memory again, the parts let go.
    t.update_alone(&episodes(&mut rng)).unwrap();
    t.save_memory_part(root).unwrap();
    assert_eq!(parts(root), 0);
    let mut back = SacTrainer::new(model.clone(), &m, obs, &h, 0, 2, Par::Seq).unwrap();
    assert!(back.load_memory(root).unwrap() && same(back.replay(), t.replay()));
    // The resumed learner's own parts follow on.
    back.update_alone(&episodes(&mut rng)).unwrap();
    back.save_memory_part(root).unwrap();
    let mut again = SacTrainer::new(model.clone(), &m, obs, &h, 0, 3, Par::Seq).unwrap();
    assert!(again.load_memory(root).unwrap() && same(again.replay(), back.replay()));
    // A clean end: the whole memory, no parts.
    back.save_memory(root).unwrap();
    assert!(!root.join("replay").exists());
    // A part of another observation is refused, naming its file.
    let (m8, _) = meta(8);
    let mut other = SacTrainer::new(policy::ActorCritic::new(&m8, 8, &mut rng), &m8, 8, &h, 0, 4, Par::Seq).unwrap();
    let trajs: Vec<policy::Trajectory> = episodes(&mut rng)
        .into_iter()
        .map(|mut t| {
            t.obs = (0..70 * 8).map(|i| i as f32 / 560.0).collect();
            t
        })
        .collect();
    other.update_alone(&trajs).unwrap();
    let alien = tempfile::tempdir().unwrap();
    other.save_memory(alien.path()).unwrap();
    std::fs::create_dir_all(root.join("replay")).unwrap();
    std::fs::copy(alien.path().join("replay.safetensors"), root.join("replay/99999999999999999999.safetensors"))
        .unwrap();
    let e = again.load_memory(root).unwrap_err();
    assert!(e.path().ends_with("99999999999999999999.safetensors"), "{e}");
    assert!(e.to_string().contains("transitions of 8 values"), "{e}");
}
