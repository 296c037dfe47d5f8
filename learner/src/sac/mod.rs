//! Soft actor-critic as DeepRacer trains it (COACH's `SoftActorCriticAgent`, read in
//! `../shared/reference/races-sensors-sac.md` §5): three networks without shared weights,
//! the policy a tanh-squashed Gaussian, twin Q heads on one embedder, V with a target copy;
//! per gradient step, on one batch and the weights as they were:
//!
//! 1. policy: `mean(α·log π(a|s) − min(q1, q2)(s, a))`, `a ~ π(s)` reparameterised, the
//!    gradient flowing through the Q heads' action input into the policy alone;
//! 2. V: `V(s)` against `min(q1, q2)(s, a) − α·log π(a|s)` (the same draw), mean squared
//!    error or Huber (`loss_type`);
//! 3. Q: each head against `r + (1 − done)·γ·V_target(s')`, `0.5·mean((q − y)²)` each, the
//!    batch's actions.
//!
//! The target copy follows V by `tau` once per iteration ([`Sac::update_target`]): DeepRacer's
//! τ = 1 is a hard copy. Paddock's one addition to the update is the temperature tuned to a
//! target entropy (`target_entropy`; DeepRacer's `sac_alpha` is fixed). The Q heads take the
//! action as the policy gives it, in [-1, 1]; DeepRacer's take it rescaled to the environment's
//! units (degrees, m/s), a choice of input scale invisible outside the learner.

mod on_gpu;
pub mod replay;
pub mod trainer;

use crate::group::{Alone, GroupError, Reducer, check_factors, factored_grads, kept, skipped};
use crate::update::StateMismatch;
use faer::Par;
use policy::model::{SAC_LOG_STD_RANGE, Squashed, sac_policy, sac_q_embedder, sac_q_head, sac_value, squashed};
use policy::nn::{Adam, Deferral, Factors, Net, Tape};
use policy::{ActionSpace, ModelMetadata};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

pub use on_gpu::{SacGpu, Session as SacSession};
pub use replay::{BadMemory, Replay, ReplayError};
pub use trainer::{SacFigures, SacStats, SacTrainer};

/// What one SAC update does, from `hyperparameters.json` and the action space.
#[derive(Clone, Debug, PartialEq)]
pub struct SacSettings {
    /// Transitions per gradient step (`batch_size`).
    pub batch_size: usize,
    /// Adam's rate for all three networks (`lr`).
    pub lr: f32,
    /// γ (`discount_factor`).
    pub gamma: f32,
    /// The temperature (`sac_alpha`): fixed, or where the tuning starts.
    pub alpha: f32,
    /// Tune the temperature so that the policy's entropy approaches this (nats); `None`:
    /// `alpha` stays as it is, as in DeepRacer.
    pub target_entropy: Option<f32>,
    /// How far the V target moves towards V at each [`Sac::update_target`] (1: a copy).
    pub tau: f32,
    /// V's loss is Huber (δ = 1) rather than the mean squared error (`loss_type`).
    pub huber: bool,
    /// Half the range of each action in the environment's units (steering degrees, m/s):
    /// the scale in log π's tanh correction.
    pub scale: [f32; 2],
}

impl SacSettings {
    /// DeepRacer's defaults for a continuous action space.
    pub fn for_space(space: &ActionSpace) -> Option<SacSettings> {
        let ActionSpace::Continuous { steering_angle, speed } = space else { return None };
        let half = |r: &(f64, f64)| ((r.1 - r.0) / 2.0) as f32;
        Some(SacSettings {
            batch_size: 64,
            lr: 3e-4,
            gamma: 0.999,
            alpha: 0.2,
            target_entropy: None,
            tau: 1.0,
            huber: false,
            scale: [half(steering_angle), half(speed)],
        })
    }
}

/// The twin Q network: one embedder, two heads on the embedding and the action.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinQ {
    /// The sensors' embedder; `None`: the observation goes to the heads as it is.
    pub embed: Option<Net>,
    /// `q1_head`.
    pub q1: Net,
    /// `q2_head`.
    pub q2: Net,
}

