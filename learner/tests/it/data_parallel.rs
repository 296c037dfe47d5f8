//! Learners that train as one. In a team each tower is trained by its own members
//! (even ranks the policy tower, odd ranks the value tower), the members of a tower take a
//! share of every minibatch and sum their gradients in rank order, and the towers' states
//! are swapped once an update: the same update as one learner on the whole batch. The group
//! here is threads of one process: the same `Reducer` seam a networked team plugs into.

use faer::Par;
use learner::{Alone, GroupError, Hyperparameters, Ppo, Reducer};
use policy::{ActorCritic, ModelMetadata, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::support::Threads;

/// Each member's `update_in` on its own thread, each with its reducer; their stats in rank order.
fn run_team<R: Reducer + Send>(
    members: &mut [Ppo],
    reducers: Vec<R>,
    trajs: &[Trajectory],
) -> Vec<Result<learner::ppo::PpoStats, learner::Refused>> {
    std::thread::scope(|s| {
        let handles: Vec<_> = members
            .iter_mut()
            .zip(reducers)
            .map(|(ppo, mut r)| s.spawn(move || ppo.update_in(trajs, &mut r)))
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
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

/// Issue 8: two learners make one learner's update.
#[test]
fn two_learners_make_one_learners_update() {
    // Teams of two (a member a tower) and four (two a tower, each with half of every
    // minibatch); every epoch, an update that stops early on `target_kl` (the members stop
    // together, at the single learner's step), and one whose value tower trains in its first
    // epoch alone (the value members sit out the later steps together).
    for size in [2, 4] {
        for (target_kl, value_epochs) in [(None, None), (Some(0.001), None), (None, Some(1))] {
            let stops = team_against_one(size, target_kl, value_epochs);
            assert_eq!(stops > 0, target_kl.is_some(), "{size}, {target_kl:?}: {stops} updates stopped early");
        }
    }
}

/// Three updates by one learner and by a team of `size` from the same start; returns how
/// many of them stopped early.
fn team_against_one(size: usize, target_kl: Option<f64>, value_epochs: Option<usize>) -> usize {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let h = Hyperparameters { num_epochs: 3, target_kl, value_epochs, ..Hyperparameters::default() };
    let mut alone = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    let mut group: Vec<Ppo> = (0..size).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let mut stopped = 0;
    for iteration in 0..3 {
        let trajs = episodes(&alone.model, 20, &mut rng);
        let one = alone.update_in(&trajs, &mut Alone).unwrap();
        assert!(one.gradient_steps > 10, "{one:?}");
        let stats: Vec<_> = run_team(&mut group, Threads::team(size), &trajs).into_iter().map(Result::unwrap).collect();
        // The team's members hold the very same state, weights and optimiser...
        for (r, m) in group.iter().enumerate().skip(1) {
            assert!(m.state() == group[0].state(), "{size}: member {r}, iteration {iteration}");
        }
        for st in &stats {
            assert_eq!((st.gradient_steps, st.value_steps), (one.gradient_steps, one.value_steps));
            assert_eq!(st.kl_stop, one.kl_stop, "iteration {iteration}");
            assert_eq!(st.policy_version, one.policy_version);
        }
        stopped += usize::from(one.kl_stop.is_some());
        if value_epochs == Some(1) {
            assert_eq!(3 * one.value_steps, one.gradient_steps, "{one:?}");
        }
        // ...and it is one learner's, to float rounding.
        for (a, b) in
            [(&alone.model.pi.params, &group[0].model.pi.params), (&alone.model.v.params, &group[0].model.v.params)]
        {
            let worst = a.iter().zip(b.iter()).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            let scale = a.iter().map(|x| x.abs()).fold(0.0f32, f32::max);
            assert!(worst <= 1e-4 * scale.max(1.0), "{size}, iteration {iteration}: weights differ by {worst}");
        }
        for (team, one) in [
            (stats[0].policy_loss, one.policy_loss),
            (stats[0].value_loss, one.value_loss),
            (stats[0].approx_kl, one.approx_kl),
            (stats[0].entropy, one.entropy),
        ] {
            assert!((team - one).abs() < 1e-3 * one.abs().max(1.0), "{size}: {team} vs {one}");
        }
        // And a real update happened.
        assert_ne!(alone.model, model);
    }
    stopped
}

/// What a watcher sees of each exchange, after the team's sum: the update's number, the
/// exchange, the members that gave to it and the sum (which it may change).
type Watch<T> = fn(&mut T, u64, u64, &[usize], &mut [f32]);

/// A member whose exchanges are watched; the watcher keeps its notes in `seen`.
struct Watched<T> {
    inner: Threads,
    seen: T,
    watch: Watch<T>,
}

impl<T: Clone> Watched<T> {
    fn team(size: usize, seen: T, watch: Watch<T>) -> Vec<Watched<T>> {
        Threads::team(size).into_iter().map(|inner| Watched { inner, seen: seen.clone(), watch }).collect()
    }
}

impl<T> Reducer for Watched<T> {
    fn shard(&self) -> (usize, usize) {
        self.inner.shard()
    }
    fn all_reduce(
        &mut self,
        step: u64,
        ranks: &[usize],
        values: &mut [f32],
        factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError> {
        let every = self.inner.all_reduce(step, ranks, values, factors)?;
        (self.watch)(&mut self.seen, self.inner.update, step, ranks, values);
        Ok(every)
    }
}

/// Issue 8: the summed shares are the whole minibatch gradient.
#[test]
fn the_summed_shares_are_the_whole_minibatch_gradient() {
    // A team of four, one minibatch of the whole batch: what the two members of each tower
    // sum at the first step must be that tower's gradient of the mean loss over every sample
    // (each share weighted by its size; Adam is blind to a constant factor, so this is
    // checked on the gradient itself), and the figures the whole team sums the loss's.
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let trajs = episodes(&model, 7, &mut rng);
    let n = trajs.iter().map(|t| t.len()).sum::<usize>();
    let h = Hyperparameters { num_epochs: 1, batch_size: n, ..Hyperparameters::default() };
    let batch = learner::ppo::make_batch_for(&trajs, &model, h.discount_factor, Par::Seq);
    let all: Vec<usize> = (0..n).collect();
    let whole = learner::ppo::loss_and_grad(&model, &batch, &all, &h, Par::Seq);
    let mut group: Vec<Ppo> = (0..4).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    // Each member records what its team summed at its first gradient step (exchanges 1 and 2).
    let reducers = Watched::team(4, Vec::new(), |first, update, step, _, values| {
        if update == 1 && (1..3).contains(&step) {
            first.push((step, values.to_vec()));
        }
    });
    let summed: Vec<Vec<(u64, Vec<f32>)>> = std::thread::scope(|s| {
        let handles: Vec<_> = group
            .iter_mut()
            .zip(reducers)
            .map(|(ppo, mut r)| {
                let t = &trajs;
                s.spawn(move || {
                    ppo.update_in(t, &mut r).unwrap();
                    r.seen
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    // Ranks 0 and 2 train the policy tower, 1 and 3 the value tower: both make exchange 1.
    let (policy, value) = (&summed[0][0], &summed[1][0]);
    assert_eq!((policy.0, value.0), (1, 1));
    assert_eq!(summed[2][0], summed[0][0], "the policy tower's members hold the same sum");
    let (policy, value) = (&policy.1, &value.1);
    assert_eq!((policy.len(), value.len()), (whole.grad_pi.len() + 2 + 4, whole.grad_v.len() + 1));
    for (name, grad, sum) in [
        ("policy", &whole.grad_pi, &policy[..whole.grad_pi.len()]),
        ("value", &whole.grad_v, &value[..whole.grad_v.len()]),
    ] {
        let worst = grad.iter().zip(sum).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let scale = grad.iter().map(|a| a.abs()).fold(0.0f32, f32::max);
        assert!(
            scale > 0.0 && worst <= 1e-4 * scale,
            "the {name} tower's summed shares differ from the whole gradient by {worst} (scale {scale})"
        );
    }
    // Exchange 2, the whole team's: policy loss, entropy, KL, clip fraction, value loss, and
    // no member's step failed.
    let figures = &summed[0][1];
    assert_eq!(figures.0, 2);
    let f = &figures.1;
    let close = |a: f32, b: f64| (a as f64 - b).abs() < 1e-4 * b.abs().max(1.0);
    assert!(close(f[0], whole.policy_loss) && close(f[1], whole.entropy) && close(f[4], whole.value_loss), "{f:?}");
    assert_eq!(f[5], 0.0, "every member's step was finite");
    let total = f[0] as f64 - h.beta_entropy * f[1] as f64 + f[4] as f64;
    assert!((total - whole.total).abs() < 1e-4 * whole.total.abs().max(1.0), "{total} vs {}", whole.total);
}

/// A member that cannot reach the others refuses the update and keeps its weights.
struct Broken;

impl Reducer for Broken {
    fn shard(&self) -> (usize, usize) {
        (1, 2)
    }
    fn all_reduce(
        &mut self,
        step: u64,
        _ranks: &[usize],
        _values: &mut [f32],
        _factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError> {
        Err(GroupError(format!("peer gone at step {step}")))
    }
}

/// Issue 8: a broken group refuses the update and keeps the weights.
#[test]
fn a_broken_group_refuses_the_update_and_keeps_the_weights() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let mut ppo = Ppo::new(model.clone(), Hyperparameters::default(), 7, 5, Par::Seq);
    let trajs = episodes(&ppo.model, 20, &mut rng);
    let refused = ppo.update_in(&trajs, &mut Broken).unwrap_err();
    assert!(refused.is_group() && refused.to_string().contains("peer gone"), "{refused:?}");
    assert_eq!(ppo.model, model);
    assert_eq!(ppo.version, 7);
}

/// Issue 8: a joiner that takes the state makes the same updates bit for bit.
#[test]
fn a_joiner_that_takes_the_state_makes_the_same_updates_bit_for_bit() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let h = Hyperparameters { num_epochs: 2, ..Hyperparameters::default() };
    let mut leader = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    for _ in 0..2 {
        let trajs = episodes(&leader.model, 12, &mut rng);
        leader.update(&trajs).unwrap();
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
    leader.update_planned(&trajs, seed, &mut Alone).unwrap();
    joiner.update_planned(&trajs, seed, &mut Alone).unwrap();
    no_moments.update_planned(&trajs, seed, &mut Alone).unwrap();
    assert_eq!(joiner.model, leader.model);
    assert_ne!(no_moments.model, leader.model);
}

/// Issue 8: a state that does not fit is refused and changes nothing.
#[test]
fn a_state_that_does_not_fit_is_refused_and_changes_nothing() {
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

/// Issue 8: a camera network's team sends factors and makes one learner's update.
#[test]
fn camera_network_team_sends_factors_and_makes_one_learners_update() {
    // DeepRacer's SHALLOW network in a team of four (two members a tower): its first dense
    // layer (5.8 M weights a tower) travels as its factors (each share's inputs and output
    // gradients), multiplied out by both members of the tower.
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
    let one = alone.update_in(&trajs, &mut Alone).unwrap();
    assert!(one.gradient_steps == 2, "{one:?}");
    let mut group: Vec<Ppo> = (0..4).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    let stats = run_team(&mut group, Threads::team(4), &trajs);
    assert!(stats.iter().all(|st| st.is_ok()), "{stats:?}");
    for m in &group[1..] {
        assert!(m.model == group[0].model, "the members hold the same weights");
    }
    let flat = |m: &ActorCritic| m.pi.params.iter().chain(&m.v.params).copied().collect::<Vec<f32>>();
    let (start, one_w, team_w) = (flat(&model), flat(&alone.model), flat(&group[0].model));
    let dist = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>().sqrt();
    let (apart, moved) = (dist(&team_w, &one_w), dist(&one_w, &start));
    assert!(moved > 0.0 && apart <= 1e-2 * moved, "the team is {apart} from one learner, which moved {moved}");
}

/// Exchanges as a member made them: the exchange, and the members that gave to it.
type Log = Vec<(u64, Vec<usize>)>;

/// Issue 8: a team trains each tower on its own members and swaps them once an update.
#[test]
fn a_team_trains_each_tower_on_its_own_members_and_swaps_them_once_an_update() {
    // No member repeats the other tower's optimiser step: in a team of four, ranks 0 and 2
    // train the policy tower and sum only their shares of it (exchange 2k + 1), ranks 1 and 3
    // the value tower; every step ends with the whole team's figures (2k + 2). After the
    // last step rank 0 gives the policy tower's state to ranks 1 and 3 (2K + 1), rank 1 the
    // value tower's to ranks 0 and 2 (2K + 2), each sending its own before it waits.
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let trajs = episodes(&model, 10, &mut rng);
    let h = Hyperparameters { num_epochs: 1, ..Hyperparameters::default() };
    let mut group: Vec<Ppo> = (0..4).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    // Each member logs its exchanges.
    let reducers = Watched::team(4, Log::new(), |log, _, step, ranks, _| log.push((step, ranks.to_vec())));
    let logs: Vec<(Log, usize)> = std::thread::scope(|s| {
        let handles: Vec<_> = group
            .iter_mut()
            .zip(reducers)
            .map(|(ppo, mut r)| {
                let t = &trajs;
                s.spawn(move || {
                    let st = ppo.update_in(t, &mut r);
                    let st = st.unwrap();
                    (r.seen, st.gradient_steps)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let steps = logs[0].1 as u64;
    assert!(steps >= 2, "{steps} gradient steps");
    let everyone = vec![0, 1, 2, 3];
    for (rank, (log, _)) in logs.iter().enumerate() {
        let tower = if rank % 2 == 0 { vec![0, 2] } else { vec![1, 3] };
        // Exchange 0: the old policy's figures, each member's rows.
        let mut expected = vec![(0, everyone.clone())];
        for k in 0..steps {
            expected.push((2 * k + 1, tower.clone()));
            expected.push((2 * k + 2, everyone.clone()));
        }
        let (give, take) = ((2 * steps + 1, vec![0]), (2 * steps + 2, vec![1]));
        match rank {
            0 => expected.extend([give, take]),
            1 => expected.extend([take, give]),
            2 => expected.push(take),
            _ => expected.push(give),
        }
        assert_eq!(log, &expected, "rank {rank}");
    }
    for m in &group[1..] {
        assert!(m.state() == group[0].state(), "the members hold the same state");
    }
}

/// A change made to a state on its way.
type Tamper = fn(&mut [f32]);

/// Issue 8: a tower state that does not fit refuses the update and changes nothing.
#[test]
fn a_tower_state_that_does_not_fit_refuses_the_update_and_changes_nothing() {
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let trajs = episodes(&model, 10, &mut rng);
    let h = Hyperparameters { num_epochs: 1, ..Hyperparameters::default() };
    let cases: [(Tamper, &str); 4] = [
        (|v| *v.last_mut().unwrap() = 0.5, "step count 0.5 is not a count"),
        (|v| v[3] = f32::NAN, "NaN at position 3"),
        (|v| v[7] = f32::INFINITY, "inf at position 7"),
        (|v| v[v.len() - 2] = -1.0, "second moment is negative"),
    ];
    for (tamper, why) in cases {
        let mut p0 = Ppo::new(model.clone(), h.clone(), 4, 5, Par::Seq);
        let mut p1 = Ppo::new(model.clone(), h.clone(), 4, 5, Par::Seq);
        let before = p0.state();
        let mut team = Threads::team(2).into_iter();
        let (t0, t1) = (team.next().unwrap(), team.next().unwrap());
        // Rank 0 receives a value tower state that was tampered with.
        let watch: Watch<Tamper> = |tamper, _, _, ranks, values| {
            if ranks == [1] {
                tamper(values)
            }
        };
        let mut r0 = Watched { inner: t0, seen: tamper, watch };
        let (s0, s1) = std::thread::scope(|s| {
            let a = s.spawn(|| p0.update_in(&trajs, &mut r0));
            let b = s.spawn(|| p1.update_in(&trajs, &mut { t1 }));
            (a.join().unwrap(), b.join().unwrap())
        });
        assert!(s1.is_ok(), "{s1:?}");
        let refused = s0.unwrap_err();
        let e = refused.to_string();
        assert!(refused.is_group() && e.contains(why) && e.contains("version 4"), "{why}: {e}");
        assert!(p0.state() == before, "{why}: the update was taken back whole");
    }
}

/// Issue 30: the value tower's warm-up holds the policy, alone and in a team.
#[test]
fn the_value_towers_warm_up_holds_the_policy_alone_and_in_a_team() {
    // An imported model's first updates (policy versions below `value_warmup_updates`) train
    // the value tower only; then the policy moves, alone and in a team alike.
    let meta = ModelMetadata::default_state_vector();
    let mut rng = ChaCha8Rng::seed_from_u64(30);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let h = Hyperparameters { num_epochs: 2, target_kl: None, value_warmup_updates: 2, ..Hyperparameters::default() };
    let mut alone = Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq);
    let mut group: Vec<Ppo> = (0..2).map(|_| Ppo::new(model.clone(), h.clone(), 0, 5, Par::Seq)).collect();
    for update in 0..3 {
        let (pi, v) = (alone.model.pi.clone(), alone.model.v.clone());
        let trajs = episodes(&alone.model, 20, &mut rng);
        alone.update_in(&trajs, &mut Alone).unwrap();
        for r in run_team(&mut group, Threads::team(2), &trajs) {
            r.unwrap();
        }
        assert_ne!(alone.model.v, v, "update {update}: the value tower learns");
        assert_eq!(alone.model.pi == pi, update < 2, "update {update}: the policy is held during the warm-up only");
        for m in &group {
            assert_eq!(m.model.pi == pi, update < 2, "team, update {update}");
            assert_ne!(m.model.v, v, "team, update {update}");
        }
    }
}
