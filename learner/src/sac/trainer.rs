//! SAC in a training run: every episode that arrives goes
//! into the replay memory, whatever version acted (off-policy data is never stale); an
//! iteration then takes `sac_gradient_steps_per_transition` gradient steps per new transition
//! (DeepRacer's one), on batches of `batch_size` drawn with replacement (while the memory
//! holds fewer, batches of the largest power of two below the iteration's steps, as
//! DeepRacer's trainer does), moves V's target once, after the iteration's first gradient
//! step, and publishes the policy as a new version.
//!
//! A checkpoint keeps the critics (`sac.safetensors` beside the model) and the transitions
//! stored since the last checkpoint (a part in the run folder's `replay/`); the whole replay
//! memory is written to the run folder (`replay.safetensors`) when the run ends, or when the
//! parts have grown as large as the memory, and the parts are then let go. A resumed run
//! continues with the critics of its last checkpoint and the memory the run kept: after a
//! clean end every transition, those of updates after the last checkpoint too (the updates
//! are made again; the experience is not thrown away), after a crash those up to its last
//! checkpoint; or it says which it starts without.
//!
//! In a learner team every member holds a copy of the replay memory: each plan
//! brings the iteration's episodes, which every member stores in the same order, and its
//! seed, from which every member draws the same batches and noise; each gradient step is then
//! shared as [`Sac::step_in`] shares it. A joiner takes over the networks, their optimisers
//! and the memory.

use super::{Losses, Replay, Sac, SacGpu, SacNets, SacSettings, Tapes};
use crate::group::{Alone, Reducer};
use crate::hyperparams::{Hyperparameters, LossType};
use crate::update::{LearnerState, Refused, StateMismatch};
use faer::Par;
use gpu::GpuError;
use policy::model::Head;
use policy::nn::InputShape;
use policy::{ActorCritic, Choice, FileError, ModelMetadata, Trajectory};
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use std::collections::HashMap;
use std::path::Path;

/// The critics' file in a checkpoint folder.
pub const CRITICS_FILE: &str = "sac.safetensors";
/// The replay memory's file in the run folder.
pub const REPLAY_FILE: &str = "replay.safetensors";
/// The folder of the parts of the replay memory written at each checkpoint since
/// [`REPLAY_FILE`] (`{count}.safetensors`, the transitions stored until then).
pub const REPLAY_PARTS: &str = "replay";

/// The parts in the run folder `root`, in the order they were written.
fn memory_parts(root: &Path) -> std::io::Result<Vec<std::path::PathBuf>> {
    let mut parts: Vec<_> = match std::fs::read_dir(root.join(REPLAY_PARTS)) {
        Ok(d) => d
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(e),
    };
    parts.sort();
    Ok(parts)
}

/// What one SAC iteration did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SacStats {
    /// Samples trained on (gradient steps × batch size).
    pub samples: usize,
    /// The policy's loss, averaged over the iteration's gradient steps.
    pub policy_loss: f64,
    /// V's loss, averaged.
    pub value_loss: f64,
    /// The policy's entropy, averaged.
    pub entropy: f64,
    /// Gradient steps taken.
    pub gradient_steps: usize,
    /// Policy version after the iteration.
    pub policy_version: u64,
    /// SAC's own figures: the critics, the temperature, the replay memory.
    pub figures: SacFigures,
}

/// SAC's figures that no other algorithm has (`metrics.jsonl` keeps them under `sac`).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SacFigures {
    /// The Q heads' loss, averaged over the iteration's gradient steps.
    pub q_loss: f64,
    /// `min(q1, q2)` at the policy's draws, averaged.
    pub q_mean: f64,
    /// The temperature at the end of the iteration.
    pub alpha: f64,
    /// Transitions in the replay memory.
    pub replay: usize,
    /// New transitions this iteration.
    pub new_transitions: usize,
    /// Episodes not stored (a choice that is not a continuous action, or a bad observation).
    pub refused_episodes: usize,
}

/// A SAC learner in a run.
pub struct SacTrainer {
    sac: Sac,
    replay: Replay,
    model: ActorCritic,
    version: u64,
    /// Draws each update's seed (a team's leader sends it in the plan).
    seeds: ChaCha8Rng,
    tapes: Tapes,
    par: Par,
    ratio: f64,
    /// Fractional gradient steps carried to the next iteration (f32: it travels to a team's
    /// joiners as it is).
    carry: f32,
    /// The last episodes stored whose gradient steps are still to make: (new transitions,
    /// episodes refused).
    pending: Option<(usize, usize)>,
    /// Transitions stored (a count of [`Replay::added`]) that the run folder holds.
    on_disk: u64,
    /// Transitions in the parts written since the whole memory was.
    in_parts: usize,
    /// The GPU the gradient steps run on when this learner trains alone.
    gpu: Option<SacGpu>,
}

