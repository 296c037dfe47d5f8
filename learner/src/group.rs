//! A group of learners that trains as one learner (a learner team's exchange), as each
//! member's update sees it; PPO and SAC both make their updates through it. The
//! [`Reducer`] sums the members' shares of a gradient step in rank order (a group of one,
//! [`Alone`], sums nothing), [`GroupError`] says why an exchange failed, and the factored
//! gradients are how the big dense layers' weight gradients travel: as their factors
//! (inputs and output gradients of a share, a fraction of the size), multiplied out by every
//! member in rank order.

use policy::nn::{FactoredGrad, Factors};

/// Why a learner group's step failed (a member lost, a share that does not fit).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct GroupError(pub String);

/// The learners of a group that trains as one learner, as one learner's update sees them.
/// The members split each gradient step's samples between them (data parallelism, as DD-PPO
/// does): each computes the gradient of its share weighted by the share's size, and
/// `all_reduce` sums the shares in rank order, so they all apply the same optimiser step to
/// the same weights and the group's update equals one learner's on the whole batch (to float
/// rounding). Each algorithm numbers the exchanges of its update (PPO's in `ppo/team.rs`,
/// SAC's at `Sac::step_in`).
pub trait Reducer {
    /// This learner's rank and the group's size.
    fn shard(&self) -> (usize, usize);
    /// Replace `values` by the sum of the shares of the members `ranks` (ascending), added
    /// in rank order, and return their `factors` in rank order. A member in `ranks` gives its
    /// own `values` and `factors`; one not in `ranks` gives nothing and receives the sum
    /// (its `values` only set the length: with one member in `ranks`, that member's values,
    /// bit for bit). `step` numbers the exchanges of one update.
    fn all_reduce(
        &mut self,
        step: u64,
        ranks: &[usize],
        values: &mut [f32],
        factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError>;
}

/// A group of one: nothing to add.
pub struct Alone;

impl Reducer for Alone {
    fn shard(&self) -> (usize, usize) {
        (0, 1)
    }
    fn all_reduce(
        &mut self,
        _step: u64,
        _ranks: &[usize],
        _values: &mut [f32],
        factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError> {
        Ok(vec![factors])
    }
}

/// The parameter ranges a tower's factored layers leave out of its gradient vector.
pub(crate) fn skipped(factors: &[Factors]) -> Vec<(usize, usize)> {
    let mut r: Vec<(usize, usize)> = factors.iter().map(|f| (f.offset, f.offset + f.n_in * f.n_out)).collect();
    r.sort_unstable();
    r
}

/// The parts of `grad` outside `skip`, in order.
pub(crate) fn kept<'a>(grad: &'a [f32], skip: &'a [(usize, usize)]) -> impl Iterator<Item = &'a [f32]> + 'a {
    let mut at = 0;
    let mut out = Vec::with_capacity(skip.len() + 1);
    for &(a, b) in skip {
        out.push(&grad[at..a]);
        at = b;
    }
    out.push(&grad[at..]);
    out.into_iter()
}

/// Every member's factors must hold its share's samples, `per_sample` numbers each (the
/// factored layers' inputs and outputs).
pub(crate) fn check_factors(every: &[Vec<f32>], per_sample: usize, shares: &[usize]) -> Result<(), GroupError> {
    if every.len() != shares.len() {
        return Err(GroupError(format!("{} members' factors for a group of {}", every.len(), shares.len())));
    }
    for (r, fr) in every.iter().enumerate() {
        if fr.len() != shares[r] * per_sample {
            return Err(GroupError(format!(
                "member {r}'s factors hold {} numbers where {} were expected",
                fr.len(),
                shares[r] * per_sample
            )));
        }
    }
    Ok(())
}

/// A tower's factored layers' weight gradients as the optimiser takes them: this learner's
/// own `factors`, or every member's shares of the tower in rank order (`every`, as
/// [`Reducer::all_reduce`] returned them: per member, layer by layer, `x` then `d`).
pub(crate) fn factored_grads<'a>(
    factors: &'a [Factors],
    every: Option<(&[&'a [f32]], &[usize])>,
) -> Vec<FactoredGrad<'a>> {
    let mut all: Vec<FactoredGrad<'a>> = factors
        .iter()
        .map(|f| FactoredGrad {
            offset: f.offset,
            n_in: f.n_in,
            n_out: f.n_out,
            shares: if every.is_none() { vec![(&f.x[..], &f.d[..])] } else { Vec::new() },
        })
        .collect();
    if let Some((every, shares)) = every {
        for (fr, &b) in every.iter().zip(shares) {
            let mut pos = 0;
            for g in all.iter_mut() {
                g.shares.push((&fr[pos..pos + b * g.n_in], &fr[pos + b * g.n_in..pos + b * (g.n_in + g.n_out)]));
                pos += b * (g.n_in + g.n_out);
            }
        }
    }
    all
}
