//! A learner team's side of PPO's update: each member's part (which tower it trains, its
//! share of each minibatch), and the exchanges through the group's [`Reducer`] that make the
//! team's update one learner's: the old policy's figures split by rank, the tower's shares
//! summed, the step's loss figures summed, and the towers' states swapped at the end. PPO's
//! own loop (`ppo/mod.rs`) reaches these through `batch_in`, `step_in_team` and
//! `swap_towers`.
//!
//! A group of one trains both towers alone. In a team the two towers are trained apart (they
//! share nothing but the minibatch): the even ranks train the policy tower and the odd ranks
//! the value tower, so that no member repeats the other tower's optimiser step. The members
//! of a tower split each minibatch's samples between them, and the tower's update equals one
//! learner's on the whole minibatch (to float rounding; with one member a tower, bit for bit
//! the step one learner takes on the same batch).
//!
//! The exchanges of an update, numbered by `step`:
//! - `0`, every member: its rows of the old policy's log-probabilities and values;
//! - `2k + 1`, the members of a tower, for the update's `k`-th gradient step: the tower's
//!   shares (made only when two or more members train the tower);
//! - `2k + 2`, every member: the step's loss figures, each tower's from its first member,
//!   and whether each member's step was finite, so that all refuse or stop together;
//! - after the last of `K` steps, `2K + 1` and `2K + 2`: rank 0 sends the policy tower's
//!   weights and optimiser state to the members that train the value tower, and rank 1 the
//!   value tower's to those that train the policy tower, so every member ends the update
//!   with the same state, bit for bit, and any of them can lead or go on alone.

use super::{Batch, LossGrad, Ppo, batch_with, logp_and_values_in, make_batch_in};
use crate::group::{GroupError, Reducer, check_factors, factored_grads, kept, skipped};
use policy::nn::{Adam, Factors};
use policy::{Head, Trajectory};

/// A team member's part in every gradient step: the tower it trains, the members that train
/// it (ascending ranks) and its place among them.
pub(super) struct Role {
    pub(super) part: Part,
    ranks: Vec<usize>,
    index: usize,
}

impl Role {
    /// The role of `rank` in a team of `size` (two or more): even ranks the policy tower,
    /// odd ranks the value tower.
    pub(super) fn of(rank: usize, size: usize) -> Role {
        let part = Part::of_rank(rank);
        let ranks: Vec<usize> = (rank % 2..size).step_by(2).collect();
        Role { part, index: rank / 2, ranks }
    }

    /// This member's samples of the minibatch `mb`, and every member's share sizes.
    pub(super) fn share<'a>(&self, mb: &'a [usize]) -> (&'a [usize], Vec<usize>) {
        let (n, k) = (mb.len(), self.ranks.len());
        let shares = (0..k).map(|r| n * (r + 1) / k - n * r / k).collect();
        (&mb[n * self.index / k..n * (self.index + 1) / k], shares)
    }
}

/// The loss figures a team sums at every gradient step: the policy loss, the entropy, the
/// approximate KL, the clip fraction (the policy tower's), the value loss, and how many
/// members' steps were not finite.
pub(super) const FIGURES: usize = 6;

/// A model's two towers, as a team splits its work (see the module's doc).
#[derive(Clone, Copy, PartialEq, Debug)]
pub(super) enum Part {
    /// The policy tower (and the log-std of a Gaussian head).
    Policy,
    /// The value tower.
    Value,
}

impl Part {
    /// The tower a team member of `rank` trains: even ranks the policy tower.
    fn of_rank(rank: usize) -> Part {
        if rank.is_multiple_of(2) { Part::Policy } else { Part::Value }
    }

    /// The other tower.
    fn other(self) -> Part {
        match self {
            Part::Policy => Part::Value,
            Part::Value => Part::Policy,
        }
    }

    /// The rank that sends the tower's state at an update's end: the first that trains it.
    fn owner(self) -> usize {
        match self {
            Part::Policy => 0,
            Part::Value => 1,
        }
    }