/// The settings `hyperparameters.json` gives SAC for `model`'s action space.
pub fn settings(h: &Hyperparameters, model: &ActorCritic) -> Option<SacSettings> {
    let Head::Squashed { scale } = model.head else { return None };
    Some(SacSettings {
        batch_size: h.batch_size,
        lr: h.lr as f32,
        gamma: h.discount_factor as f32,
        alpha: h.sac_alpha as f32,
        target_entropy: h.sac_target_entropy.map(|t| t as f32),
        tau: h.sac_tau as f32,
        huber: h.loss_type == LossType::Huber,
        scale,
    })
}

/// The parts of a sample held as bytes in the replay memory: the cameras' pixels.
fn pixel_ranges(meta: &ModelMetadata, obs_size: usize) -> Vec<std::ops::Range<usize>> {
    let mut at = 0;
    let mut out = Vec::new();
    for (_, shape) in policy::model::inputs(meta, obs_size) {
        if let InputShape::Image(..) = shape {
            out.push(at..at + shape.size());
        }
        at += shape.size();
    }
    out
}

impl SacTrainer {
    /// A SAC learner for `model` (SAC's policy and V: fresh, resumed or cloned) at `version`,
    /// with fresh critics and an empty replay memory.
    pub fn new(
        model: ActorCritic,
        meta: &ModelMetadata,
        obs_size: usize,
        h: &Hyperparameters,
        version: u64,
        seed: u64,
        par: Par,
    ) -> Result<SacTrainer, String> {
        let s = settings(h, &model).ok_or("SAC needs SAC's policy head (a continuous action space)")?;
        let mut seeds = ChaCha8Rng::seed_from_u64(seed ^ 0x0c1);
        let mut nets = SacNets::new(meta, obs_size, &mut seeds);
        nets.policy = model.pi.clone();
        nets.v = model.v.clone();
        nets.v_target = model.v.clone();
        let pixels = pixel_ranges(meta, obs_size);
        let capacity = replay_capacity(h.sac_replay_size, nets.obs_size(), &pixels, total_memory());
        let replay = Replay::new(capacity, nets.obs_size(), pixels);
        Ok(SacTrainer {
            sac: Sac::new(nets, s, seed),
            replay,
            model,
            version,
            seeds,
            tapes: Tapes::default(),
            par,
            ratio: h.sac_gradient_steps_per_transition,
            carry: 0.0,
            pending: None,
            on_disk: 0,
            // The first checkpoint writes the whole memory (and clears any parts a run of the
            // same folder left).
            in_parts: usize::MAX,
            gpu: None,
        })
    }

    /// Make this learner's gradient steps with the network maths on `gpu` when it trains
    /// alone.
    pub fn with_gpu(mut self, gpu: std::sync::Arc<gpu::Gpu>) -> SacTrainer {
        self.gpu = Some(SacGpu::new(gpu));
        self
    }

    /// The GPU the maths run on, if any (its adapter).
    pub fn device(&self) -> Option<&str> {
        self.gpu.as_ref().map(|g| g.adapter())
    }

    /// The replay memory.
    pub fn replay(&self) -> &Replay {
        &self.replay
    }

    /// The learner's networks and state.
    pub fn sac(&self) -> &Sac {
        &self.sac
    }

