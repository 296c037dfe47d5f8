//! Clipped PPO as DeepRacer runs it (COACH's `ClippedPPOAgent` with the simapp's settings): GAE (λ 0.95) with a zero
//! bootstrap at every episode end, advantages standardised over the batch, clip ε 0.2,
//! entropy bonus `beta_entropy`, Huber or MSE value loss on a separate value tower, Adam
//! (ε 1e-5, β2 0.999) without gradient clipping, `num_epochs` epochs of shuffled
//! minibatches of `batch_size` (the remainder dropped). As in DeepRacer, the old policy's
//! log-probabilities and the values behind GAE are the network's as the update begins
//! ([`make_batch_for`]), not those the experience was acted with. Paddock's additions:
//! the epochs stop early once a minibatch's approximate KL passes 1.5 × `target_kl`; and a
//! sample with a negative advantage counts at most `dual_clip` × its advantage (dual-clip
//! PPO), so a ratio far above 1 on an action the policy has all but ruled out since it was
//! acted cannot make one step's gradient explode.
//!
//! A non-finite loss or gradient refuses the whole update: the weights and the optimiser
//! state go back to where the iteration began, and the update returns why ([`Refused`]).
//!
//! The update is written once for a learner alone and for a team: a [`Reducer`] says which
//! part of each minibatch this learner computes and sums the members' shares (`team.rs`);
//! alone ([`Alone`]), it computes everything and sums nothing.
//!
//! With a GPU ([`Ppo::with_gpu`]) a learner alone makes the same update with the network
//! maths on it (`on_gpu.rs`); a team's members make theirs on faer.

mod on_gpu;
mod team;

pub use on_gpu::GpuTrainer;

use team::{Part, Role};

use crate::group::{Alone, Reducer, factored_grads};
use crate::hyperparams::{Hyperparameters, LossType};
use crate::update::{LearnerState, Refused, StateMismatch};
use faer::Par;
use policy::model::{LOG_STD_RANGE, clip_log_std, gaussian_entropy, gaussian_logp, log_softmax};
use policy::nn::{Adam, Deferral, Factors, Precision, Tape};
use policy::{ActorCritic, Choice, Head, Trajectory};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

/// PPO's clip range.
pub const CLIP_EPSILON: f32 = 0.2;
/// GAE's λ.
pub const GAE_LAMBDA: f64 = 0.95;

/// Experience flattened for training.
#[derive(Clone, Debug, Default)]
pub struct Batch {
    /// Inputs per observation.
    pub obs_size: usize,
    /// Observations, row-major.
    pub obs: Vec<f32>,
    /// Actions taken.
    pub choices: Vec<Choice>,
    /// Behaviour log-probabilities.
    pub logp_old: Vec<f32>,
    /// Standardised advantages.
    pub adv: Vec<f32>,
    /// Value targets (GAE advantage + value).
    pub returns: Vec<f32>,
    /// Values at acting time.
    pub values_old: Vec<f32>,
}

impl Batch {
    /// Steps in the batch.
    pub fn len(&self) -> usize {
        self.adv.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.adv.is_empty()
    }
}

/// GAE advantages and value targets for one trajectory (bootstrap 0 at its end), from the
/// values it was acted with.
pub fn gae(t: &Trajectory, gamma: f64, lambda: f64) -> (Vec<f64>, Vec<f64>) {
    gae_of(&t.rewards, &t.values, gamma, lambda)
}

/// GAE advantages and value targets for one episode's `rewards` and `values`.
fn gae_of(rewards: &[f32], values: &[f32], gamma: f64, lambda: f64) -> (Vec<f64>, Vec<f64>) {
    let n = rewards.len();
    let mut adv = vec![0.0; n];
    let mut next_adv = 0.0;
    let mut next_value = 0.0;
    for i in (0..n).rev() {
        let v = values[i] as f64;
        let delta = rewards[i] as f64 + gamma * next_value - v;
        next_adv = delta + gamma * lambda * next_adv;
        adv[i] = next_adv;
        next_value = v;
    }
    let returns = adv.iter().zip(values).map(|(a, v)| a + *v as f64).collect();
    (adv, returns)
}

/// Flatten trajectories into a batch with standardised advantages, against the log-probabilities
/// and values they were acted with.
pub fn make_batch(trajs: &[Trajectory], obs_size: usize, gamma: f64) -> Batch {
    let acted = |_: &[f32], _: &[Choice]| {
        let logp = trajs.iter().flat_map(|t| t.logp.iter().copied()).collect();
        Ok::<_, std::convert::Infallible>((logp, trajs.iter().flat_map(|t| t.values.iter().copied()).collect()))
    };
    let Ok(b) = batch_with(trajs, obs_size, gamma, acted);
    b
}

