//! The experience buffer: episodes waiting for the next update, and those dropped on the way
//! in, each counted under its reason. A batch seen before (same worker, same sequence number)
//! is a duplicate; an episode whose observations do not fit the run, or that is empty, is bad;
//! one acted by a version more than `max_lag` behind the learner's (or by a version this
//! learner never published, before a restart) is stale, on arrival or after an update.

use policy::Trajectory;
use std::collections::{BTreeSet, HashMap};

/// What became of an episode offered to the buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Admitted {
    /// Kept for training.
    Kept,
    /// Not the run's observation size, or empty.
    Bad,
    /// Too old, or from a version this learner never published.
    Stale,
}

/// Episodes waiting for an update, and the counts of what was dropped.
#[derive(Default)]
pub(super) struct Buffer {
    trajs: Vec<Trajectory>,
    /// The worker of each buffered episode.
    from: Vec<String>,
    /// Per worker, the batch numbers seen in each of its last lives (a life: the number's
    /// high 32 bits), the newest last.
    seen: HashMap<String, Vec<(u64, BTreeSet<u64>)>>,
    /// Batches dropped as duplicates.
    pub(super) dup: u64,
    /// Episodes dropped as stale.
    pub(super) stale: u64,
    /// Episodes dropped as malformed.
    pub(super) bad: u64,
    /// Episodes received (kept or not).
    pub(super) received: u64,
}

/// Batch numbers remembered per life of a worker.
const SEEN_PER_WORKER: usize = 4096;
/// Lives remembered per worker.
const LIVES_PER_WORKER: usize = 8;

/// An order of episodes by what they hold: the version that acted, the world, the
/// environment and its episode counter (both local to a worker), then the behaviour
/// log-probabilities and rewards bit for bit, which two workers' episodes share only if they
/// are the same episode. No worker's name enters it: agents that swap names between runs
/// (the coordinator numbers them as they register) still give the same order.
pub(super) fn canonical(a: &Trajectory, b: &Trajectory) -> std::cmp::Ordering {
    let bits = |x: &f32| x.to_bits();
    (a.policy_version, &a.world, a.env, a.episode)
        .cmp(&(b.policy_version, &b.world, b.env, b.episode))
        .then_with(|| a.logp.iter().map(bits).cmp(b.logp.iter().map(bits)))
        .then_with(|| a.rewards.iter().map(bits).cmp(b.rewards.iter().map(bits)))
}

/// Whether an episode acted by `acted` is too old (or too new) for a learner at `version`.
pub(super) fn is_stale(acted: u64, version: u64, max_lag: u64) -> bool {
    acted > version || version - acted > max_lag
}

impl Buffer {
    /// An empty buffer that has received `received` episodes before (a resumed run).
    pub(super) fn new(received: u64) -> Buffer {
        Buffer { received, ..Buffer::default() }
    }

    /// Whether batch `seq` of `worker` is new (a repeat is counted as a duplicate). A worker
    /// numbers its batches upwards within a life of its process, the life in the number's
    /// high 32 bits (drawn at random when it starts: a worker started again under its id is
    /// not taken for its earlier life, whatever the clocks say). The last
    /// [`SEEN_PER_WORKER`] numbers of each of its last [`LIVES_PER_WORKER`] lives are kept;
    /// one below all of those is a repeat, so a run of days holds a bounded set.
    pub(super) fn first_sight(&mut self, worker: &str, seq: u64) -> bool {
        let lives = self.seen.entry(worker.to_string()).or_default();
        let life = seq >> 32;
        let k = match lives.iter().position(|(l, _)| *l == life) {
            Some(k) => k,
            None => {
                if lives.len() >= LIVES_PER_WORKER {
                    lives.remove(0);
                }
                lives.push((life, BTreeSet::new()));
                lives.len() - 1
            }
        };
        let seen = &mut lives[k].1;
        let below = seen.len() >= SEEN_PER_WORKER && seen.first().is_some_and(|f| seq < *f);
        let new = !below && seen.insert(seq);
        if seen.len() > SEEN_PER_WORKER {
            seen.pop_first();
        }
        if !new {
            self.dup += 1;
        }
        new
    }

    /// Offer one episode of `worker`'s to a learner at `version`.
    pub(super) fn admit(
        &mut self,
        worker: &str,
        t: Trajectory,
        version: u64,
        max_lag: u64,
        obs_size: usize,
    ) -> Admitted {
        self.received += 1;
        if t.obs.len() != t.len() * obs_size || t.is_empty() {
            self.bad += 1;
            return Admitted::Bad;
        }
        if is_stale(t.policy_version, version, max_lag) {
            self.stale += 1;
            return Admitted::Stale;
        }
        self.trajs.push(t);
        self.from.push(worker.to_string());
        Admitted::Kept
    }

    /// Episodes waiting.
    pub(super) fn len(&self) -> usize {
        self.trajs.len()
    }

    /// The bytes the episodes waiting hold.
    pub(super) fn bytes(&self) -> usize {
        self.trajs.iter().map(Trajectory::heap_bytes).sum()
    }

