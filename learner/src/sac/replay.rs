//! SAC's replay memory (COACH's `ExperienceReplay`): a ring of transitions sampled uniformly
//! with replacement. Episodes are stored whole and in order, so a step's next observation is
//! the next slot's, and observations are stored once. The camera's pixels are stored as
//! bytes (a 120×160 frame is 19 kB, not 77); a value there that is not a whole number in
//! 0..=255 is refused, never rounded.

use super::Batch;
use rand::Rng;
use std::ops::Range;

/// Why an episode was not stored.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReplayError {
    /// Its observations are not `steps × obs` values.
    #[error("an episode of {steps} steps has {values} observation values, expected {per} a step")]
    Shape {
        /// Steps.
        steps: usize,
        /// Values given.
        values: usize,
        /// Values per step.
        per: usize,
    },
    /// A pixel that is not a byte.
    #[error("observation value {index} of step {step} is {value}, expected a pixel (a whole number in 0..=255)")]
    NotAByte {
        /// The step.
        step: usize,
        /// Index in the observation.
        index: usize,
        /// The value.
        value: f32,
    },
}

/// The replay memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Replay {
    capacity: usize,
    per: usize,
    /// The parts of an observation stored as bytes (the camera's pixels), in order.
    bytes: Vec<Range<usize>>,
    byte_len: usize,
    pixels: Vec<u8>,
    floats: Vec<f32>,
    action: Vec<[f32; 2]>,
    reward: Vec<f32>,
    /// 0: the step has a successor in the next slot; 1: the episode ended there; 2: the
    /// episode was cut there (no successor: never sampled).
    end: Vec<u8>,
    len: usize,
    head: usize,
    added: u64,
}

impl Replay {
    /// An empty memory of `capacity` transitions of `per` values, the parts `bytes` of each
    /// held as bytes.
    pub fn new(capacity: usize, per: usize, bytes: Vec<Range<usize>>) -> Replay {
        let capacity = capacity.max(1);
        let byte_len = bytes.iter().map(|r| r.len()).sum();
        Replay {
            capacity,
            per,
            bytes,
            byte_len,
            pixels: Vec::new(),
            floats: Vec::new(),
            action: Vec::new(),
            reward: Vec::new(),
            end: Vec::new(),
            len: 0,
            head: 0,
            added: 0,
        }
    }

    /// Transitions held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Nothing held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The most it holds.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Transitions ever stored.
    pub fn added(&self) -> u64 {
        self.added
    }

    /// Store one episode: `obs` (`steps × per`), the actions in [-1, 1], the rewards, and
    /// whether it ended at its last step (`done`) or was cut there. Nothing is stored when
    /// any of it is refused.
    pub fn push_episode(
        &mut self,
        obs: &[f32],
        actions: &[[f32; 2]],
        rewards: &[f32],
        done: bool,
    ) -> Result<(), ReplayError> {
        let steps = rewards.len();
        if obs.len() != steps * self.per || actions.len() != steps {
            return Err(ReplayError::Shape { steps, values: obs.len(), per: self.per });
        }
        for (step, row) in obs.chunks_exact(self.per.max(1)).enumerate() {
            for r in &self.bytes {
                if let Some(k) = row[r.clone()].iter().position(|v| !(v.fract() == 0.0 && (0.0..=255.0).contains(v))) {
                    return Err(ReplayError::NotAByte { step, index: r.start + k, value: row[r.start + k] });
                }
            }
        }
        for (step, row) in obs.chunks_exact(self.per.max(1)).enumerate().take(steps) {
            let end = match (step + 1 == steps, done) {
                (false, _) => 0,
                (true, true) => 1,
                (true, false) => 2,
            };
            self.put(row, actions[step], rewards[step], end);
        }
        Ok(())
    }

    fn put(&mut self, row: &[f32], action: [f32; 2], reward: f32, end: u8) {
        let slot = self.head;
        let fl = self.per - self.byte_len;
        if self.reward.len() < self.capacity {
            self.pixels.resize(self.pixels.len() + self.byte_len, 0);
            self.floats.resize(self.floats.len() + fl, 0.0);
            self.action.push(action);
            self.reward.push(reward);
            self.end.push(end);
        } else {
            self.action[slot] = action;
            self.reward[slot] = reward;
            self.end[slot] = end;
        }
        let (mut pb, mut pf) = (slot * self.byte_len, slot * fl);
        let mut at = 0;
        for r in &self.bytes {
            for v in &row[at..r.start] {
                self.floats[pf] = *v;
                pf += 1;
            }
            for v in &row[r.clone()] {
                self.pixels[pb] = *v as u8;
                pb += 1;
            }
            at = r.end;
        }
        for v in &row[at..] {
            self.floats[pf] = *v;
            pf += 1;
        }
        self.head = (self.head + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
        self.added += 1;
    }

    /// The observation in `slot`, appended to `out`.
    fn obs_into(&self, slot: usize, out: &mut Vec<f32>) {
        let fl = self.per - self.byte_len;
        let (mut pb, mut pf) = (slot * self.byte_len, slot * fl);
        let mut at = 0;
        for r in &self.bytes {
            out.extend_from_slice(&self.floats[pf..pf + (r.start - at)]);
            pf += r.start - at;
            out.extend(self.pixels[pb..pb + r.len()].iter().map(|&b| b as f32));
            pb += r.len();
            at = r.end;
        }
        out.extend_from_slice(&self.floats[pf..pf + (self.per - at)]);
    }

    /// Transitions that can be sampled (a cut episode's last step cannot).
    pub fn usable(&self) -> usize {
        self.end.iter().filter(|&&e| e != 2).count()
    }

    /// `n` transitions drawn uniformly with replacement; `None` while none is usable.
    pub fn sample(&self, n: usize, rng: &mut impl Rng) -> Option<Batch> {
        if !self.end.iter().any(|&e| e != 2) {
            return None;
        }
        let mut b = Batch::default();
        while b.len() < n {
            let slot = rng.random_range(0..self.len);
            let end = self.end[slot];
            if end == 2 {
                continue;
            }
            self.obs_into(slot, &mut b.obs);
            // An ended episode's next observation is not used (no bootstrap): its own stands in.
            let next = if end == 1 { slot } else { (slot + 1) % self.capacity };
            self.obs_into(next, &mut b.next_obs);
            b.action.extend_from_slice(&self.action[slot]);
            b.reward.push(self.reward[slot]);
            b.done.push(if end == 1 { 1.0 } else { 0.0 });
        }
        Some(b)
    }
}