/// Flatten trajectories into a batch as DeepRacer's PPO sees it (COACH
/// syncs its old-policy network before computing advantages): the old log-probabilities and
/// the values behind GAE come from `model`, the network as the update begins, not from acting
/// time. Experience acted a version or two back (the lag flow control allows) is then clipped
/// around the policy being trained, and its advantages rest on that policy's value estimates.
pub fn make_batch_for(trajs: &[Trajectory], model: &ActorCritic, gamma: f64, par: Par) -> Batch {
    make_batch_in(trajs, model, gamma, par, Precision::F32)
}

/// [`make_batch_for`] with the network's products in `precision` (the update's own, so that
/// an update's first ratios are 1 whatever the precision).
pub fn make_batch_in(trajs: &[Trajectory], model: &ActorCritic, gamma: f64, par: Par, precision: Precision) -> Batch {
    let mine = |obs: &[f32], choices: &[Choice]| {
        Ok::<_, std::convert::Infallible>(logp_and_values_in(model, obs, choices, par, precision))
    };
    let Ok(b) = batch_with(trajs, model.obs_size(), gamma, mine);
    b
}

/// Rows per forward pass when a batch's figures are recomputed (bounds the tape's memory for
/// camera networks).
const RELABEL_ROWS: usize = 256;

/// The batch of `trajs`, its old log-probabilities and values from `figures` (given the
/// flattened observations and choices).
fn batch_with<E>(
    trajs: &[Trajectory],
    obs_size: usize,
    gamma: f64,
    figures: impl FnOnce(&[f32], &[Choice]) -> Result<(Vec<f32>, Vec<f32>), E>,
) -> Result<Batch, E> {
    let mut b = Batch { obs_size, ..Batch::default() };
    for t in trajs {
        b.obs.extend_from_slice(&t.obs);
        b.choices.extend_from_slice(&t.choices);
    }
    (b.logp_old, b.values_old) = figures(&b.obs, &b.choices)?;
    let mut adv = Vec::with_capacity(b.choices.len());
    let mut at = 0;
    for t in trajs {
        let (a, r) = gae_of(&t.rewards, &b.values_old[at..at + t.len()], gamma, GAE_LAMBDA);
        at += t.len();
        adv.extend(a);
        b.returns.extend(r.iter().map(|x| *x as f32));
    }
    let n = adv.len().max(1) as f64;
    let mean = adv.iter().sum::<f64>() / n;
    let std = (adv.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / n).sqrt();
    b.adv = adv.iter().map(|a| ((a - mean) / (std + 1e-8)) as f32).collect();
    Ok(b)
}

/// log π(choice | obs) and V(obs) by `model` for every row of `obs`.
pub fn logp_and_values(model: &ActorCritic, obs: &[f32], choices: &[Choice], par: Par) -> (Vec<f32>, Vec<f32>) {
    logp_and_values_in(model, obs, choices, par, Precision::F32)
}

/// [`logp_and_values`] with the network's products in `precision`.
pub fn logp_and_values_in(
    model: &ActorCritic,
    obs: &[f32],
    choices: &[Choice],
    par: Par,
    precision: Precision,
) -> (Vec<f32>, Vec<f32>) {
    let os = model.obs_size();
    let dim = model.pi.out_size();
    let (mut logp, mut values) = (Vec::with_capacity(choices.len()), Vec::with_capacity(choices.len()));
    let mut tape = Tape::default();
    tape.precision = precision;
    for (rows, picked) in obs.chunks(RELABEL_ROWS * os).zip(choices.chunks(RELABEL_ROWS)) {
        let n = picked.len();
        model.pi.forward(rows, n, &mut tape, par);
        logp.extend(tape.output().chunks_exact(dim).zip(picked).map(|(row, c)| logp_of(model, row, *c)));
        model.v.forward(rows, n, &mut tape, par);
        values.extend_from_slice(&tape.output()[..n]);
    }
    (logp, values)
}

/// log π(choice) from the policy tower's output `row`.
fn logp_of(model: &ActorCritic, row: &[f32], choice: Choice) -> f32 {
    match (&model.head, choice) {
        (Head::Categorical(_), Choice::Discrete(c)) => log_softmax(row)[c],
        (Head::Gaussian { log_std }, Choice::Continuous(x)) => gaussian_logp(row, log_std, &x),
        _ => panic!("the batch's actions do not fit the model's head"),
    }
}

/// Losses of one minibatch and their gradients.
#[derive(Clone, Debug, Default)]
pub struct LossGrad {
    /// Clipped surrogate loss (to minimise).
    pub policy_loss: f64,
    /// Value loss.
    pub value_loss: f64,
    /// Mean entropy.
    pub entropy: f64,
    /// The total minimised: policy − β·entropy + value.
    pub total: f64,
    /// Mean (r − 1) − ln r.
    pub approx_kl: f64,
    /// Fraction of samples whose ratio left [1−ε, 1+ε].
    pub clip_fraction: f64,
    /// Gradient for the policy tower's parameters.
    pub grad_pi: Vec<f32>,
    /// Gradient for the value tower's parameters.
    pub grad_v: Vec<f32>,
    /// Gradient for the Gaussian head's log-std.
    pub grad_log_std: [f32; 2],
    /// Dense layers of the policy tower whose weight gradient was left as its factors
    /// (their part of `grad_pi` is zero).
    pub factors_pi: Vec<Factors>,
    /// The same for the value tower.
    pub factors_v: Vec<Factors>,
}