    /// The tower's gradient and its factored layers.
    fn of(self, lg: &LossGrad) -> (&Vec<f32>, &Vec<Factors>) {
        match self {
            Part::Policy => (&lg.grad_pi, &lg.factors_pi),
            Part::Value => (&lg.grad_v, &lg.factors_v),
        }
    }
}

impl Ppo {
    /// The update's batch ([`make_batch_for`]). In a team each member works out the old
    /// policy's figures for its rank's share of the rows, and the group adds them up (exchange
    /// 0 of the update; a row's figures come from one member, the others add zeros), so that
    /// pass is split like the gradients.
    pub(super) fn batch_in(&self, trajs: &[Trajectory], group: &mut dyn Reducer) -> Result<Batch, GroupError> {
        let (rank, size) = group.shard();
        let (model, par, gamma, precision) = (&self.model, self.par, self.hyper.discount_factor, self.hyper.precision);
        if size == 1 {
            return Ok(make_batch_in(trajs, model, gamma, par, precision));
        }
        let os = model.obs_size();
        batch_with(trajs, os, gamma, |obs, choices| {
            let n = choices.len();
            let (a, b) = (n * rank / size, n * (rank + 1) / size);
            let (logp, values) = logp_and_values_in(model, &obs[a * os..b * os], &choices[a..b], par, precision);
            let mut both = vec![0.0f32; 2 * n];
            both[a..b].copy_from_slice(&logp);
            both[n + a..n + b].copy_from_slice(&values);
            let every: Vec<usize> = (0..size).collect();
            group.all_reduce(0, &every, &mut both, Vec::new())?;
            let values = both.split_off(n);
            Ok((both, values))
        })
    }

    /// The optimiser step of one minibatch in a team, `at` = (`k`, whether the value tower
    /// trains in this step): the Adam step of the tower this member trains, as
    /// [`Ppo::apply`] takes it, on the sum of the shares of the members that train it
    /// (exchange `2k + 1`, made when there are two or more), then the step's loss figures
    /// summed over the team (exchange `2k + 2`). In a step where the value tower does not
    /// train, its members make neither its exchange nor its step (every member knows which
    /// steps those are). Returns whether every member's step was finite; `lg` then holds the
    /// team's figures.
    pub(super) fn step_in_team(
        &mut self,
        group: &mut dyn Reducer,
        at: (u64, bool),
        role: &Role,
        lg: &mut LossGrad,
        shares: &[usize],
    ) -> Result<bool, GroupError> {
        let (step, value) = at;
        let size = group.shard().1;
        let part = role.part;
        let idle = part == Part::Value && !value;
        let every = if role.ranks.len() > 1 && !idle {
            let (mut values, factors) = share_of(lg, part, shares, role.index);
            let every = group.all_reduce(2 * step + 1, &role.ranks, &mut values, factors)?;
            check_factors(&every, part.of(lg).1.iter().map(|f| f.n_in + f.n_out).sum(), shares)?;
            take_sum(lg, part, &values);
            Some(every)
        } else {
            None
        };
        let every: Option<Vec<&[f32]>> = every.as_ref().map(|e| e.iter().map(|v| &v[..]).collect());
        let factored = factored_grads(part.of(lg).1, every.as_deref().map(|e| (e, shares)));
        let finite = match part {
            Part::Value if idle => true,
            Part::Policy if self.holds_policy() => lg.grad_log_std.iter().all(|g| g.is_finite()),
            Part::Policy => {
                let ok = self.opt_pi.step_factored(&mut self.model.pi.params, &lg.grad_pi, &factored, self.par);
                self.step_log_std(lg);
                ok && lg.grad_log_std.iter().all(|g| g.is_finite())
            }
            Part::Value => self.opt_v.step_factored(&mut self.model.v.params, &lg.grad_v, &factored, self.par),
        };
        // Each tower's figures come from its first member (the others hold the same sums).
        let mut figures = [0.0f32; FIGURES];
        if role.index == 0 {
            match part {
                Part::Policy => figures[..4]
                    .copy_from_slice(&[lg.policy_loss, lg.entropy, lg.approx_kl, lg.clip_fraction].map(|f| f as f32)),
                Part::Value => figures[4] = lg.value_loss as f32,
            }
        }
        figures[5] = if finite { 0.0 } else { 1.0 };
        let everyone: Vec<usize> = (0..size).collect();
        group.all_reduce(2 * step + 2, &everyone, &mut figures, Vec::new())?;
        let [pl, ent, kl, clip, vl, bad] = figures.map(|f| f as f64);
        (lg.policy_loss, lg.entropy, lg.approx_kl, lg.clip_fraction, lg.value_loss) = (pl, ent, kl, clip, vl);
        lg.total = pl - self.hyper.beta_entropy * ent + vl;
        Ok(bad == 0.0 && lg.total.is_finite())
    }