/// SAC's networks.
#[derive(Clone, Debug, PartialEq)]
pub struct SacNets {
    /// The policy: means and log-stds (what is published and driven).
    pub policy: Net,
    /// The critics.
    pub q: TwinQ,
    /// The state value.
    pub v: Net,
    /// V's target copy.
    pub v_target: Net,
}

impl SacNets {
    /// Fresh networks for `meta` (its action space must be continuous).
    pub fn new(meta: &ModelMetadata, obs_size: usize, rng: &mut impl rand::Rng) -> SacNets {
        let policy = sac_policy(meta, obs_size, rng);
        let embed = sac_q_embedder(meta, obs_size, rng);
        let width = embed.as_ref().map_or(policy.in_size(), |e| e.out_size());
        let (q1, q2) = (sac_q_head(width, rng), sac_q_head(width, rng));
        let v = sac_value(meta, obs_size, rng);
        SacNets { policy, q: TwinQ { embed, q1, q2 }, v_target: v.clone(), v }
    }

    /// Values per observation.
    pub fn obs_size(&self) -> usize {
        self.policy.in_size()
    }
}

/// A batch of transitions, row-major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Batch {
    /// `len × obs` observations.
    pub obs: Vec<f32>,
    /// `len × 2` actions in [-1, 1] (the policy's `tanh(u)`).
    pub action: Vec<f32>,
    /// Rewards.
    pub reward: Vec<f32>,
    /// 1 where the episode ended at the step (no bootstrap), else 0.
    pub done: Vec<f32>,
    /// `len × obs` next observations.
    pub next_obs: Vec<f32>,
}

impl Batch {
    /// The transitions `rows` of the batch.
    pub fn rows(&self, rows: std::ops::Range<usize>) -> Batch {
        let per = if self.is_empty() { 0 } else { self.obs.len() / self.len() };
        Batch {
            obs: self.obs[rows.start * per..rows.end * per].to_vec(),
            action: self.action[2 * rows.start..2 * rows.end].to_vec(),
            reward: self.reward[rows.clone()].to_vec(),
            done: self.done[rows.clone()].to_vec(),
            next_obs: self.next_obs[rows.start * per..rows.end * per].to_vec(),
        }
    }

    /// Transitions held.
    pub fn len(&self) -> usize {
        self.reward.len()
    }

    /// No transitions.
    pub fn is_empty(&self) -> bool {
        self.reward.is_empty()
    }
}

/// The three losses, and what the logs show of an update.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Losses {
    /// `mean(α·log π − min q)`.
    pub policy: f64,
    /// The two Q heads' loss.
    pub q: f64,
    /// V's loss.
    pub v: f64,
    /// `mean(−log π)` of the policy's draws.
    pub entropy: f64,
    /// `mean(min(q1, q2))` at the policy's draws.
    pub q_mean: f64,
    /// The temperature used.
    pub alpha: f64,
}

/// The dense layers of each network whose weight gradient is left as its factors (inputs and
/// output gradients) until Adam multiplies it out: for a camera network's big layers the
/// factors of a batch are a fraction of the product, and they are what a learner team's
/// members exchange. Empty: every gradient in full.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Defer {
    /// The policy's layers.
    pub policy: Vec<usize>,
    /// `q1`'s.
    pub q1: Vec<usize>,
    /// `q2`'s.
    pub q2: Vec<usize>,
    /// V's.
    pub v: Vec<usize>,
}

impl Defer {
    /// The layers worth factoring for batches of `batch` transitions
    /// ([`Net::factorable`]); the Q embedder has none (convolutions only).
    pub fn for_batch(nets: &SacNets, batch: usize) -> Defer {
        Defer {
            policy: nets.policy.factorable(batch),
            q1: nets.q.q1.factorable(batch),
            q2: nets.q.q2.factorable(batch),
            v: nets.v.factorable(batch),
        }
    }

    /// Nothing deferred.
    pub fn none() -> Defer {
        Defer::default()
    }
}

/// The deferred layers' factors, per network (last layer first, as a backward pass pushes
/// them).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Deferred {
    /// The policy's.
    pub policy: Vec<Factors>,
    /// `q1`'s.
    pub q1: Vec<Factors>,
    /// `q2`'s.
    pub q2: Vec<Factors>,
    /// V's.
    pub v: Vec<Factors>,
}