/// Buffers reused across gradient steps (tapes, the gathered minibatch).
#[derive(Default, Debug)]
pub struct Workspace {
    tape_pi: Tape,
    tape_v: Tape,
    obs: Vec<f32>,
    grad_pi: Vec<f32>,
    grad_v: Vec<f32>,
}

impl Workspace {
    /// Hand a used gradient's buffers back for the next step.
    pub fn recycle(&mut self, lg: LossGrad) {
        self.grad_pi = lg.grad_pi;
        self.grad_v = lg.grad_v;
        self.tape_pi.take_back(lg.factors_pi);
        self.tape_v.take_back(lg.factors_v);
    }
}

impl Clone for Workspace {
    /// Buffers are scratch space: a clone starts empty.
    fn clone(&self) -> Self {
        Workspace::default()
    }
}

/// The PPO loss of `model` on the samples `idx` of `batch`, and its gradient.
pub fn loss_and_grad(model: &ActorCritic, batch: &Batch, idx: &[usize], h: &Hyperparameters, par: Par) -> LossGrad {
    loss_and_grad_with(&mut Workspace::default(), model, batch, idx, h, par)
}

/// [`loss_and_grad`] reusing `ws`'s buffers.
pub fn loss_and_grad_with(
    ws: &mut Workspace,
    model: &ActorCritic,
    batch: &Batch,
    idx: &[usize],
    h: &Hyperparameters,
    par: Par,
) -> LossGrad {
    loss_and_grad_factored(ws, model, batch, idx, h, par, (&[], &[]))
}

/// [`loss_and_grad_with`], leaving the weight gradient of the dense layers `defer` (policy
/// tower's, value tower's; layer indices) as their factors.
pub fn loss_and_grad_factored(
    ws: &mut Workspace,
    model: &ActorCritic,
    batch: &Batch,
    idx: &[usize],
    h: &Hyperparameters,
    par: Par,
    defer: (&[usize], &[usize]),
) -> LossGrad {
    loss_and_grad_of(ws, Minibatch { model, batch, idx }, h, par, defer, Towers::BOTH)
}

/// Which towers a gradient step computes: a team member trains one, and once an update's
/// `value_epochs` have passed its steps leave the value tower alone.
#[derive(Clone, Copy, PartialEq, Debug)]
struct Towers {
    policy: bool,
    value: bool,
}

impl Towers {
    const BOTH: Towers = Towers { policy: true, value: true };

    /// The towers that a step computes for a member with `part` (`None`: alone), when the
    /// value tower trains in this step or not.
    fn of(part: Option<Part>, value_trains: bool) -> Towers {
        Towers { policy: part != Some(Part::Value), value: part != Some(Part::Policy) && value_trains }
    }
}

/// What a loss is taken of: `model`'s towers on the samples `idx` of `batch`.
#[derive(Clone, Copy)]
struct Minibatch<'a> {
    model: &'a ActorCritic,
    batch: &'a Batch,
    idx: &'a [usize],
}

/// [`loss_and_grad_factored`] of the `towers` named: a tower left out keeps its loss
/// figures and gradient at zero.
fn loss_and_grad_of(
    ws: &mut Workspace,
    on: Minibatch<'_>,
    h: &Hyperparameters,
    par: Par,
    defer: (&[usize], &[usize]),
    towers: Towers,
) -> LossGrad {
    let Minibatch { model, batch, idx } = on;
    let n = idx.len();
    let os = batch.obs_size;
    let Workspace { tape_pi, tape_v, obs, grad_pi, grad_v } = ws;
    (tape_pi.precision, tape_v.precision) = (h.precision, h.precision);
    // Zeroed but for the deferred layers' weights, which the backward pass leaves alone
    // (46 MB for SHALLOW's two towers, not written on every minibatch).
    let take_zeroed = |buf: &mut Vec<f32>, net: &policy::nn::Net, defer: &[usize]| {
        let mut v = std::mem::take(buf);
        if v.len() != net.params.len() {
            v.clear();
            v.resize(net.params.len(), 0.0);
            return v;
        }
        let mut at = 0;
        for (a, b) in deferred_ranges(net, defer).into_iter().chain(std::iter::once((v.len(), v.len()))) {
            v[at..a].fill(0.0);
            at = b;
        }
        v
    };
    let grad_pi = take_zeroed(grad_pi, &model.pi, defer.0);
    let grad_v = take_zeroed(grad_v, &model.v, defer.1);
    obs.clear();
    for &i in idx {
        obs.extend_from_slice(&batch.obs[i * os..(i + 1) * os]);
    }
    let beta = h.beta_entropy as f32;
    let dual = h.dual_clip.map_or(f32::INFINITY, |c| c as f32);
    let inv_n = 1.0 / n as f32;
    let mut out_stats = LossGrad { grad_pi, grad_v, ..Default::default() };
    if towers.policy {
        policy_loss_and_grad(on, (beta, dual), par, defer.0, (&obs[..], tape_pi), &mut out_stats);
    }
    if towers.value {
        model.v.forward(obs, n, tape_v, par);
        let values = tape_v.output().to_vec();
        let mut d_v = vec![0.0f32; n];
        for (k, &i) in idx.iter().enumerate() {
            let err = values[k] - batch.returns[i];
            let (loss, grad) = match h.loss_type {
                LossType::Huber if err.abs() <= 1.0 => (0.5 * err * err, err),
                LossType::Huber => (err.abs() - 0.5, err.signum()),
                LossType::MeanSquaredError => (err * err, 2.0 * err),
            };
            out_stats.value_loss += loss as f64;
            d_v[k] = grad * inv_n;
        }
        let deferral = Deferral { layers: defer.1, factors: &mut out_stats.factors_v };
        model.v.backward_factored(tape_v, &d_v, &mut out_stats.grad_v, par, deferral);
    }

    let nf = n as f64;
    out_stats.policy_loss /= nf;
    out_stats.value_loss /= nf;
    out_stats.entropy /= nf;
    out_stats.approx_kl /= nf;
    out_stats.clip_fraction /= nf;
    out_stats.total = out_stats.policy_loss - h.beta_entropy * out_stats.entropy + out_stats.value_loss;
    out_stats
}