    /// The first `n` episodes to arrive (fewer if fewer wait), with their workers, in the
    /// order of their content ([`canonical`]), not of their arrival: the update shuffles its
    /// minibatches over that order, so a run whose workers deliver the same episodes makes
    /// the same update however their deliveries interleave.
    pub(super) fn take(&mut self, n: usize) -> (Vec<Trajectory>, Vec<String>) {
        let n = n.min(self.trajs.len());
        let mut taken: Vec<(Trajectory, String)> = self.trajs.drain(..n).zip(self.from.drain(..n)).collect();
        taken.sort_by(|a, b| canonical(&a.0, &b.0));
        taken.into_iter().unzip()
    }

    /// After an update to `version`: the episodes still waiting that it made too old are
    /// dropped and counted.
    pub(super) fn drop_stale(&mut self, version: u64, max_lag: u64) {
        let mut i = 0;
        while i < self.trajs.len() {
            if is_stale(self.trajs[i].policy_version, version, max_lag) {
                self.trajs.remove(i);
                self.from.remove(i);
                self.stale += 1;
            } else {
                i += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(version: u64, steps: usize, obs_per_step: usize) -> Trajectory {
        Trajectory {
            policy_version: version,
            obs: vec![0.0; steps * obs_per_step],
            rewards: vec![1.0; steps],
            choices: vec![policy::Choice::Discrete(0); steps],
            logp: vec![0.0; steps],
            values: vec![0.0; steps],
            done: true,
            ..Default::default()
        }
    }

    /// Issue 29: each episode is kept, or dropped under its reason.
    #[test]
    fn each_episode_is_kept_or_dropped_under_its_reason() {
        // A learner at version 10 that takes episodes at most 2 versions old, 4 floats a step.
        // (episode, what becomes of it)
        let table = [
            (episode(10, 5, 4), Admitted::Kept),
            (episode(8, 5, 4), Admitted::Kept),
            (episode(7, 5, 4), Admitted::Stale),
            (episode(11, 5, 4), Admitted::Stale),
            (episode(10, 5, 3), Admitted::Bad),
            (episode(10, 0, 4), Admitted::Bad),
            (Trajectory { obs: vec![0.0; 21], ..episode(10, 5, 4) }, Admitted::Bad),
        ];
        let mut b = Buffer::new(100);
        for (i, (t, want)) in table.iter().enumerate() {
            assert_eq!(b.admit("w", t.clone(), 10, 2, 4), *want, "row {i}");
        }
        assert_eq!((b.len(), b.stale, b.bad, b.received), (2, 2, 3, 107));
    }

    /// Issue 29: a batch seen before is a duplicate, per worker.
    #[test]
    fn a_batch_seen_before_is_a_duplicate_per_worker() {
        let mut b = Buffer::default();
        let table = [("a", 1, true), ("a", 2, true), ("a", 1, false), ("b", 1, true), ("b", 1, false), ("a", 3, true)];
        for (worker, seq, new) in table {
            assert_eq!(b.first_sight(worker, seq), new, "{worker} {seq}");
        }
        assert_eq!(b.dup, 2);
        // A long run: the set stays bounded, and an old number is still a repeat.
        for seq in 10..10 + 3 * SEEN_PER_WORKER as u64 {
            assert!(b.first_sight("c", seq));
        }
        assert_eq!(b.seen["c"][0].1.len(), SEEN_PER_WORKER);
        assert!(!b.first_sight("c", 11) && !b.first_sight("c", 10 + 3 * SEEN_PER_WORKER as u64 - 1));
        // A worker started again (a new life, even one numbered lower) starts afresh; its
        // earlier life's repeats are still repeats.
        assert!(b.first_sight("c", 1 << 32) && b.first_sight("c", (1 << 32) + 1));
        assert!(!b.first_sight("c", 1 << 32));
        assert!(b.first_sight("d", 5 << 32) && b.first_sight("d", (2 << 32) + 1));
        assert!(!b.first_sight("c", 12));
        // Lives are bounded too.
        for life in 0..3 * LIVES_PER_WORKER as u64 {
            b.first_sight("e", life << 32);
        }
        assert_eq!(b.seen["e"].len(), LIVES_PER_WORKER);
    }

    /// Issue 29: the first episodes to arrive are trained on, and an update ages the rest.
    #[test]
    fn the_first_to_arrive_are_trained_on_and_an_update_ages_the_rest() {
        let mut b = Buffer::default();
        for (v, w) in [(5, "a"), (6, "b"), (7, "a"), (7, "c")] {
            assert_eq!(b.admit(w, episode(v, 3, 2), 7, 2, 2), Admitted::Kept);
        }
        let (trajs, from) = b.take(2);
        assert_eq!(trajs.iter().map(|t| t.policy_version).collect::<Vec<_>>(), [5, 6]);
        assert_eq!(from, ["a", "b"]);
        // The update made version 9: the version-7 episodes are 2 behind (kept); at 10 they go.
        b.drop_stale(9, 2);
        assert_eq!((b.len(), b.stale), (2, 0));
        b.drop_stale(10, 2);
        assert_eq!((b.len(), b.stale), (0, 2));
        assert_eq!(b.take(5).0.len(), 0);
    }
}
