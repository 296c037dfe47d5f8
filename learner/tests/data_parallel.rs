//! Issue 8: data-parallel PPO. Learners that each take a share of every minibatch and sum
//! their gradients in rank order make the same update as one learner on the whole batch.
//! The group here is threads joined by a barrier: the same `Reducer` seam a networked group
//! plugs into.

use faer::Par;
use learner::{Alone, GroupError, Hyperparameters, Ppo, Reducer};
use policy::{ActorCritic, ModelMetadata, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::{Arc, Barrier, Mutex};

/// Each rank's (values, factors), put there before the barrier.
type Slots = Arc<Mutex<Vec<(Vec<f32>, Vec<f32>)>>>;

/// Threads of one process as a learner group.
struct Threads {
    rank: usize,
    size: usize,
    slots: Slots,
    barrier: Arc<Barrier>,
}

impl Reducer for Threads {
    fn shard(&self) -> (usize, usize) {
        (self.rank, self.size)
    }

    fn all_reduce(&mut self, _step: u64, values: &mut [f32], factors: Vec<f32>) -> Result<Vec<Vec<f32>>, GroupError> {
        self.slots.lock().unwrap()[self.rank] = (values.to_vec(), factors);
        self.barrier.wait();
        let every = {
            let slots = self.slots.lock().unwrap();
            values.fill(0.0);
            for (s, _) in slots.iter() {
                for (v, x) in values.iter_mut().zip(s) {
                    *v += x;
                }
            }
            slots.iter().map(|(_, f)| f.clone()).collect()
        };
        self.barrier.wait();
        Ok(every)
    }
}

fn episodes(model: &ActorCritic, n: usize, rng: &mut ChaCha8Rng) -> Vec<Trajectory> {
    let os = model.obs_size();
    (0..n)
        .map(|_| {
            let len = rng.random_range(5..40);
            let obs: Vec<f32> = (0..len * os).map(|_| rng.random_range(-1.0..1.0)).collect();
            let acts = model.act(&obs, len, false, rng, Par::Seq);
            Trajectory {
                world: "reinvent_base".into(),
                obs,
                choices: acts.iter().map(|a| a.choice).collect(),
                logp: acts.iter().map(|a| a.logp).collect(),
                values: acts.iter().map(|a| a.value).collect(),
                rewards: (0..len).map(|_| rng.random_range(0.0..1.0)).collect(),
                done: true,
                ..Default::default()
            }
        })
        .collect()
}

#[test]
fn issue_8_two_learners_make_one_learners_update() {
    // Every epoch, and an update that stops early on `target_kl`: the members stop together,
    // at the single learner's step.
    for target_kl in [None, Some(0.001)] {
        let stops = two_learners_against_one(target_kl);
        assert_eq!(stops > 0, target_kl.is_some(), "{target_kl:?}: {stops} updates stopped early");
    }
}

/// Three updates by one learner and by a team of two from the same start; returns how many
/// of them stopped early.
fn two_learners_against_one(target_kl: Option<f64>) -> usize {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let h = Hyperparameters { num_epochs: 3, target_kl, ..Hyperparameters::default() };
    let mut alone = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    let mut group: Vec<Ppo> = (0..2).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let slots = Arc::new(Mutex::new(vec![(Vec::new(), Vec::new()); 2]));
    let barrier = Arc::new(Barrier::new(2));
    let mut stopped = 0;
    for iteration in 0..3 {
        let trajs = episodes(&alone.model, 20, &mut rng);
        let one = alone.update_in(&trajs, &mut Alone);
        assert!(one.refused.is_none() && one.gradient_steps > 10, "{one:?}");
        let stats: Vec<_> = std::thread::scope(|s| {
            let handles: Vec<_> = group
                .iter_mut()
                .enumerate()
                .map(|(rank, ppo)| {
                    let (trajs, slots, barrier) = (&trajs, slots.clone(), barrier.clone());
                    s.spawn(move || ppo.update_in(trajs, &mut Threads { rank, size: 2, slots, barrier }))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        // The group's members hold the very same weights...
        assert_eq!(group[0].model, group[1].model, "iteration {iteration}");
        assert_eq!(stats[0].gradient_steps, one.gradient_steps);
        assert_eq!((stats[0].kl_stop, stats[1].kl_stop), (one.kl_stop, one.kl_stop), "iteration {iteration}");
        stopped += usize::from(one.kl_stop.is_some());
        // ...and they are one learner's, to float rounding.
        for (a, b) in
            [(&alone.model.pi.params, &group[0].model.pi.params), (&alone.model.v.params, &group[0].model.v.params)]
        {
            let worst = a.iter().zip(b.iter()).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            let scale = a.iter().map(|x| x.abs()).fold(0.0f32, f32::max);
            assert!(worst <= 1e-4 * scale.max(1.0), "iteration {iteration}: weights differ by {worst}");
        }
        assert!(
            (stats[0].policy_loss - one.policy_loss).abs() < 1e-3,
            "{} vs {}",
            stats[0].policy_loss,
            one.policy_loss
        );
        // And a real update happened.
        assert_ne!(alone.model, model);
    }
    stopped
}

/// Rank 0 of two, recording what the group summed at its first gradient step: exchange 0
/// (the policy tower) and exchange 1 (the value tower, the log-std gradient, the figures).
struct Recording {
    inner: Threads,
    first: Vec<Vec<f32>>,
}

impl Reducer for Recording {
    fn shard(&self) -> (usize, usize) {
        self.inner.shard()
    }
    fn all_reduce(&mut self, step: u64, values: &mut [f32], factors: Vec<f32>) -> Result<Vec<Vec<f32>>, GroupError> {
        let every = self.inner.all_reduce(step, values, factors)?;
        // Exchange 0 is the old policy's figures; 1 and 2 the first gradient step's parts.
        if (1..3).contains(&step) {
            assert_eq!(self.first.len() as u64, step - 1, "exchanges in order");
            self.first.push(values.to_vec());
        }
        Ok(every)
    }
}

#[test]
fn issue_8_the_summed_shares_are_the_whole_minibatch_gradient() {
    // One minibatch of the whole batch: what the group sums at its first step must be the
    // gradient of the mean loss over every sample (each share weighted by its size; Adam is
    // blind to a constant factor, so this is checked on the gradient itself).
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let trajs = episodes(&model, 7, &mut rng);
    let n = trajs.iter().map(|t| t.len()).sum::<usize>();
    let h = Hyperparameters { num_epochs: 1, batch_size: n, ..Hyperparameters::default() };
    let batch = learner::ppo::make_batch_for(&trajs, &model, h.discount_factor, Par::Seq);
    let all: Vec<usize> = (0..n).collect();
    let whole = learner::ppo::loss_and_grad(&model, &batch, &all, &h, Par::Seq);
    let slots = Arc::new(Mutex::new(vec![(Vec::new(), Vec::new()); 2]));
    let barrier = Arc::new(Barrier::new(2));
    let mut group: Vec<Ppo> = (0..2).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let summed = std::thread::scope(|s| {
        let mut it = group.iter_mut();
        let (p0, p1) = (it.next().unwrap(), it.next().unwrap());
        let (t, sl, b) = (&trajs, slots.clone(), barrier.clone());
        let first = s.spawn(move || {
            let mut r = Recording { inner: Threads { rank: 0, size: 2, slots: sl, barrier: b }, first: Vec::new() };
            p0.update_in(t, &mut r);
            r.first
        });
        let (t, sl, b) = (&trajs, slots.clone(), barrier.clone());
        s.spawn(move || p1.update_in(t, &mut Threads { rank: 1, size: 2, slots: sl, barrier: b }));
        first.join().unwrap()
    });
    let (policy, value) = (&summed[0], &summed[1]);
    assert_eq!((policy.len(), value.len()), (whole.grad_pi.len(), whole.grad_v.len() + 2 + 6));
    for (name, grad, sum) in
        [("policy", &whole.grad_pi, &policy[..]), ("value", &whole.grad_v, &value[..whole.grad_v.len()])]
    {
        let worst = grad.iter().zip(sum).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let scale = grad.iter().map(|a| a.abs()).fold(0.0f32, f32::max);
        assert!(
            scale > 0.0 && worst <= 1e-4 * scale,
            "the {name} tower's summed shares differ from the whole gradient by {worst} (scale {scale})"
        );
    }
    let total = value[whole.grad_v.len() + 2 + 3];
    assert!((total as f64 - whole.total).abs() < 1e-4 * whole.total.abs().max(1.0), "{total} vs {}", whole.total);
}

/// A member that cannot reach the others refuses the update and keeps its weights.
struct Broken;

impl Reducer for Broken {
    fn shard(&self) -> (usize, usize) {
        (1, 2)
    }
    fn all_reduce(&mut self, step: u64, _values: &mut [f32], _factors: Vec<f32>) -> Result<Vec<Vec<f32>>, GroupError> {
        Err(GroupError(format!("peer gone at step {step}")))
    }
}

#[test]
fn issue_8_a_broken_group_refuses_the_update_and_keeps_the_weights() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let mut ppo = Ppo::new(model.clone(), Hyperparameters::default(), 7, 5, Par::Seq);
    let trajs = episodes(&ppo.model, 20, &mut rng);
    let stats = ppo.update_in(&trajs, &mut Broken);
    assert!(stats.refused.as_deref().is_some_and(|r| r.contains("peer gone")), "{stats:?}");
    assert_eq!(ppo.model, model);
    assert_eq!(ppo.version, 7);
}

#[test]
fn issue_8_a_joiner_that_takes_the_state_makes_the_same_updates_bit_for_bit() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let h = Hyperparameters { num_epochs: 2, ..Hyperparameters::default() };
    let mut leader = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    for _ in 0..2 {
        let trajs = episodes(&leader.model, 12, &mut rng);
        leader.update(&trajs);
    }
    // A fresh learner (other initial weights, no optimiser history) takes the leader's state.
    let other = ActorCritic::new(&meta, 27, &mut ChaCha8Rng::seed_from_u64(99));
    let mut joiner = Ppo::new(other, h.clone(), 0, 77, Par::Seq);
    joiner.restore(leader.state()).unwrap();
    assert_eq!(joiner.version, leader.version);
    assert_eq!(joiner.state(), leader.state());
    // From the same plan (trajectories and shuffle seed) both make the same update. Without
    // the optimiser's moments it would differ: Adam's step depends on them.
    let trajs = episodes(&leader.model, 12, &mut rng);
    let seed = leader.draw_seed();
    let mut no_moments = Ppo::new(leader.model.clone(), h, leader.version, 5, Par::Seq);
    leader.update_planned(&trajs, seed, &mut Alone);
    joiner.update_planned(&trajs, seed, &mut Alone);
    no_moments.update_planned(&trajs, seed, &mut Alone);
    assert_eq!(joiner.model, leader.model);
    assert_ne!(no_moments.model, leader.model);
}

#[test]
fn issue_8_a_state_that_does_not_fit_is_refused_and_changes_nothing() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let mut ppo = Ppo::new(model.clone(), Hyperparameters::default(), 3, 5, Par::Seq);
    let good = ppo.state();
    let mut short = good.clone();
    short.tensors[0].1.pop();
    let mut missing = good.clone();
    missing.tensors.retain(|(n, _)| n != "adam.v.m");
    let mut extra = good.clone();
    extra.tensors.push(("mystery".into(), vec![1.0]));
    let mut bad_count = good.clone();
    bad_count.tensors.iter_mut().find(|(n, _)| n == "adam.pi.t").unwrap().1[0] = 0.5;
    for (bad, why) in [(short, "values"), (missing, "adam.v.m"), (extra, "mystery"), (bad_count, "count")] {
        let mut s = bad;
        s.version = 40;
        let e = ppo.restore(s).unwrap_err().to_string();
        assert!(e.contains(why), "{e}");
        assert_eq!(ppo.state(), good, "nothing changed");
    }
}

#[test]
fn issue_8_camera_network_team_sends_factors_and_makes_one_learners_update() {
    // DeepRacer's SHALLOW network: its first dense layer (11.5 M weights) travels as its
    // factors (each share's inputs and output gradients), multiplied out by every member.
    let meta = ModelMetadata::parse(
        r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":0,"speed":1},{"steering_angle":30,"speed":1}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW","version":"5"}"#,
        "test",
    )
    .unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    assert_eq!(model.pi.factorable(64).len(), 1, "the big dense layer is factored");
    let os = model.obs_size();
    let trajs: Vec<Trajectory> = (0..2)
        .map(|_| {
            let len = 64;
            let obs: Vec<f32> = (0..len * os).map(|_| rng.random_range(0..=255u8) as f32).collect();
            let acts = model.act(&obs, len, false, &mut rng, Par::Seq);
            Trajectory {
                world: "reinvent_base".into(),
                obs,
                choices: acts.iter().map(|a| a.choice).collect(),
                logp: acts.iter().map(|a| a.logp).collect(),
                values: acts.iter().map(|a| a.value).collect(),
                rewards: (0..len).map(|_| rng.random_range(0.0..1.0)).collect(),
                done: true,
                ..Default::default()
            }
        })
        .collect();
    let h = Hyperparameters { num_epochs: 1, batch_size: 64, ..Hyperparameters::default() };
    let mut alone = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    let one = alone.update_in(&trajs, &mut Alone);
    assert!(one.refused.is_none() && one.gradient_steps == 2, "{one:?}");
    let mut group: Vec<Ppo> = (0..2).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let slots = Arc::new(Mutex::new(vec![(Vec::new(), Vec::new()); 2]));
    let barrier = Arc::new(Barrier::new(2));
    std::thread::scope(|s| {
        for (rank, ppo) in group.iter_mut().enumerate() {
            let (trajs, slots, barrier) = (&trajs, slots.clone(), barrier.clone());
            s.spawn(move || {
                let st = ppo.update_in(trajs, &mut Threads { rank, size: 2, slots, barrier });
                assert!(st.refused.is_none(), "{st:?}");
            });
        }
    });
    assert_eq!(group[0].model, group[1].model, "the members hold the same weights");
    let flat = |m: &ActorCritic| m.pi.params.iter().chain(&m.v.params).copied().collect::<Vec<f32>>();
    let (start, one_w, team_w) = (flat(&model), flat(&alone.model), flat(&group[0].model));
    let dist = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>().sqrt();
    let (apart, moved) = (dist(&team_w, &one_w), dist(&one_w, &start));
    assert!(moved > 0.0 && apart <= 1e-2 * moved, "the team is {apart} from one learner, which moved {moved}");
}

/// Rank 0 of two, logging the calls: what it sent ahead must be what it then reduces.
struct Ordered {
    inner: Threads,
    log: Vec<(&'static str, u64)>,
    ahead: std::collections::BTreeMap<u64, (Vec<f32>, Vec<f32>)>,
}

impl Reducer for Ordered {
    fn shard(&self) -> (usize, usize) {
        self.inner.shard()
    }
    fn send(&mut self, step: u64, values: &[f32], factors: &[f32]) -> Result<(), GroupError> {
        self.log.push(("send", step));
        self.ahead.insert(step, (values.to_vec(), factors.to_vec()));
        Ok(())
    }
    fn all_reduce(&mut self, step: u64, values: &mut [f32], factors: Vec<f32>) -> Result<Vec<Vec<f32>>, GroupError> {
        self.log.push(("reduce", step));
        // Exchange 0 (the old policy's figures) is not sent ahead; every other one is.
        if step > 0 {
            assert_eq!(self.ahead.remove(&step), Some((values.to_vec(), factors.clone())), "exchange {step}");
        }
        self.inner.all_reduce(step, values, factors)
    }
}

#[test]
fn issue_8_a_team_step_sends_the_policy_towers_share_before_the_value_tower_runs() {
    // A gradient step makes two exchanges: the policy tower's share is sent as soon as its
    // backward pass ends, the value tower's (which exists only once that tower has run)
    // after it, and only then does the member wait for the others: first for the policy
    // tower (whose optimiser step then runs while the value tower's shares travel).
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let trajs = episodes(&model, 10, &mut rng);
    let h = Hyperparameters { num_epochs: 1, ..Hyperparameters::default() };
    let slots = Arc::new(Mutex::new(vec![(Vec::new(), Vec::new()); 2]));
    let barrier = Arc::new(Barrier::new(2));
    let mut group: Vec<Ppo> = (0..2).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let (log, steps) = std::thread::scope(|s| {
        let mut it = group.iter_mut();
        let (p0, p1) = (it.next().unwrap(), it.next().unwrap());
        let (t, sl, b) = (&trajs, slots.clone(), barrier.clone());
        let first = s.spawn(move || {
            let inner = Threads { rank: 0, size: 2, slots: sl, barrier: b };
            let mut r = Ordered { inner, log: Vec::new(), ahead: Default::default() };
            let st = p0.update_in(t, &mut r);
            assert!(r.ahead.is_empty(), "every exchange sent ahead was reduced");
            (r.log, st.gradient_steps)
        });
        let (t, sl, b) = (&trajs, slots.clone(), barrier.clone());
        s.spawn(move || p1.update_in(t, &mut Threads { rank: 1, size: 2, slots: sl, barrier: b }));
        first.join().unwrap()
    });
    assert!(steps >= 2, "{steps} gradient steps");
    // Exchange 0: the old policy's figures, each member's rows (issue 8: split like the
    // gradients, not worked out whole by every member).
    let expected: Vec<(&str, u64)> = std::iter::once(("reduce", 0))
        .chain(
            (0..steps as u64)
                .flat_map(|k| [("send", 2 * k + 1), ("send", 2 * k + 2), ("reduce", 2 * k + 1), ("reduce", 2 * k + 2)]),
        )
        .collect();
    assert_eq!(log, expected);
    assert_eq!(group[0].model, group[1].model, "the members hold the same weights");
}