    /// Take the critics (and the temperature) from a checkpoint folder; false when it holds
    /// none.
    pub fn load_state(&mut self, dir: &Path) -> Result<bool, FileError> {
        let path = dir.join(CRITICS_FILE);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
            Err(e) => return Err(FileError::io(&path, e)),
        };
        let bad = |m: String| FileError::invalid(path.display().to_string(), m);
        let st = SafeTensors::deserialize(&bytes).map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let mut next = self.sac.clone();
        let nets = &mut next.nets;
        let mut targets: Vec<(&str, &mut Vec<f32>)> =
            vec![("q1", &mut nets.q.q1.params), ("q2", &mut nets.q.q2.params), ("v_target", &mut nets.v_target.params)];
        if let Some(e) = nets.q.embed.as_mut() {
            targets.push(("q_embed", &mut e.params));
        }
        for (name, dst) in targets {
            read_into(&st, name, dst).map_err(bad)?;
        }
        let mut la = [0.0f32];
        read_into(&st, "log_alpha", &mut la).map_err(bad)?;
        next.log_alpha = la[0];
        self.sac = next;
        Ok(true)
    }

    /// Take the replay memory the run folder `root` kept: the whole memory written when a run
    /// ended (or when its parts grew as large as the memory), then the parts written at each
    /// checkpoint since, in order. False when it holds none. Refused, naming the file, when
    /// one does not fit this run (its memory then starts empty).
    pub fn load_memory(&mut self, root: &Path) -> Result<bool, FileError> {
        let mut found = false;
        let mut memory = Replay::new(self.replay.capacity(), self.replay.per(), self.replay.byte_ranges().to_vec());
        let path = root.join(REPLAY_FILE);
        match std::fs::read(&path) {
            Ok(bytes) => {
                memory.extend_from_bytes(&bytes).map_err(|e| FileError::invalid(path.display().to_string(), e.0))?;
                found = true;
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(FileError::io(&path, e)),
        }
        let mut parts = 0;
        let parts_dir = root.join(REPLAY_PARTS);
        for part in memory_parts(root).map_err(FileError::io_at(&parts_dir))? {
            let bytes = std::fs::read(&part).map_err(FileError::io_at(&part))?;
            let before = memory.added();
            if memory.extend_from_bytes(&bytes).map_err(|e| FileError::invalid(part.display().to_string(), e.0))? {
                parts += (memory.added() - before) as usize;
                found = true;
            }
        }
        self.replay = memory;
        (self.on_disk, self.in_parts) = (self.replay.added(), parts);
        Ok(found)
    }

    /// Store the episodes; returns (new transitions, episodes refused).
    fn store(&mut self, trajs: &[Trajectory]) -> (usize, usize) {
        let (mut new, mut refused) = (0, 0);
        for t in trajs {
            let actions: Option<Vec<[f32; 2]>> = t
                .choices
                .iter()
                .map(|c| match c {
                    Choice::Continuous(a) if a.iter().all(|v| v.is_finite() && v.abs() <= 1.0) => Some(*a),
                    _ => None,
                })
                .collect();
            let stored = actions
                .ok_or_else(|| "an action that is not SAC's (a continuous action in [-1, 1])".to_string())
                .and_then(|a| self.replay.push_episode(&t.obs, &a, &t.rewards, t.done).map_err(|e| e.to_string()));
            match stored {
                Ok(()) => new += t.rewards.len(),
                Err(why) => {
                    refused += 1;
                    tracing::warn!(world = %t.world, env = t.env, episode = t.episode, "episode not stored in the replay memory: {why}");
                }
            }
        }
        (new, refused)
    }
}

/// The largest replay memory, in bytes, this machine takes from a learner team's leader: a
/// quarter of its memory, as [`replay_capacity`] caps its own (unbounded when unknown).
pub fn memory_limit() -> u64 {
    total_memory().map_or(u64::MAX, |m| m / 4)
}

/// The machine's memory in bytes (Linux's `/proc/meminfo`), if known.
fn total_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The replay memory's capacity: `wanted` transitions, or as many as a quarter of `memory`
/// holds when they would not fit (DeepRacer's million camera frames are 19 GB), which is said.
/// A quarter, so that writing it at the end and reading it back on resume, each with a copy
/// of it in hand, stay within half.
pub fn replay_capacity(wanted: usize, per: usize, pixels: &[std::ops::Range<usize>], memory: Option<u64>) -> usize {
    let bytes: usize = pixels.iter().map(|r| r.len()).sum();
    let each = (bytes + 4 * (per - bytes) + 8 + 4 + 1) as u64;
    let Some(memory) = memory else { return wanted };
    let fits = (memory / 4 / each) as usize;
    if wanted <= fits {
        return wanted;
    }
    tracing::warn!(
        "sac_replay_size {wanted} transitions of {each} bytes need {:.1} GB, more than a quarter of this machine's {:.1} GB: \
         the replay memory holds {fits}",
        (wanted as u64 * each) as f64 / 1e9,
        memory as f64 / 1e9
    );
    fits.max(1)
}