impl Deferred {
    fn parts(&self) -> [&Vec<Factors>; 4] {
        [&self.policy, &self.q1, &self.q2, &self.v]
    }
}

/// Parameter gradients of the three losses (and the temperature's).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Grads {
    /// Of the policy loss wrt the policy's parameters.
    pub policy: Vec<f32>,
    /// Of the Q loss wrt the embedder's parameters (empty without one).
    pub q_embed: Vec<f32>,
    /// Of the Q loss wrt `q1`'s.
    pub q1: Vec<f32>,
    /// Of the Q loss wrt `q2`'s.
    pub q2: Vec<f32>,
    /// Of V's loss wrt V's.
    pub v: Vec<f32>,
    /// Of the temperature's loss wrt log α (0 when the temperature is fixed).
    pub log_alpha: f32,
    /// The deferred layers' weight gradients, as factors (their places in the vectors above
    /// hold zeros).
    pub factors: Deferred,
}

impl Grads {
    /// Each network's gradient with its deferred layers' factors, in exchange order: the
    /// policy, the Q embedder (none deferred), `q1`, `q2`, V.
    fn parts(&self) -> [(&Vec<f32>, &[Factors]); 5] {
        let f = &self.factors;
        [(&self.policy, &f.policy), (&self.q_embed, &[]), (&self.q1, &f.q1), (&self.q2, &f.q2), (&self.v, &f.v)]
    }

    /// [`Grads::parts`], the gradients to write.
    fn parts_mut(&mut self) -> [(&mut Vec<f32>, &[Factors]); 5] {
        let f = &self.factors;
        [
            (&mut self.policy, &f.policy),
            (&mut self.q_embed, &[]),
            (&mut self.q1, &f.q1),
            (&mut self.q2, &f.q2),
            (&mut self.v, &f.v),
        ]
    }
}

/// Buffers kept between gradient steps.
#[derive(Debug, Default)]
pub struct Tapes {
    policy: Tape,
    embed: Tape,
    q1: Tape,
    q2: Tape,
    v: Tape,
    target: Tape,
    x: Vec<f32>,
    dx1: Vec<f32>,
    dx2: Vec<f32>,
    scratch1: Vec<f32>,
    scratch2: Vec<f32>,
}

/// The three losses on `batch` and their gradients, with the weights as they are: `eps`
/// (`len × 2`) is the standard-normal noise of the policy's draws, so the result is a
/// function of the weights alone (what the finite-difference checks need).
pub fn losses_and_grads(
    nets: &SacNets,
    s: &SacSettings,
    alpha: f32,
    batch: &Batch,
    eps: &[f32],
    par: Par,
    t: &mut Tapes,
) -> (Losses, Grads) {
    let share = Share { batch, eps, weight: 1.0 / batch.len().max(1) as f32 };
    losses_and_grads_share(nets, s, alpha, share, &Defer::none(), par, t)
}

/// A learner's share of a batch: its transitions, their noise (two values each), and the
/// weight of each (one over the whole batch's size).
#[derive(Clone, Copy, Debug)]
pub struct Share<'a> {
    /// The share's transitions.
    pub batch: &'a Batch,
    /// Two noise values per transition.
    pub eps: &'a [f32],
    /// Each transition's weight in the losses and gradients.
    pub weight: f32,
}