/// The policy tower's part of [`loss_and_grad_of`]: the clipped surrogate (bounded below by
/// `dual` × a negative advantage; infinite: no bound) and entropy (summed over `idx`, not yet
/// divided), the tower's gradient and the log-std's.
fn policy_loss_and_grad(
    on: Minibatch<'_>,
    (beta, dual): (f32, f32),
    par: Par,
    defer: &[usize],
    (obs, tape_pi): (&[f32], &mut Tape),
    out_stats: &mut LossGrad,
) {
    let Minibatch { model, batch, idx } = on;
    let n = idx.len();
    let inv_n = 1.0 / n as f32;
    model.pi.forward(obs, n, tape_pi, par);
    let out = tape_pi.output().to_vec();
    let out = &out[..];
    let dim = model.pi.out_size();
    let mut d_out = vec![0.0f32; n * dim];
    let mut g_log_std = [0.0f32; 2];
    for (k, &i) in idx.iter().enumerate() {
        let row = &out[k * dim..(k + 1) * dim];
        let a = batch.adv[i];
        let (logp, entropy) = match (&model.head, batch.choices[i]) {
            (Head::Categorical(_), Choice::Discrete(c)) => {
                let lp = log_softmax(row);
                let h: f32 = -lp.iter().map(|l| l.exp() * l).sum::<f32>();
                (lp[c], h)
            }
            (Head::Gaussian { log_std }, Choice::Continuous(x)) => {
                (gaussian_logp(row, log_std, &x), gaussian_entropy(log_std))
            }
            _ => panic!("the batch's actions do not fit the model's head"),
        };
        let ratio = (logp - batch.logp_old[i]).exp();
        let clipped = ratio.clamp(1.0 - CLIP_EPSILON, 1.0 + CLIP_EPSILON);
        let (s1, s2) = (ratio * a, clipped * a);
        // Dual clip: past `dual`, a negative advantage's surrogate is a constant.
        let floored = a < 0.0 && s1.min(s2) < dual * a;
        out_stats.policy_loss -= if floored { dual * a } else { s1.min(s2) } as f64;
        out_stats.entropy += entropy as f64;
        out_stats.approx_kl += ((ratio - 1.0) - (logp - batch.logp_old[i])) as f64;
        if (ratio - 1.0).abs() > CLIP_EPSILON {
            out_stats.clip_fraction += 1.0;
        }
        // d(loss)/d(logp): only the unclipped term carries a gradient.
        let g_logp = if s1 <= s2 && !floored { -a * ratio * inv_n } else { 0.0 };
        let d = &mut d_out[k * dim..(k + 1) * dim];
        match (&model.head, batch.choices[i]) {
            (Head::Categorical(_), Choice::Discrete(c)) => {
                let lp = log_softmax(row);
                for j in 0..dim {
                    let p = lp[j].exp();
                    let onehot = if j == c { 1.0 } else { 0.0 };
                    // logp term, and −β·H with dH/dz_j = −p_j (log p_j + H).
                    d[j] = g_logp * (onehot - p) + beta * inv_n * p * (lp[j] + entropy);
                }
            }
            (Head::Gaussian { log_std }, Choice::Continuous(x)) => {
                for j in 0..2 {
                    let ls = clip_log_std(log_std[j]);
                    let var = (2.0 * ls).exp();
                    let diff = x[j] - row[j];
                    d[j] = g_logp * diff / var;
                    if log_std[j] > LOG_STD_RANGE.0 && log_std[j] < LOG_STD_RANGE.1 {
                        g_log_std[j] += g_logp * (diff * diff / var - 1.0);
                    }
                }
            }
            _ => unreachable!(),
        }
    }
    if let Head::Gaussian { log_std } = &model.head {
        for j in 0..2 {
            if log_std[j] > LOG_STD_RANGE.0 && log_std[j] < LOG_STD_RANGE.1 {
                g_log_std[j] -= beta; // −β·H, dH/dlogσ = 1
            }
        }
    }
    let deferral = Deferral { layers: defer, factors: &mut out_stats.factors_pi };
    model.pi.backward_factored(tape_pi, &d_out, &mut out_stats.grad_pi, par, deferral);
    out_stats.grad_log_std = g_log_std;
}