    /// The end of a team's update (exchanges `first` and `first + 1`): rank 0 sends the
    /// policy tower's state (weights, log-std, optimiser moments) to the members that trained
    /// the value tower, and rank 1 the value tower's to those that trained the policy tower
    /// (`mine`: the tower this member trained). Each member sends before it waits, so the two
    /// travel at once.
    pub(super) fn swap_towers(
        &mut self,
        group: &mut dyn Reducer,
        first: u64,
        mine: Part,
        rank: usize,
    ) -> Result<(), GroupError> {
        let step = |p: Part| if p == Part::Policy { first } else { first + 1 };
        if rank == mine.owner() {
            let mut state = self.tower_state(mine);
            group.all_reduce(step(mine), &[rank], &mut state, Vec::new())?;
        }
        let other = mine.other();
        let mut state = vec![0.0; self.tower_state_len(other)];
        group.all_reduce(step(other), &[other.owner()], &mut state, Vec::new())?;
        self.set_tower_state(other, &state)
    }

    /// A tower's parameters and their optimisers: the policy tower's weights, then the
    /// log-std (none with a categorical head); the value tower's weights.
    fn tower_pieces(&self, part: Part) -> Vec<(&[f32], &Adam)> {
        match part {
            Part::Policy => {
                let log_std: &[f32] = match &self.model.head {
                    Head::Gaussian { log_std } => log_std,
                    Head::Categorical(_) | Head::Squashed { .. } => &[],
                };
                vec![(&self.model.pi.params, &self.opt_pi), (log_std, &self.opt_log_std)]
            }
            Part::Value => vec![(&self.model.v.params, &self.opt_v)],
        }
    }

    /// A tower's weights and optimiser state, flat: for each of its pieces the parameters,
    /// then Adam's first and second moments and its step count.
    fn tower_state(&self, part: Part) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.tower_state_len(part));
        for (params, opt) in self.tower_pieces(part) {
            let (m, v, t) = opt.moments();
            out.extend_from_slice(params);
            out.extend_from_slice(m);
            out.extend_from_slice(v);
            out.push(t as f32);
        }
        out
    }

    /// The length of [`Ppo::tower_state`], without making it.
    fn tower_state_len(&self, part: Part) -> usize {
        self.tower_pieces(part).iter().map(|(p, o)| p.len() + 2 * o.moments().0.len() + 1).sum()
    }

    /// Take a tower's state as [`Ppo::tower_state`] lays it out. Refused, with nothing
    /// changed, when it does not fit.
    fn set_tower_state(&mut self, part: Part, state: &[f32]) -> Result<(), GroupError> {
        let Ppo { model, opt_pi, opt_v, opt_log_std, .. } = self;
        let mut none = [0.0f32; 0];
        let mut pieces: Vec<(&mut [f32], &mut Adam)> = match part {
            Part::Policy => {
                let log_std: &mut [f32] = match &mut model.head {
                    Head::Gaussian { log_std } => log_std,
                    Head::Categorical(_) | Head::Squashed { .. } => &mut none,
                };
                vec![(&mut model.pi.params[..], opt_pi), (log_std, opt_log_std)]
            }
            Part::Value => vec![(&mut model.v.params[..], opt_v)],
        };
        // Every size and step count first, so that a state that does not fit changes nothing.
        let sizes: Vec<(usize, usize)> = pieces.iter().map(|(p, o)| (p.len(), o.moments().0.len())).collect();
        let expected: usize = sizes.iter().map(|(p, n)| p + 2 * n + 1).sum();
        if state.len() != expected {
            return Err(GroupError(format!(
                "a tower's state of {} numbers where {expected} were expected",
                state.len()
            )));
        }
        if let Some(i) = state.iter().position(|x| !x.is_finite()) {
            return Err(GroupError(format!("a tower's state holds {} at position {i}", state[i])));
        }
        let mut at = 0;
        for &(p, n) in &sizes {
            let t = state[at + p + 2 * n];
            if !(t >= 0.0 && t.fract() == 0.0 && t < u32::MAX as f32) {
                return Err(GroupError(format!("optimiser step count {t} is not a count")));
            }
            if let Some(i) = state[at + p + n..at + p + 2 * n].iter().position(|v| *v < 0.0) {
                return Err(GroupError(format!("a tower's second moment is negative at position {}", at + p + n + i)));
            }
            at += p + 2 * n + 1;
        }
        let mut at = 0;
        for ((params, opt), (p, n)) in pieces.iter_mut().zip(sizes) {
            let piece = &state[at..at + p + 2 * n + 1];
            params.copy_from_slice(&piece[..p]);
            let (m, v, t) = (piece[p..p + n].to_vec(), piece[p + n..p + 2 * n].to_vec(), piece[p + 2 * n] as u32);
            opt.set_moments(m, v, t).map_err(|e| GroupError(e.to_string()))?;
            at += p + 2 * n + 1;
        }
        Ok(())
    }
}