/// [`losses_and_grads`] of `share` of a batch: the shares' losses and gradients add up to
/// the batch's. The weight gradients of the layers `defer` are left as their factors.
pub fn losses_and_grads_share(
    nets: &SacNets,
    s: &SacSettings,
    alpha: f32,
    share: Share<'_>,
    defer: &Defer,
    par: Par,
    t: &mut Tapes,
) -> (Losses, Grads) {
    let Share { batch, eps, weight } = share;
    let b = batch.len();
    let inv = weight;
    assert_eq!(eps.len(), 2 * b, "two noise values per transition");
    let mut g = Grads {
        policy: vec![0.0; nets.policy.params.len()],
        q_embed: vec![0.0; nets.q.embed.as_ref().map_or(0, |e| e.params.len())],
        q1: vec![0.0; nets.q.q1.params.len()],
        q2: vec![0.0; nets.q.q2.params.len()],
        v: vec![0.0; nets.v.params.len()],
        log_alpha: 0.0,
        factors: Deferred::default(),
    };
    if b == 0 {
        return (Losses { alpha: alpha as f64, ..Losses::default() }, g);
    }
    // The policy's draws.
    nets.policy.forward(&batch.obs, b, &mut t.policy, par);
    let out = t.policy.output().to_vec();
    let draws: Vec<Squashed> =
        (0..b).map(|i| squashed(&out[i * 4..i * 4 + 4], [eps[2 * i], eps[2 * i + 1]], s.scale)).collect();
    // The Q embedding of s, used by both evaluations of the heads.
    let emb = match &nets.q.embed {
        Some(e) => {
            e.forward(&batch.obs, b, &mut t.embed, par);
            t.embed.output().to_vec()
        }
        None => batch.obs.clone(),
    };
    let width = emb.len() / b.max(1);
    let heads_on = |x: &mut Vec<f32>, actions: &mut dyn Iterator<Item = [f32; 2]>| {
        x.clear();
        for (row, a) in emb.chunks_exact(width).zip(actions) {
            x.extend_from_slice(row);
            x.extend_from_slice(&a);
        }
    };
    // Q: the batch's actions against r + (1 − done)·γ·V_target(s').
    nets.v_target.forward(&batch.next_obs, b, &mut t.target, par);
    let v_next = t.target.output().to_vec();
    heads_on(&mut t.x, &mut batch.action.chunks_exact(2).map(|a| [a[0], a[1]]));
    nets.q.q1.forward(&t.x, b, &mut t.q1, par);
    nets.q.q2.forward(&t.x, b, &mut t.q2, par);
    let (mut d1, mut d2) = (vec![0.0f32; b], vec![0.0f32; b]);
    let mut q_loss = 0.0f64;
    for i in 0..b {
        let y = batch.reward[i] + (1.0 - batch.done[i]) * s.gamma * v_next[i];
        let (e1, e2) = (t.q1.output()[i] - y, t.q2.output()[i] - y);
        q_loss += 0.5 * (e1 as f64).powi(2) + 0.5 * (e2 as f64).powi(2);
        d1[i] = e1 * inv;
        d2[i] = e2 * inv;
    }
    nets.q.q1.backward_input_factored(
        &mut t.q1,
        &d1,
        &mut g.q1,
        par,
        Deferral { layers: &defer.q1, factors: &mut g.factors.q1 },
        &mut t.dx1,
    );
    nets.q.q2.backward_input_factored(
        &mut t.q2,
        &d2,
        &mut g.q2,
        par,
        Deferral { layers: &defer.q2, factors: &mut g.factors.q2 },
        &mut t.dx2,
    );
    if let Some(e) = &nets.q.embed {
        let d_emb: Vec<f32> = (t.dx1.chunks_exact(width + 2).zip(t.dx2.chunks_exact(width + 2)))
            .flat_map(|(r1, r2)| r1[..width].iter().zip(&r2[..width]).map(|(x, y)| x + y).collect::<Vec<_>>())
            .collect();
        e.backward(&mut t.embed, &d_emb, &mut g.q_embed, par);
    }
    // The policy's draws through the heads: min(q1, q2) and its gradient wrt the action.
    heads_on(&mut t.x, &mut draws.iter().map(|d| d.a));
    nets.q.q1.forward(&t.x, b, &mut t.q1, par);
    nets.q.q2.forward(&t.x, b, &mut t.q2, par);
    let (q1p, q2p) = (t.q1.output().to_vec(), t.q2.output().to_vec());
    let min_q: Vec<f32> = q1p.iter().zip(&q2p).map(|(a, b)| a.min(*b)).collect();
    let first: Vec<bool> = q1p.iter().zip(&q2p).map(|(a, b)| a <= b).collect();
    let dm1: Vec<f32> = first.iter().map(|&f| if f { -inv } else { 0.0 }).collect();
    let dm2: Vec<f32> = first.iter().map(|&f| if f { 0.0 } else { -inv }).collect();
    t.scratch1.clear();
    t.scratch1.resize(g.q1.len(), 0.0);
    t.scratch2.clear();
    t.scratch2.resize(g.q2.len(), 0.0);
    nets.q.q1.backward_input(&mut t.q1, &dm1, &mut t.scratch1, par, &mut t.dx1);
    nets.q.q2.backward_input(&mut t.q2, &dm2, &mut t.scratch2, par, &mut t.dx2);
    let mut d_out = vec![0.0f32; 4 * b];
    let (mut pi_loss, mut ent, mut qm) = (0.0f64, 0.0f64, 0.0f64);
    for (i, d) in draws.iter().enumerate() {
        pi_loss += (alpha * d.logp - min_q[i]) as f64;
        ent -= d.logp as f64;
        qm += min_q[i] as f64;
        for k in 0..2 {
            let a = d.a[k];
            let slope = 1.0 - a * a;
            let jac = s.scale[k] * slope + f32::EPSILON;
            let d_corr = if jac > 1e-10 && jac < 1.0 { 2.0 * a * s.scale[k] * slope / jac } else { 0.0 };
            let dq_da = t.dx1[i * (width + 2) + width + k] + t.dx2[i * (width + 2) + width + k];
            let d_u = alpha * inv * d_corr + dq_da * slope;
            let ls = out[i * 4 + 2 + k];
            d_out[i * 4 + k] = d_u;
            if ls > SAC_LOG_STD_RANGE.0 && ls < SAC_LOG_STD_RANGE.1 {
                d_out[i * 4 + 2 + k] = -alpha * inv + d_u * ls.exp() * eps[2 * i + k];
            }
        }
    }
    nets.policy.backward_factored(
        &mut t.policy,
        &d_out,
        &mut g.policy,
        par,
        Deferral { layers: &defer.policy, factors: &mut g.factors.policy },
    );
    // V against min q − α·log π of the same draws.
    nets.v.forward(&batch.obs, b, &mut t.v, par);
    let mut dv = vec![0.0f32; b];
    let mut v_loss = 0.0f64;
    for i in 0..b {
        let e = t.v.output()[i] - (min_q[i] - alpha * draws[i].logp);
        if s.huber {
            v_loss += if e.abs() <= 1.0 { 0.5 * (e as f64).powi(2) } else { e.abs() as f64 - 0.5 };
            dv[i] = e.clamp(-1.0, 1.0) * inv;
        } else {
            v_loss += (e as f64).powi(2);
            dv[i] = 2.0 * e * inv;
        }
    }
    nets.v.backward_factored(&mut t.v, &dv, &mut g.v, par, Deferral { layers: &defer.v, factors: &mut g.factors.v });
    if let Some(h) = s.target_entropy {
        // SAC's temperature loss −log α·(log π + H̄), as Stable-Baselines3 writes it.
        g.log_alpha = -draws.iter().map(|d| d.logp + h).sum::<f32>() * inv;
    }
    let w = inv as f64;
    let losses = Losses {
        policy: pi_loss * w,
        q: q_loss * w,
        v: v_loss * w,
        entropy: ent * w,
        q_mean: qm * w,
        alpha: alpha as f64,
    };
    (losses, g)
}