fn read_into(st: &SafeTensors, name: &str, dst: &mut [f32]) -> Result<(), String> {
    let t = st.tensor(name).map_err(|_| format!("has no tensor '{name}'"))?;
    if t.dtype() != Dtype::F32 || t.data().len() != dst.len() * 4 {
        return Err(format!(
            "tensor '{name}' holds {} bytes of {:?}, expected {} f32",
            t.data().len(),
            t.dtype(),
            dst.len()
        ));
    }
    for (d, c) in dst.iter_mut().zip(t.data().chunks_exact(4)) {
        *d = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    Ok(())
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Write named f32 vectors as safetensors, atomically (a temporary file renamed).
pub(crate) fn write_tensors(
    path: &Path,
    named: &[(&str, Vec<u8>, Dtype)],
    info: HashMap<String, String>,
) -> Result<(), FileError> {
    let views: Vec<(String, TensorView<'_>)> = named
        .iter()
        .map(|(n, b, d)| {
            let len = b.len() * 8 / d.bitsize();
            (n.to_string(), TensorView::new(*d, vec![len], b).expect("sizes agree"))
        })
        .collect();
    let bytes = safetensors::serialize(views, Some(info))
        .map_err(|e| FileError::invalid(path.display().to_string(), e.to_string()))?;
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).and_then(|_| std::fs::rename(&tmp, path)).map_err(FileError::io_at(path))
}

/// What a run and a learner team need of a SAC learner, besides its updates.
impl SacTrainer {
    /// The policy version workers act with (+1 per accepted iteration).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The model published, evaluated and saved: SAC's policy and V.
    pub fn model(&self) -> &ActorCritic {
        &self.model
    }

    /// The learning rate the next iteration uses.
    pub fn lr(&self) -> f64 {
        self.sac.settings.lr as f64
    }

    /// Set the learning rate the next iteration uses.
    pub fn set_lr(&mut self, lr: f64) {
        self.sac.set_lr(lr as f32);
    }

    /// Write the critics and the temperature into the checkpoint folder `dir`
    /// ([`CRITICS_FILE`]).
    pub fn save_state(&self, dir: &Path) -> Result<(), FileError> {
        let nets = &self.sac.nets;
        let mut named = vec![
            ("q1", f32_bytes(&nets.q.q1.params), Dtype::F32),
            ("q2", f32_bytes(&nets.q.q2.params), Dtype::F32),
            ("v_target", f32_bytes(&nets.v_target.params), Dtype::F32),
            ("log_alpha", f32_bytes(&[self.sac.log_alpha]), Dtype::F32),
        ];
        if let Some(e) = &nets.q.embed {
            named.push(("q_embed", f32_bytes(&e.params), Dtype::F32));
        }
        let info = HashMap::from([
            ("format".to_string(), "paddock-sac-critics-1".to_string()),
            ("policy_version".to_string(), self.version.to_string()),
        ]);
        write_tensors(&dir.join(CRITICS_FILE), &named, info)
    }

    /// Write the whole replay memory into the run folder `root` ([`REPLAY_FILE`]) and let
    /// the parts go.
    pub fn save_memory(&self, root: &Path) -> Result<(), FileError> {
        self.replay.save(&root.join(REPLAY_FILE))?;
        // The parts are in the whole memory now.
        match std::fs::remove_dir_all(root.join(REPLAY_PARTS)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(FileError::io(&root.join(REPLAY_PARTS), e)),
            _ => Ok(()),
        }
    }

    /// Write into the run folder `root` the transitions stored since the last checkpoint (a
    /// part in [`REPLAY_PARTS`]), or the whole memory when the parts would hold more than it.
    pub fn save_memory_part(&mut self, root: &Path) -> Result<(), FileError> {
        let new = (self.replay.added() - self.on_disk).min(self.replay.len() as u64) as usize;
        if new == 0 {
            return Ok(());
        }
        if self.in_parts.saturating_add(new) > self.replay.capacity() {
            // As many transitions in parts as the memory holds: the whole memory instead.
            self.save_memory(root)?;
            (self.on_disk, self.in_parts) = (self.replay.added(), 0);
            return Ok(());
        }
        let Some(bytes) = self.replay.segment_since(self.on_disk) else { return Ok(()) };
        let dir = root.join(REPLAY_PARTS);
        let path = dir.join(format!("{:020}.safetensors", self.replay.added()));
        let tmp = path.with_extension("tmp");
        std::fs::create_dir_all(&dir)
            .and_then(|_| std::fs::write(&tmp, bytes))
            .and_then(|_| std::fs::rename(&tmp, &path))
            .map_err(FileError::io_at(&path))?;
        (self.on_disk, self.in_parts) = (self.replay.added(), self.in_parts + new);
        Ok(())
    }
}

/// The gradient steps owed for `new` transitions at `ratio` steps each, with `carry` steps
/// owed from before, and the fraction of a step carried on (in [0, 1)).
fn steps_and_carry(new: usize, ratio: f64, carry: f32) -> (usize, f32) {
    let wanted = new as f64 * ratio + carry as f64;
    let steps = wanted.floor() as usize;
    let carry = (wanted - steps as f64) as f32;
    // A fraction just below one rounds to one in f32: that step is made now.
    if carry >= 1.0 { (steps + 1, 0.0) } else { (steps, carry) }
}

impl SacTrainer {
    /// The gradient steps of an iteration that stored `stored` (new transitions, episodes
    /// refused), their batches and noise drawn from `seed`, each step shared with `group`;
    /// then the new version. A refused iteration leaves the networks as they were (the
    /// episodes stay in the memory).
    fn iterate(&mut self, stored: (usize, usize), seed: u64, group: &mut dyn Reducer) -> Result<SacStats, Refused> {
        let (new, refused_episodes) = stored;
        let (steps, carry) = steps_and_carry(new, self.ratio, self.carry);
        let batch_size = if self.replay.len() > self.sac.settings.batch_size {
            self.sac.settings.batch_size
        } else {
            // DeepRacer's trainer before the memory holds a batch: the largest power of two
            // not above the new steps.
            1usize << (usize::BITS - 1 - new.max(1).leading_zeros())
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        self.sac.reseed(seed);
        let before = self.sac.clone();
        let version = self.version;
        let device = |error: GpuError| Refused::Device { error: error.to_string(), version };
        // Alone, with a GPU: the iteration's steps there (a team's members share faer's).
        if self.gpu.is_some() && group.shard().1 > 1 {
            crate::device::note_team_on_cpu();
        }
        let mut session = match (&self.gpu, group.shard().1) {
            (Some(g), 1) if steps > 0 => Some(g.begin(&self.sac, batch_size).map_err(device)?),
            _ => None,
        };
        let mut sum = Losses::default();
        for i in 0..steps {
            let Some(batch) = self.replay.sample(batch_size, &mut rng) else { break };
            let stepped = match session.as_mut() {
                Some(s) => s.step(&mut self.sac, &batch).map_err(device),
                None => (self.sac.step_in(&batch, group, i as u64, self.par, &mut self.tapes).map(|l| (l, true)))
                    .map_err(|error| Refused::Group { error, version }),
            };
            let (l, finite_grads) = match stepped {
                Ok(l) => l,
                Err(why) => {
                    self.sac = before;
                    return Err(why);
                }
            };
            if ![l.policy, l.q, l.v].iter().all(|x| x.is_finite()) || !finite_grads {
                let loss = [l.policy, l.q, l.v].into_iter().find(|x| !x.is_finite()).unwrap_or(f64::NAN);
                self.sac = before;
                return Err(Refused::NonFinite { step: i, loss, version });
            }
            if i == 0 {
                match &session {
                    Some(s) => s.update_target(self.sac.settings.tau),
                    None => self.sac.update_target(),
                }
            }
            for (s, x) in [
                (&mut sum.policy, l.policy),
                (&mut sum.q, l.q),
                (&mut sum.v, l.v),
                (&mut sum.entropy, l.entropy),
                (&mut sum.q_mean, l.q_mean),
            ] {
                *s += x;
            }
        }
        if let Some(Err(error)) = session.map(|s| s.finish(&mut self.sac)) {
            self.sac = before;
            return Err(device(error));
        }
        self.carry = carry;
        self.pending = None;
        let n = steps.max(1) as f64;
        self.version += 1;
        self.sync_model();
        Ok(SacStats {
            samples: steps * batch_size,
            policy_loss: sum.policy / n,
            value_loss: sum.v / n,
            entropy: sum.entropy / n,
            gradient_steps: steps,
            policy_version: self.version,
            figures: SacFigures {
                q_loss: sum.q / n,
                q_mean: sum.q_mean / n,
                alpha: self.sac.alpha() as f64,
                replay: self.replay.len(),
                new_transitions: new,
                refused_episodes,
            },
        })
    }

    /// The published model takes the policy's and V's weights.
    fn sync_model(&mut self) {
        self.model.pi.params.clone_from(&self.sac.nets.policy.params);
        self.model.v.params.clone_from(&self.sac.nets.v.params);
    }
}

/// A SAC learner's part in a learner team: the plan's update, and what a joiner takes over.
impl SacTrainer {
    /// The seed of the next iteration (a team's leader draws it and sends it in the plan).
    pub fn draw_seed(&mut self) -> u64 {
        self.seeds.next_u64()
    }

    /// The iteration every member makes from a plan: `trajs` stored, then the gradient steps
    /// drawn from `seed`, each shared with `group`. A refused iteration leaves the networks as
    /// they were (the episodes stay in the memory).
    pub fn update_planned(
        &mut self,
        trajs: &[Trajectory],
        seed: u64,
        group: &mut dyn Reducer,
    ) -> Result<SacStats, Refused> {
        let stored = self.store(trajs);
        self.pending = Some(stored);
        self.iterate(stored, seed, group)
    }

    /// The iteration made by a learner alone.
    pub fn update_alone(&mut self, trajs: &[Trajectory]) -> Result<SacStats, Refused> {
        let seed = self.draw_seed();
        self.update_planned(trajs, seed, &mut Alone)
    }

    /// The leader makes alone the iteration its team's attempt failed at. The episodes of the
    /// failed attempt are in the memory already: only its steps are made.
    pub fn update_again(&mut self, trajs: &[Trajectory]) -> Result<SacStats, Refused> {
        let stored = match self.pending {
            Some(stored) => stored,
            None => self.store(trajs),
        };
        let seed = self.draw_seed();
        self.iterate(stored, seed, &mut Alone)
    }

    /// What a joiner takes over: the networks, their optimisers, the carried fraction of a step.
    pub fn state(&self) -> LearnerState {
        let mut tensors = self.sac.tensors();
        tensors.push(("carry".into(), vec![self.carry]));
        LearnerState { version: self.version, tensors }
    }

    /// The replay memory, as bytes, that a joiner takes over with [`SacTrainer::state`]
    /// (always some: a SAC learner has one).
    pub fn memory(&self) -> Option<Vec<u8>> {
        Some(self.replay.to_bytes())
    }

    /// Take over a member's state and replay memory. Refused, with nothing changed, unless
    /// both fit.
    pub fn restore(&mut self, state: LearnerState, memory: Option<&[u8]>) -> Result<(), StateMismatch> {
        let Some(bytes) = memory else {
            return Err(StateMismatch(
                "a SAC learner's state comes with its replay memory, and this one has none".into(),
            ));
        };
        let mut tensors = state.tensors;
        let carry = match tensors.iter().position(|(n, _)| n == "carry") {
            Some(i) => tensors.remove(i).1,
            None => return Err(StateMismatch("the state has no tensor `carry`".into())),
        };
        if carry.len() != 1 || !(0.0..1.0).contains(&carry[0]) {
            return Err(StateMismatch(format!("tensor `carry` is {carry:?}, expected one number in [0, 1)")));
        }
        let capacity = Replay::capacity_of(bytes).map_err(|e| StateMismatch(e.0))?.unwrap_or(self.replay.capacity());
        let replay =
            Replay::from_bytes(bytes, capacity).map_err(|e| StateMismatch(format!("the replay memory: {e}")))?;
        if replay.per() != self.replay.per() {
            return Err(StateMismatch(format!(
                "the replay memory holds transitions of {} values, this learner's observation has {}",
                replay.per(),
                self.replay.per()
            )));
        }
        let mut sac = self.sac.clone();
        sac.set_tensors(tensors)?;
        self.sac = sac;
        self.replay = replay;
        self.carry = carry[0];
        self.version = state.version;
        self.pending = None;
        // Another learner's memory: the next checkpoint writes it whole.
        (self.on_disk, self.in_parts) = (0, usize::MAX);
        self.sync_model();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    /// Issue 32: the fraction of a gradient step carried to the next iteration stays in [0, 1).
    fn the_carried_fraction_of_a_step_stays_below_one() {
        for (new, ratio, carry, want) in [
            (10, 1.0, 0.0, (10, 0.0)),
            (3, 0.5, 0.0, (1, 0.5)),
            (3, 0.5, 0.5, (2, 0.0)),
            (1, 0.999_999_999_9, 0.0, (1, 0.0)),
            (0, 0.05, 0.25, (0, 0.25)),
        ] {
            let got = steps_and_carry(new, ratio, carry);
            assert_eq!(got, want, "{new} × {ratio} + {carry}");
            assert!((0.0..1.0).contains(&got.1));
        }
    }
}