/// The weights of the dense layers `defer` (layer indices of `net`), as sorted parameter
/// ranges.
fn deferred_ranges(net: &policy::nn::Net, defer: &[usize]) -> Vec<(usize, usize)> {
    let mut r: Vec<(usize, usize)> = defer
        .iter()
        .filter_map(|&i| match net.layers[i] {
            policy::nn::Layer::Dense { inp, out, offset } => Some((offset, offset + inp * out)),
            _ => None,
        })
        .collect();
    r.sort_unstable();
    r
}

/// What one PPO update did.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct PpoStats {
    /// Samples trained on.
    pub samples: usize,
    /// Mean clipped-surrogate loss over minibatches.
    pub policy_loss: f64,
    /// Mean value loss.
    pub value_loss: f64,
    /// Mean entropy.
    pub entropy: f64,
    /// Mean approximate KL between the old and new policy.
    pub approx_kl: f64,
    /// Mean clip fraction.
    pub clip_fraction: f64,
    /// 1 − Var(returns − values) / Var(returns), before the update.
    pub explained_variance: f64,
    /// Gradient steps taken.
    pub gradient_steps: usize,
    /// Of those, the steps that trained the value tower (fewer once `value_epochs` ends its
    /// part of the update); `value_loss` is their mean.
    pub value_steps: usize,
    /// Policy version after the update.
    pub policy_version: u64,
    /// The update stopped before its last epoch: this gradient step's approximate KL passed
    /// 1.5 × `target_kl` (the step itself was taken).
    pub kl_stop: Option<usize>,
}

/// The learner's state: the model, its optimisers, its version.
#[derive(Clone)]
pub struct Ppo {
    /// The model being trained.
    pub model: ActorCritic,
    /// Hyperparameters.
    pub hyper: Hyperparameters,
    /// Current policy version (+1 per accepted update).
    pub version: u64,
    opt_pi: Adam,
    opt_v: Adam,
    opt_log_std: Adam,
    rng: ChaCha8Rng,
    par: Par,
    ws: Workspace,
    gpu: Option<GpuTrainer>,
}

impl Ppo {
    /// A learner for `model` at `version`.
    pub fn new(model: ActorCritic, hyper: Hyperparameters, version: u64, seed: u64, par: Par) -> Ppo {
        let lr = hyper.lr as f32;
        Ppo {
            opt_pi: Adam::new(model.pi.params.len(), lr),
            opt_v: Adam::new(model.v.params.len(), lr),
            opt_log_std: Adam::new(2, lr),
            model,
            hyper,
            version,
            rng: ChaCha8Rng::seed_from_u64(seed),
            par,
            ws: Default::default(),
            gpu: None,
        }
    }

    /// Make this learner's updates with the network maths on `gpu` when it trains alone.
    pub fn with_gpu(mut self, gpu: std::sync::Arc<gpu::Gpu>) -> Ppo {
        self.gpu = Some(GpuTrainer::new(gpu));
        self
    }

    /// The GPU the maths run on, if any (its adapter).
    pub fn device(&self) -> Option<&str> {
        self.gpu.as_ref().map(|g| g.adapter())
    }

    /// Train on a set of trajectories (one iteration).
    pub fn update(&mut self, trajs: &[Trajectory]) -> Result<PpoStats, Refused> {
        self.update_in(trajs, &mut Alone)
    }

    /// Train on a set of trajectories as one learner of a data-parallel group: every learner
    /// of the group calls this with the same trajectories, from the same state.
    pub fn update_in(&mut self, trajs: &[Trajectory], group: &mut dyn Reducer) -> Result<PpoStats, Refused> {
        let seed = self.draw_seed();
        self.update_planned(trajs, seed, group)
    }

    /// The shuffle seed of the next update (a group's leader draws it and sends it to the
    /// members with the trajectories).
    pub fn draw_seed(&mut self) -> u64 {
        use rand::RngCore;
        self.rng.next_u64()
    }

    /// Train with minibatches shuffled from `seed`: the update every member of a group makes
    /// from the leader's plan. A refused update leaves the weights and optimisers as they were.
    pub fn update_planned(
        &mut self,
        trajs: &[Trajectory],
        seed: u64,
        group: &mut dyn Reducer,
    ) -> Result<PpoStats, Refused> {
        self.refusable(|p| p.train(trajs, seed, group))
    }

