//! What the learner's tests share: a team of threads of one process.

use learner::{GroupError, Reducer};
use std::collections::HashMap;
use std::sync::{Arc, Condvar, Mutex};

/// What the members posted, by (update, exchange, rank).
type Posts = HashMap<(u64, u64, usize), (Vec<f32>, Vec<f32>)>;

/// The threads' shared board: shares posted, and a wake-up when one is.
#[derive(Default)]
struct Board {
    posts: Mutex<Posts>,
    posted: Condvar,
}

/// A thread of one process as a team member. Exchange 0 opens every update (every member
/// makes it), so counting them tells the updates apart.
pub struct Threads {
    rank: usize,
    size: usize,
    board: Arc<Board>,
    /// The updates begun (exchange 0 seen).
    pub update: u64,
}

impl Threads {
    /// `size` members sharing one board.
    pub fn team(size: usize) -> Vec<Threads> {
        let board = Arc::new(Board::default());
        (0..size).map(|rank| Threads { rank, size, board: board.clone(), update: 0 }).collect()
    }
}

impl Reducer for Threads {
    fn shard(&self) -> (usize, usize) {
        (self.rank, self.size)
    }

    fn all_reduce(
        &mut self,
        step: u64,
        ranks: &[usize],
        values: &mut [f32],
        factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError> {
        if step == 0 {
            self.update += 1;
        }
        let u = self.update;
        let mut posts = self.board.posts.lock().unwrap();
        if ranks.contains(&self.rank) {
            posts.insert((u, step, self.rank), (values.to_vec(), factors));
            self.board.posted.notify_all();
        }
        while !ranks.iter().all(|&r| posts.contains_key(&(u, step, r))) {
            posts = self.board.posted.wait(posts).unwrap();
        }
        let shares: Vec<&(Vec<f32>, Vec<f32>)> = ranks.iter().map(|&r| &posts[&(u, step, r)]).collect();
        for (i, v) in values.iter_mut().enumerate() {
            let mut acc = shares[0].0[i];
            for s in &shares[1..] {
                acc += s.0[i];
            }
            *v = acc;
        }
        Ok(shares.iter().map(|s| s.1.clone()).collect())
    }
}