/// This learner's share of `part` of a minibatch (`shares[rank]` of its samples), weighted
/// by its size: the values to sum over the tower's members (the gradient but its factored
/// layers' weights; then for the policy tower the log-std gradient, the policy loss, the
/// entropy, the approximate KL and the clip fraction; for the value tower the value loss),
/// and the factored layers' factors.
fn share_of(lg: &LossGrad, part: Part, shares: &[usize], rank: usize) -> (Vec<f32>, Vec<f32>) {
    let (mine, all) = (shares[rank], shares.iter().sum::<usize>());
    let w = mine as f32 / all as f32;
    // An empty share contributes nothing (its means are not numbers).
    let weigh = |x: f32| if mine == 0 { 0.0 } else { x * w };
    let (grad, factors) = part.of(lg);
    let skip = skipped(factors);
    let mut values = Vec::with_capacity(grad.len() + 6);
    for run in kept(grad, &skip) {
        values.extend(run.iter().map(|g| weigh(*g)));
    }
    let figures = match part {
        Part::Policy => {
            values.extend(lg.grad_log_std.iter().map(|g| weigh(*g)));
            vec![lg.policy_loss, lg.entropy, lg.approx_kl, lg.clip_fraction]
        }
        Part::Value => vec![lg.value_loss],
    };
    values.extend(figures.iter().map(|f| weigh(*f as f32)));
    let mut mine_f = Vec::with_capacity(factors.iter().map(|f| f.x.len() + f.d.len()).sum());
    for f in factors {
        mine_f.extend_from_slice(&f.x);
        mine_f.extend(f.d.iter().map(|d| d * w));
    }
    (values, mine_f)
}

/// Put the tower members' sum of `part` (laid out as [`share_of`] made it) back into `lg`.
fn take_sum(lg: &mut LossGrad, part: Part, values: &[f32]) {
    let skip = skipped(part.of(lg).1);
    let grad = if part == Part::Policy { &mut lg.grad_pi } else { &mut lg.grad_v };
    let (mut at, mut from) = (0, 0);
    for &(a, b) in skip.iter().chain(std::iter::once(&(grad.len(), grad.len()))) {
        let n = a - from;
        grad[from..a].copy_from_slice(&values[at..at + n]);
        at += n;
        from = b;
    }
    let f = &values[at..];
    match part {
        Part::Policy => {
            lg.grad_log_std.copy_from_slice(&f[..2]);
            (lg.policy_loss, lg.entropy, lg.approx_kl, lg.clip_fraction) =
                (f[2] as f64, f[3] as f64, f[4] as f64, f[5] as f64);
        }
        Part::Value => lg.value_loss = f[0] as f64,
    }
}