    /// Make an update with `update`; if it is refused, put the weights and optimisers back.
    fn refusable(&mut self, update: impl FnOnce(&mut Ppo) -> Result<PpoStats, Refused>) -> Result<PpoStats, Refused> {
        let saved = (self.model.clone(), self.opt_pi.clone(), self.opt_v.clone(), self.opt_log_std.clone());
        let result = update(self);
        if result.is_err() {
            (self.model, self.opt_pi, self.opt_v, self.opt_log_std) = saved;
        }
        result
    }

    /// PPO's update: the batch (GAE on the old policy's values), then `num_epochs` epochs of
    /// shuffled minibatches, each a gradient step, until the epochs end or the approximate KL
    /// passes 1.5 × `target_kl`. In a team each member computes its part of every minibatch
    /// and the group sums them ([`Ppo::step_in_team`]), and the members swap the towers they
    /// trained at the end.
    fn train(&mut self, trajs: &[Trajectory], seed: u64, group: &mut dyn Reducer) -> Result<PpoStats, Refused> {
        let version = self.version;
        let group_failed = |error| Refused::Group { error, version };
        if self.gpu.is_some() && group.shard().1 > 1 {
            crate::device::note_team_on_cpu();
        }
        let batch = match (&mut self.gpu, group.shard().1) {
            (Some(g), 1) => g
                .make_batch(trajs, &self.model, [&self.opt_pi, &self.opt_v], &self.hyper)
                .map_err(|e| Refused::Device { error: e.to_string(), version })?,
            _ => self.batch_in(trajs, group).map_err(group_failed)?,
        };
        self.epochs(&batch, seed, group)
    }

    /// The epochs of an update on a batch already made, as a learner alone: what `learner
    /// bench` times (on faer and on the GPU), without GAE's forward pass over the batch. A
    /// refused update leaves the weights and optimisers as they were.
    pub fn update_on_batch(&mut self, batch: &Batch, seed: u64) -> Result<PpoStats, Refused> {
        self.refusable(|p| p.epochs(batch, seed, &mut Alone))
    }

