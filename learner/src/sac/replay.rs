//! SAC's replay memory (COACH's `ExperienceReplay`): a ring of transitions sampled uniformly
//! with replacement. Episodes are stored whole and in order, so a step's next observation is
//! the next slot's, and observations are stored once. The camera's pixels are stored as
//! bytes (a 120×160 frame is 19 kB, not 77); a value there that is not a whole number in
//! 0..=255 is refused, never rounded.

use super::Batch;
use rand::Rng;
use std::ops::Range;

/// Why a replay memory's bytes (what [`Replay::save`] wrote) were refused: what is wrong with
/// them, naming the header key, tensor or byte range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct BadMemory(pub String);

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

    /// Values per observation.
    pub fn per(&self) -> usize {
        self.per
    }

    /// Write the memory to `path` (safetensors, streamed to a temporary file then renamed):
    /// its buffers as they lie in the ring, the pixels without a copy, and where the oldest
    /// transition is.
    pub fn save(&self, path: &std::path::Path) -> Result<(), policy::FileError> {
        let tmp = path.with_extension("tmp");
        self.with_views(|views, info| safetensors::serialize_to_file(views, Some(info), &tmp))
            .map_err(|e| policy::FileError::invalid(path.display().to_string(), e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(policy::FileError::io_at(path))
    }

    /// The memory as [`Replay::save`] writes it, in memory (what a learner team's joiner
    /// receives).
    pub fn to_bytes(&self) -> Vec<u8> {
        self.with_views(|views, info| safetensors::serialize(views, Some(info))).expect("a memory's tensors serialise")
    }

    fn with_views<T>(
        &self,
        write: impl FnOnce(
            Vec<(&str, safetensors::tensor::TensorView<'_>)>,
            std::collections::HashMap<String, String>,
        ) -> Result<T, safetensors::SafeTensorError>,
    ) -> Result<T, safetensors::SafeTensorError> {
        use safetensors::{Dtype, tensor::TensorView};
        let le = |v: &mut dyn Iterator<Item = f32>| -> Vec<u8> { v.flat_map(|x| x.to_le_bytes()).collect() };
        let floats = le(&mut self.floats.iter().copied());
        let action = le(&mut self.action.iter().flatten().copied());
        let reward = le(&mut self.reward.iter().copied());
        let ranges: Vec<String> = self.bytes.iter().map(|r| format!("{}-{}", r.start, r.end)).collect();
        let info = std::collections::HashMap::from([
            ("format".to_string(), "paddock-replay-1".to_string()),
            ("per".to_string(), self.per.to_string()),
            ("bytes".to_string(), ranges.join(",")),
            ("added".to_string(), self.added.to_string()),
            ("oldest".to_string(), self.oldest().to_string()),
            ("capacity".to_string(), self.capacity.to_string()),
        ]);
        let named: [(&str, &[u8], Dtype); 5] = [
            ("pixels", &self.pixels, Dtype::U8),
            ("floats", &floats, Dtype::F32),
            ("action", &action, Dtype::F32),
            ("reward", &reward, Dtype::F32),
            ("end", &self.end, Dtype::U8),
        ];
        let views: Vec<(&str, TensorView<'_>)> = named
            .iter()
            .map(|(n, b, d)| (*n, TensorView::new(*d, vec![b.len() * 8 / d.bitsize()], b).expect("sizes agree")))
            .collect();
        write(views, info)
    }

    /// The slot of the oldest transition.
    fn oldest(&self) -> usize {
        if self.len < self.capacity { 0 } else { self.head }
    }

    /// The capacity a memory's bytes were written with (`None`: not said, an older file).
    pub fn capacity_of(bytes: &[u8]) -> Result<Option<usize>, BadMemory> {
        let (_, meta) = safetensors::SafeTensors::read_metadata(bytes)
            .map_err(|e| BadMemory(format!("not a safetensors file: {e}")))?;
        match meta.metadata().as_ref().and_then(|m| m.get("capacity")) {
            None => Ok(None),
            Some(c) => c.parse().map(Some).map_err(|_| BadMemory(format!("'capacity' is {c:?}, not a number"))),
        }
    }

    /// A memory of `capacity` transitions holding what [`Replay::save`] wrote (the newest
    /// of them, when it held more).
    pub fn from_bytes(bytes: &[u8], capacity: usize) -> Result<Replay, BadMemory> {
        let file = Stored::read(bytes).map_err(BadMemory)?;
        let mut r = Replay::new(capacity, file.per, file.bytes.clone());
        let n = file.end.len();
        if n == r.capacity && file.oldest > 0 {
            // A full ring into one of its size: as it lay, so that it writes the same bytes
            // again and draws the same batches (a learner team's joiner holds the leader's).
            let fl = file.per - r.byte_len;
            r.pixels = file.pixels.to_vec();
            r.floats = (0..n * fl).map(|i| le(file.floats, i)).collect();
            r.action = (0..n).map(|i| [le(file.action, 2 * i), le(file.action, 2 * i + 1)]).collect();
            r.reward = (0..n).map(|i| le(file.reward, i)).collect();
            r.end = file.end.to_vec();
            (r.len, r.head) = (n, file.oldest);
            r.added = file.added.max(n as u64);
            return Ok(r);
        }
        r.append(&file);
        Ok(r)
    }

    /// Append what [`Replay::save`] or [`Replay::segment_since`] wrote, oldest first (the
    /// oldest of this memory's make way when it is full); false, and nothing appended, when
    /// this memory has stored as many transitions as it had (it holds them already). Refused,
    /// with nothing changed, unless it holds transitions of this memory's shape.
    pub fn extend_from_bytes(&mut self, bytes: &[u8]) -> Result<bool, BadMemory> {
        let file = Stored::read(bytes).map_err(BadMemory)?;
        if file.per != self.per || file.bytes != self.bytes {
            return Err(BadMemory(format!(
                "transitions of {} values (bytes at {:?}), this run's have {} (bytes at {:?})",
                file.per, file.bytes, self.per, self.bytes
            )));
        }
        if file.added <= self.added {
            return Ok(false);
        }
        self.append(&file);
        Ok(true)
    }

    /// The parts of an observation held as bytes.
    pub fn byte_ranges(&self) -> &[Range<usize>] {
        &self.bytes
    }

    fn append(&mut self, file: &Stored<'_>) {
        let n = file.end.len();
        let fl = self.per - self.byte_len;
        let mut row = vec![0.0f32; self.per];
        // Oldest first (as the ring lay, when it was not full); the newest `capacity` of them
        // when they do not all fit.
        for i in (0..n).map(|k| (file.oldest + k) % n.max(1)).skip(n.saturating_sub(self.capacity)) {
            let (mut pb, mut pf, mut at) = (i * self.byte_len, i * fl, 0);
            for range in self.bytes.clone() {
                for v in &mut row[at..range.start] {
                    *v = le(file.floats, pf);
                    pf += 1;
                }
                for v in &mut row[range.clone()] {
                    *v = file.pixels[pb] as f32;
                    pb += 1;
                }
                at = range.end;
            }
            for v in &mut row[at..] {
                *v = le(file.floats, pf);
                pf += 1;
            }
            self.put(&row, [le(file.action, 2 * i), le(file.action, 2 * i + 1)], le(file.reward, i), file.end[i]);
        }
        self.added = self.added.max(file.added);
    }

    /// The transitions stored since `from` (a count of [`Replay::added`]) that the ring still
    /// holds, written as [`Replay::save`] writes a memory, for [`Replay::extend_from_bytes`]
    /// to append to the memory they followed; `None` when there are none. Written between
    /// iterations, it holds whole episodes.
    pub fn segment_since(&self, from: u64) -> Option<Vec<u8>> {
        let n = (self.added.saturating_sub(from)).min(self.len as u64) as usize;
        if n == 0 {
            return None;
        }
        let mut seg = Replay::new(n, self.per, self.bytes.clone());
        let mut row = Vec::with_capacity(self.per);
        for k in (1..=n).rev() {
            let slot = (self.head + self.capacity - k) % self.capacity;
            row.clear();
            self.obs_into(slot, &mut row);
            seg.put(&row, self.action[slot], self.reward[slot], self.end[slot]);
        }
        seg.added = self.added;
        Some(seg.to_bytes())
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
        // Drawn by age (0: the oldest), so that two memories holding the same transitions
        // give the same batch from the same seed however their rings lie.
        let oldest = self.oldest();
        while b.len() < n {
            let slot = (oldest + rng.random_range(0..self.len)) % self.capacity;
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

/// A memory's file, read but not copied.
struct Stored<'a> {
    per: usize,
    bytes: Vec<Range<usize>>,
    added: u64,
    oldest: usize,
    pixels: &'a [u8],
    floats: &'a [u8],
    action: &'a [u8],
    reward: &'a [u8],
    end: &'a [u8],
}

impl<'a> Stored<'a> {
    fn read(bytes: &'a [u8]) -> Result<Stored<'a>, String> {
        let (_, meta) =
            safetensors::SafeTensors::read_metadata(bytes).map_err(|e| format!("not a safetensors file: {e}"))?;
        let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| format!("not a safetensors file: {e}"))?;
        let info = meta.metadata().clone().unwrap_or_default();
        let field = |k: &str| info.get(k).cloned().ok_or_else(|| format!("no '{k}' in its header"));
        if field("format")? != "paddock-replay-1" {
            return Err(format!("format '{}', expected paddock-replay-1", field("format")?));
        }
        let per: usize = field("per")?.parse().map_err(|_| "'per' is not a number".to_string())?;
        let mut ranges = Vec::new();
        for part in field("bytes")?.split(',').filter(|p| !p.is_empty()) {
            let (a, b) = part.split_once('-').ok_or_else(|| format!("byte range '{part}'"))?;
            let (a, b): (usize, usize) = (
                a.parse().map_err(|_| format!("byte range '{part}'"))?,
                b.parse().map_err(|_| format!("byte range '{part}'"))?,
            );
            if a > b || b > per || ranges.last().is_some_and(|r: &Range<usize>| r.end > a) {
                return Err(format!("byte range '{part}' does not fit {per} values"));
            }
            ranges.push(a..b);
        }
        // Borrowed from `bytes`: a camera memory is not copied twice on the way in.
        let tensor = |n: &str| st.tensor(n).map(|t| t.data()).map_err(|_| format!("has no tensor '{n}'"));
        let (pixels, floats, action, reward, end) =
            (tensor("pixels")?, tensor("floats")?, tensor("action")?, tensor("reward")?, tensor("end")?);
        let n = end.len();
        let byte_len: usize = ranges.iter().map(|r| r.len()).sum();
        let fl = per - byte_len;
        if pixels.len() != n * byte_len || floats.len() != n * fl * 4 || action.len() != n * 8 || reward.len() != n * 4
        {
            return Err(format!("tensor sizes do not agree with {n} transitions of {per} values"));
        }
        if end.iter().any(|&e| e > 2) {
            return Err("tensor 'end' holds values other than 0, 1 and 2".into());
        }
        let oldest: usize = field("oldest")?.parse().map_err(|_| "'oldest' is not a number".to_string())?;
        if n > 0 && oldest >= n {
            return Err(format!("'oldest' is {oldest}, past the {n} transitions held"));
        }
        let added = field("added")?.parse().unwrap_or(n as u64).max(n as u64);
        Ok(Stored { per, bytes: ranges, added, oldest, pixels, floats, action, reward, end })
    }
}

/// The little-endian f32 at `i` of `b`.
fn le(b: &[u8], i: usize) -> f32 {
    f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
}