/// A SAC learner's state: the networks, their optimisers, the temperature.
#[derive(Clone, Debug)]
pub struct Sac {
    /// The networks.
    pub nets: SacNets,
    /// The settings.
    pub settings: SacSettings,
    /// log α.
    pub log_alpha: f32,
    /// Gradient steps taken.
    pub steps: u64,
    adam_policy: Adam,
    adam_embed: Adam,
    adam_q1: Adam,
    adam_q2: Adam,
    adam_v: Adam,
    adam_alpha: Adam,
    rng: ChaCha8Rng,
}

impl Sac {
    /// A learner for `nets`, its noise from `seed`.
    pub fn new(nets: SacNets, settings: SacSettings, seed: u64) -> Sac {
        let lr = settings.lr;
        let adam = |n: &Net| Adam::new(n.params.len(), lr);
        Sac {
            adam_policy: adam(&nets.policy),
            adam_embed: Adam::new(nets.q.embed.as_ref().map_or(0, |e| e.params.len()), lr),
            adam_q1: adam(&nets.q.q1),
            adam_q2: adam(&nets.q.q2),
            adam_v: adam(&nets.v),
            adam_alpha: Adam::new(1, lr),
            log_alpha: settings.alpha.ln(),
            steps: 0,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5ac),
            nets,
            settings,
        }
    }

    /// Set every optimiser's learning rate (the run's schedule).
    pub fn set_lr(&mut self, lr: f32) {
        self.settings.lr = lr;
        for opt in [
            &mut self.adam_policy,
            &mut self.adam_embed,
            &mut self.adam_q1,
            &mut self.adam_q2,
            &mut self.adam_v,
            &mut self.adam_alpha,
        ] {
            opt.lr = lr;
        }
    }

    /// The temperature now.
    pub fn alpha(&self) -> f32 {
        self.log_alpha.exp()
    }

    /// One gradient step on `batch`: all three losses from the weights as they were, then
    /// each network's Adam step (and the temperature's, when it is tuned).
    pub fn step(&mut self, batch: &Batch, par: Par, tapes: &mut Tapes) -> Losses {
        self.step_in(batch, &mut Alone, 0, par, tapes).expect("a learner alone cannot lose a member")
    }

    /// [`Sac::step`] as one member of a group that trains as one learner: every member
    /// calls it with the same batch from the same state (the same noise is drawn), takes its
    /// rank's share of the transitions, and the shares' gradients and losses are summed in
    /// rank order (exchange `exchange` of the update), so every member applies the same Adam
    /// steps and ends the step with the same state, that of one learner on the whole batch.
    pub fn step_in(
        &mut self,
        batch: &Batch,
        group: &mut dyn Reducer,
        exchange: u64,
        par: Par,
        tapes: &mut Tapes,
    ) -> Result<Losses, GroupError> {
        let eps = self.noise(batch.len());
        let (rank, size) = group.shard();
        let b = batch.len();
        let (lo, hi) = (b * rank / size.max(1), b * (rank + 1) / size.max(1));
        let weight = 1.0 / b.max(1) as f32;
        let alpha = self.alpha();
        // The big dense layers, chosen for the whole batch: every member defers the same.
        let defer = Defer::for_batch(&self.nets, b);
        let (mut losses, mut g) = if size > 1 {
            let rows = batch.rows(lo..hi);
            let share = Share { batch: &rows, eps: &eps[2 * lo..2 * hi], weight };
            losses_and_grads_share(&self.nets, &self.settings, alpha, share, &defer, par, tapes)
        } else {
            let share = Share { batch, eps: &eps, weight };
            losses_and_grads_share(&self.nets, &self.settings, alpha, share, &defer, par, tapes)
        };
        let shares: Vec<usize> = (0..size).map(|r| b * (r + 1) / size - b * r / size).collect();
        let mut every = None;
        if size > 1 {
            // One exchange: the gradients but the deferred layers' weights, the temperature's,
            // and the losses' shares summed; the deferred layers' factors gathered.
            let mut flat: Vec<f32> = Vec::new();
            for (grad, factors) in g.parts() {
                let skip = skipped(factors);
                for run in kept(grad, &skip) {
                    flat.extend_from_slice(run);
                }
            }
            let l = &losses;
            flat.extend([g.log_alpha, l.policy as f32, l.q as f32, l.v as f32, l.entropy as f32, l.q_mean as f32]);
            let mut mine = Vec::new();
            for f in g.factors.parts().into_iter().flatten() {
                mine.extend_from_slice(&f.x);
                mine.extend_from_slice(&f.d);
            }
            let ranks: Vec<usize> = (0..size).collect();
            let theirs = group.all_reduce(exchange, &ranks, &mut flat, mine)?;
            let per_sample: usize = g.factors.parts().into_iter().flatten().map(|f| f.n_in + f.n_out).sum();
            check_factors(&theirs, per_sample, &shares)?;
            let mut at = 0;
            for (grad, factors) in g.parts_mut() {
                let skip = skipped(factors);
                let mut from = 0;
                for &(a, end) in skip.iter().chain(std::iter::once(&(grad.len(), grad.len()))) {
                    let n = a - from;
                    grad[from..a].copy_from_slice(&flat[at..at + n]);
                    at += n;
                    from = end;
                }
            }
            let tail = &flat[at..];
            g.log_alpha = tail[0];
            losses = Losses {
                policy: tail[1] as f64,
                q: tail[2] as f64,
                v: tail[3] as f64,
                entropy: tail[4] as f64,
                q_mean: tail[5] as f64,
                alpha: alpha as f64,
            };
            every = Some(theirs);
        }
        self.apply(&g, every.as_deref().map(|e| (e, &shares[..])), par);
        let Deferred { policy, q1, q2, v } = g.factors;
        tapes.policy.take_back(policy);
        tapes.q1.take_back(q1);
        tapes.q2.take_back(q2);
        tapes.v.take_back(v);
        Ok(losses)
    }

    /// The policy's noise for a step on `b` transitions (two standard-normal draws each).
    fn noise(&mut self, b: usize) -> Vec<f32> {
        (0..2 * b).map(|_| StandardNormal.sample(&mut self.rng)).collect()
    }

    /// The temperature's Adam step on its gradient `g`.
    fn step_alpha(&mut self, g: f32) {
        let mut la = [self.log_alpha];
        self.adam_alpha.step(&mut la, &[g]);
        self.log_alpha = la[0];
    }

    /// Each network's Adam step on `g` (and the temperature's, when it is tuned): the
    /// deferred layers' weight gradients multiplied out from this learner's factors, or from
    /// every member's (`every`, with each member's share of the batch) in rank order.
    fn apply(&mut self, g: &Grads, every: Option<(&[Vec<f32>], &[usize])>, par: Par) {
        // Each member's factors, cut per network (the networks' layers follow one another).
        let parts = g.factors.parts();
        let mut cuts: Vec<Vec<&[f32]>> = vec![Vec::new(); parts.len()];
        if let Some((every, shares)) = every {
            for (fr, &b) in every.iter().zip(shares) {
                let mut at = 0;
                for (k, fs) in parts.iter().enumerate() {
                    let n = b * fs.iter().map(|f| f.n_in + f.n_out).sum::<usize>();
                    cuts[k].push(&fr[at..at + n]);
                    at += n;
                }
            }
        }
        let fg = |k: usize| factored_grads(parts[k], every.map(|(_, shares)| (&cuts[k][..], shares)));
        let (policy, q1, q2, v) = (fg(0), fg(1), fg(2), fg(3));
        self.adam_policy.step_factored(&mut self.nets.policy.params, &g.policy, &policy, par);
        if let Some(e) = self.nets.q.embed.as_mut() {
            self.adam_embed.step_with(&mut e.params, &g.q_embed, par);
        }
        self.adam_q1.step_factored(&mut self.nets.q.q1.params, &g.q1, &q1, par);
        self.adam_q2.step_factored(&mut self.nets.q.q2.params, &g.q2, &q2, par);
        self.adam_v.step_factored(&mut self.nets.v.params, &g.v, &v, par);
        if self.settings.target_entropy.is_some() {
            self.step_alpha(g.log_alpha);
        }
        self.steps += 1;
    }

    /// Draw the next gradient steps' noise from `seed` (every member of a team from the
    /// plan's).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5ac);
    }

    /// The networks' weights, their optimisers' moments and log α, as named tensors (`policy`,
    /// `q_embed`, `q1`, `q2`, `v`, `v_target`, `log_alpha`; `adam.policy.m`, `.v` and `.t`, …).
    pub fn tensors(&self) -> Vec<(String, Vec<f32>)> {
        let mut out: Vec<(String, Vec<f32>)> = Vec::new();
        for (name, net) in self.nets_named() {
            out.push((name.into(), net.to_vec()));
        }
        out.push(("log_alpha".into(), vec![self.log_alpha]));
        for (name, opt) in self.adams() {
            let (m, v, t) = opt.moments();
            out.push((format!("adam.{name}.m"), m.to_vec()));
            out.push((format!("adam.{name}.v"), v.to_vec()));
            out.push((format!("adam.{name}.t"), vec![t as f32]));
        }
        out
    }

    /// Take back what [`Sac::tensors`] gave. Refused, with nothing changed, unless every tensor
    /// is there with this learner's sizes and no other.
    pub fn set_tensors(&mut self, tensors: Vec<(String, Vec<f32>)>) -> Result<(), StateMismatch> {
        let mut next = self.clone();
        let mut named: std::collections::BTreeMap<String, Vec<f32>> = tensors.into_iter().collect();
        let mut take = |name: &str, len: usize| -> Result<Vec<f32>, StateMismatch> {
            let t = named.remove(name).ok_or_else(|| StateMismatch(format!("the state has no tensor `{name}`")))?;
            if t.len() != len {
                return Err(StateMismatch(format!("tensor `{name}` has {} values where {len} were expected", t.len())));
            }
            if let Some(i) = t.iter().position(|x| !x.is_finite()) {
                return Err(StateMismatch(format!("tensor `{name}` holds {} at position {i}", t[i])));
            }
            Ok(t)
        };
        let n = &mut next.nets;
        let mut nets: Vec<(&str, &mut Vec<f32>)> = vec![("policy", &mut n.policy.params)];
        if let Some(e) = n.q.embed.as_mut() {
            nets.push(("q_embed", &mut e.params));
        }
        nets.extend([
            ("q1", &mut n.q.q1.params),
            ("q2", &mut n.q.q2.params),
            ("v", &mut n.v.params),
            ("v_target", &mut n.v_target.params),
        ]);
        for (name, params) in nets {
            *params = take(name, params.len())?;
        }
        next.log_alpha = take("log_alpha", 1)?[0];
        for (name, opt) in [
            ("policy", &mut next.adam_policy),
            ("q_embed", &mut next.adam_embed),
            ("q1", &mut next.adam_q1),
            ("q2", &mut next.adam_q2),
            ("v", &mut next.adam_v),
            ("alpha", &mut next.adam_alpha),
        ] {
            let len = opt.moments().0.len();
            let m = take(&format!("adam.{name}.m"), len)?;
            let v = take(&format!("adam.{name}.v"), len)?;
            let t = take(&format!("adam.{name}.t"), 1)?[0];
            if !(t >= 0.0 && t.fract() == 0.0 && t < u32::MAX as f32) {
                return Err(StateMismatch(format!("optimiser step count {t} is not a count")));
            }
            if let Some(i) = v.iter().position(|x| *x < 0.0) {
                return Err(StateMismatch(format!("adam.{name}.v is negative at position {i}")));
            }
            opt.set_moments(m, v, t as u32).map_err(|e| StateMismatch(e.to_string()))?;
        }
        if let Some(extra) = named.keys().next() {
            return Err(StateMismatch(format!("the state has an unknown tensor `{extra}`")));
        }
        *self = next;
        Ok(())
    }

    /// The networks' parameters by name ([`Sac::tensors`]'s order).
    fn nets_named(&self) -> Vec<(&'static str, &[f32])> {
        let n = &self.nets;
        let mut out: Vec<(&'static str, &[f32])> = vec![("policy", &n.policy.params)];
        if let Some(e) = &n.q.embed {
            out.push(("q_embed", &e.params));
        }
        out.extend([
            ("q1", &n.q.q1.params[..]),
            ("q2", &n.q.q2.params[..]),
            ("v", &n.v.params[..]),
            ("v_target", &n.v_target.params[..]),
        ]);
        out
    }

    /// The optimisers by name.
    fn adams(&self) -> [(&'static str, &Adam); 6] {
        [
            ("policy", &self.adam_policy),
            ("q_embed", &self.adam_embed),
            ("q1", &self.adam_q1),
            ("q2", &self.adam_q2),
            ("v", &self.adam_v),
            ("alpha", &self.adam_alpha),
        ]
    }

    /// Move V's target copy towards V by `tau` (1: copy it).
    pub fn update_target(&mut self) {
        let tau = self.settings.tau;
        for (t, v) in self.nets.v_target.params.iter_mut().zip(&self.nets.v.params) {
            *t = if tau >= 1.0 { *v } else { tau * v + (1.0 - tau) * *t };
        }
    }
}