    /// `num_epochs` epochs of shuffled minibatches of `batch` (see [`Ppo::train`]).
    fn epochs(&mut self, batch: &Batch, seed: u64, group: &mut dyn Reducer) -> Result<PpoStats, Refused> {
        let version = self.version;
        let group_failed = |error| Refused::Group { error, version };
        let n = batch.len();
        let bs = self.hyper.batch_size.min(n.max(1));
        if n / bs == 0 {
            return Err(Refused::TooFewSamples { samples: n, batch: bs });
        }
        let mut stats = PpoStats { samples: n, explained_variance: explained_variance(batch), ..Default::default() };
        let mut shuffle = ChaCha8Rng::seed_from_u64(seed);
        let (hold, value_epochs) = (self.holds_policy(), self.value_epochs());
        if let (Some(g), 1) = (&mut self.gpu, group.shard().1) {
            let opts = [&mut self.opt_pi, &mut self.opt_v, &mut self.opt_log_std];
            let order = |o: &mut Vec<usize>| o.shuffle(&mut shuffle);
            let epochs = on_gpu::Epochs { batch, bs, hold_policy: hold, value_epochs, version };
            g.train(&mut self.model, opts, &self.hyper, epochs, order, &mut stats)?;
            return Ok(self.finish(stats));
        }
        let mut order: Vec<usize> = (0..n).collect();
        // The big dense layers' weight gradients stay factors until the optimiser multiplies
        // them out (alone or in a team: one path).
        let defer = (self.model.pi.factorable(bs), self.model.v.factorable(bs));
        let (rank, size) = group.shard();
        let role = (size > 1).then(|| Role::of(rank, size));
        'epochs: for epoch in 0..self.hyper.num_epochs {
            order.shuffle(&mut shuffle);
            let value = epoch < value_epochs;
            for mb in order.chunks_exact(bs) {
                let at = (stats.gradient_steps, value);
                let lg = self.minibatch(batch, mb, (&defer.0, &defer.1), group, role.as_ref(), at)?;
                stats.policy_loss += lg.policy_loss;
                stats.value_loss += lg.value_loss;
                stats.value_steps += usize::from(value);
                stats.entropy += lg.entropy;
                stats.approx_kl += lg.approx_kl;
                stats.clip_fraction += lg.clip_fraction;
                stats.gradient_steps += 1;
                // Every member of a team holds the group's figures here: all stop together.
                let too_far = self.hyper.target_kl.is_some_and(|t| lg.approx_kl > 1.5 * t);
                self.ws.recycle(lg);
                if too_far {
                    stats.kl_stop = Some(stats.gradient_steps);
                    break 'epochs;
                }
            }
        }
        // A team's members trained one tower each: they swap the towers' states.
        if let Some(role) = &role {
            self.swap_towers(group, 2 * stats.gradient_steps as u64 + 1, role.part, rank).map_err(group_failed)?;
        }
        Ok(self.finish(stats))
    }

    /// An accepted update's figures (averaged over its gradient steps) and the next version.
    fn finish(&mut self, mut stats: PpoStats) -> PpoStats {
        let k = stats.gradient_steps as f64;
        stats.policy_loss /= k;
        stats.value_loss /= (stats.value_steps as f64).max(1.0);
        stats.entropy /= k;
        stats.approx_kl /= k;
        stats.clip_fraction /= k;
        self.version += 1;
        stats.policy_version = self.version;
        stats
    }

    /// Gradient step `step` on the minibatch `mb`, `at` = (`step`, whether the value tower
    /// trains in it): the loss and its gradient (in a team, of this member's share and
    /// tower), then the optimiser step (in a team, on the members' sum). Returns the loss
    /// figures (a team's sums), or why the update must be refused.
    fn minibatch(
        &mut self,
        batch: &Batch,
        mb: &[usize],
        defer: (&[usize], &[usize]),
        group: &mut dyn Reducer,
        role: Option<&Role>,
        at: (usize, bool),
    ) -> Result<LossGrad, Refused> {
        let (step, value) = at;
        let (mine, shares) = role.map_or((mb, vec![mb.len()]), |r| r.share(mb));
        let t0 = std::time::Instant::now();
        let mut ws = std::mem::take(&mut self.ws);
        let towers = Towers::of(role.map(|r| r.part), value);
        let on = Minibatch { model: &self.model, batch, idx: mine };
        let mut lg = loss_and_grad_of(&mut ws, on, &self.hyper, self.par, defer, towers);
        self.ws = ws;
        let t1 = std::time::Instant::now();
        let finite = match role {
            None => self.apply(&lg, value),
            Some(role) => self
                .step_in_team(group, (step as u64, value), role, &mut lg, &shares)
                .map_err(|error| Refused::Group { error, version: self.version })?,
        };
        tracing::trace!(
            gradient_ms = (t1 - t0).as_secs_f64() * 1e3,
            optimiser_ms = t1.elapsed().as_secs_f64() * 1e3,
            "gradient step {step} (in a team the optimiser's time includes the exchanges)"
        );
        if !finite {
            return Err(Refused::NonFinite { step, loss: lg.total, version: self.version });
        }
        Ok(lg)
    }

    /// The optimiser step of one minibatch of a learner alone: Adam on both towers (the
    /// factored layers' gradients multiplied out from this learner's factors; the value
    /// tower's only when `value`) and on the log-std. Returns whether the loss and every
    /// gradient value were finite; when not, the caller restores the state it saved.
    fn apply(&mut self, lg: &LossGrad, value: bool) -> bool {
        let mut finite = lg.total.is_finite() && lg.grad_log_std.iter().all(|g| g.is_finite());
        if !self.holds_policy() {
            finite &= self.opt_pi.step_factored(
                &mut self.model.pi.params,
                &lg.grad_pi,
                &factored_grads(&lg.factors_pi, None),
                self.par,
            );
            self.step_log_std(lg);
        }
        if value {
            finite &= self.opt_v.step_factored(
                &mut self.model.v.params,
                &lg.grad_v,
                &factored_grads(&lg.factors_v, None),
                self.par,
            );
        }
        finite
    }

    /// The epochs of this update in which the value tower trains: `value_epochs` of them
    /// (every one without it, and in the value warm-up, where the value tower is all that
    /// trains).
    pub(super) fn value_epochs(&self) -> usize {
        let all = self.hyper.num_epochs;
        if self.holds_policy() { all } else { self.hyper.value_epochs.map_or(all, |k| k.min(all)) }
    }

    /// The value tower's warm-up: an update that starts below `value_warmup_updates` holds
    /// the policy as it is (its gradient is computed and not applied), alone or in a team.
    pub(super) fn holds_policy(&self) -> bool {
        self.version < self.hyper.value_warmup_updates
    }

    fn step_log_std(&mut self, lg: &LossGrad) {
        if let Head::Gaussian { log_std } = &mut self.model.head {
            self.opt_log_std.step(log_std, &lg.grad_log_std);
        }
    }

    /// One gradient step of a learner alone on the samples `idx` of `batch`, as an update
    /// takes each minibatch (forward, backward, the optimiser step): what `learner bench`
    /// times. No refusal here: returns whether the numbers were finite.
    pub fn gradient_step(&mut self, batch: &Batch, idx: &[usize]) -> bool {
        let defer = (self.model.pi.factorable(idx.len()), self.model.v.factorable(idx.len()));
        let mut ws = std::mem::take(&mut self.ws);
        let lg = loss_and_grad_factored(&mut ws, &self.model, batch, idx, &self.hyper, self.par, (&defer.0, &defer.1));
        let ok = self.apply(&lg, true);
        ws.recycle(lg);
        self.ws = ws;
        ok
    }

    /// The state a joining member takes over.
    pub fn state(&self) -> LearnerState {
        let mut tensors =
            vec![("pi".to_string(), self.model.pi.params.clone()), ("v".into(), self.model.v.params.clone())];
        if let Head::Gaussian { log_std } = &self.model.head {
            tensors.push(("log_std".into(), log_std.to_vec()));
        }
        let (opt_pi, opt_v) = self.optimisers();
        for (name, opt) in [("pi", &opt_pi), ("v", &opt_v), ("log_std", &self.opt_log_std)] {
            let (m, v, t) = opt.moments();
            tensors.push((format!("adam.{name}.m"), m.to_vec()));
            tensors.push((format!("adam.{name}.v"), v.to_vec()));
            tensors.push((format!("adam.{name}.t"), vec![t as f32]));
        }
        LearnerState { version: self.version, tensors }
    }

    /// The towers' optimisers as they stand: the CPU's, or, while the model's state is on the
    /// GPU, its moments read back. A GPU that cannot be read is fatal here: the state a
    /// checkpoint or a joiner takes must not be silently stale.
    fn optimisers(&self) -> (Adam, Adam) {
        let (mut pi, mut v) = (self.opt_pi.clone(), self.opt_v.clone());
        let read = self.gpu.as_ref().map(|g| g.moments()).transpose();
        match read {
            Ok(Some(Some([(pm, pv, pt), (vm, vv, vt)]))) => {
                pi.set_moments(pm, pv, pt).expect("the GPU holds this model's moments");
                v.set_moments(vm, vv, vt).expect("the GPU holds this model's moments");
            }
            Ok(_) => {}
            Err(e) => panic!("reading Adam's moments back from the GPU: {e}"),
        }
        (pi, v)
    }

    /// Take over another member's state. Refused, with nothing changed, unless every tensor
    /// is there with the size this learner's model has.
    pub fn restore(&mut self, state: LearnerState) -> Result<(), StateMismatch> {
        let mut next = self.clone();
        let mut tensors: std::collections::BTreeMap<String, Vec<f32>> = state.tensors.into_iter().collect();
        let mut take = |name: &str, len: usize| -> Result<Vec<f32>, StateMismatch> {
            let t = tensors.remove(name).ok_or_else(|| StateMismatch(format!("the state has no tensor `{name}`")))?;
            if t.len() != len {
                return Err(StateMismatch(format!("tensor `{name}` has {} values where {len} were expected", t.len())));
            }
            Ok(t)
        };
        next.model.pi.params = take("pi", self.model.pi.params.len())?;
        next.model.v.params = take("v", self.model.v.params.len())?;
        if let Head::Gaussian { log_std } = &mut next.model.head {
            let l = take("log_std", 2)?;
            *log_std = [l[0], l[1]];
        }
        for (name, opt) in [("pi", &mut next.opt_pi), ("v", &mut next.opt_v), ("log_std", &mut next.opt_log_std)] {
            let n = opt.moments().0.len();
            let m = take(&format!("adam.{name}.m"), n)?;
            let v = take(&format!("adam.{name}.v"), n)?;
            let t = take(&format!("adam.{name}.t"), 1)?[0];
            if !(t >= 0.0 && t.fract() == 0.0 && t < u32::MAX as f32) {
                return Err(StateMismatch(format!("optimiser step count {t} is not a count")));
            }
            opt.set_moments(m, v, t as u32).map_err(|e| StateMismatch(e.to_string()))?;
        }
        if let Some(extra) = tensors.keys().next() {
            return Err(StateMismatch(format!("the state has an unknown tensor `{extra}`")));
        }
        next.version = state.version;
        // The GPU takes the restored state at the next update.
        if let Some(g) = &mut next.gpu {
            g.evict();
        }
        *self = next;
        Ok(())
    }

    /// The learning rate the next update uses.
    pub fn lr(&self) -> f64 {
        self.hyper.lr
    }

    /// Change the learning rate (the job's schedule sets it before every update).
    pub fn set_lr(&mut self, lr: f64) {
        self.hyper.lr = lr;
        for opt in [&mut self.opt_pi, &mut self.opt_v, &mut self.opt_log_std] {
            opt.lr = lr as f32;
        }
    }
}

fn explained_variance(b: &Batch) -> f64 {
    let n = b.len().max(1) as f64;
    let mean = |v: &mut dyn Iterator<Item = f64>| v.sum::<f64>() / n;
    let mr = mean(&mut b.returns.iter().map(|x| *x as f64));
    let var_r = mean(&mut b.returns.iter().map(|x| (*x as f64 - mr).powi(2)));
    let diffs: Vec<f64> = b.returns.iter().zip(&b.values_old).map(|(r, v)| (*r - *v) as f64).collect();
    let md = mean(&mut diffs.iter().copied());
    let var_d = mean(&mut diffs.iter().map(|d| (d - md).powi(2)));
    if var_r > 0.0 { 1.0 - var_d / var_r } else { f64::NAN }
}
