//! The learner's and the workers' vocabulary ([`policy::exchange`]) on the wire, and back.
//!
//! Decoding a message's bytes is not enough: every message coming back is checked against
//! the job it claims to be for (its id, its model's observation size, its worlds, the sender
//! the key names), and anything that does not fit is an error the caller counts and drops.

use crate::{DecodeError, keys, limits, trajectory_from_wire, trajectory_to_wire};
use policy::exchange as ex;
use policy::folder::{self, Manifest};
use std::sync::Arc;

/// The most episodes one grant may hold per agent, trials one request may ask for, and
/// trajectories one batch may carry: far above any real job, low enough to refuse nonsense.
pub const SANITY_LIMIT: u64 = 100_000;

/// What a received message is checked against.
#[derive(Clone, Copy, Debug)]
pub struct JobView<'a> {
    /// The job's id.
    pub job_id: &'a str,
    /// Its model's observation size.
    pub obs_size: usize,
    /// Its worlds.
    pub worlds: &'a [String],
    /// Its model's action space.
    pub actions: crate::Actions,
}

fn invalid<T>(m: String) -> Result<T, DecodeError> {
    Err(DecodeError::Invalid(m))
}

fn same_job(got: &str, want: &str) -> Result<(), DecodeError> {
    if got != want {
        return invalid(format!("message for job {got:?} on job {want:?}'s key"));
    }
    Ok(())
}

/// A grant on the wire.
pub fn credit_to_wire(job: &str, c: &ex::Credit) -> crate::Credit {
    crate::Credit {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version: c.version,
        round: c.round,
        grants: c.episodes.iter().map(|(a, n)| crate::Grant { agent_id: a.clone(), episodes: *n }).collect(),
        checks_closed_through: c.checks_closed_through,
    }
}

/// A grant back, for `job`.
pub fn credit_from_wire(w: crate::Credit, job: &str) -> Result<ex::Credit, DecodeError> {
    same_job(&w.job_id, job)?;
    let mut episodes = std::collections::BTreeMap::new();
    for g in w.grants {
        if !keys::is_valid_name(&g.agent_id) || g.episodes > SANITY_LIMIT {
            return invalid(format!("grant of {} episodes to {:?}", g.episodes, g.agent_id));
        }
        episodes.insert(g.agent_id, g.episodes);
    }
    Ok(ex::Credit {
        version: w.policy_version,
        round: w.round,
        episodes,
        checks_closed_through: w.checks_closed_through,
    })
}

/// An evaluation request on the wire.
pub fn eval_request_to_wire(job: &str, r: &ex::EvalRequest) -> crate::EvalRequest {
    crate::EvalRequest {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        id: r.id,
        agent_id: r.worker.clone(),
        policy_version: r.version,
        world: r.world.clone(),
        trials: r.trials,
        seed: r.seed,
        verify_id: r.then_verify.map_or(0, |v| v.id),
        verify_trials: r.then_verify.map_or(0, |v| v.trials),
        verify_seed: r.then_verify.map_or(0, |v| v.seed),
        verify_laps: r.then_verify.map_or(0, |v| v.laps),
    }
}

/// An evaluation request back: for `job`, for `agent` (the key's), on one of the job's worlds.
pub fn eval_request_from_wire(
    w: crate::EvalRequest,
    job: &JobView<'_>,
    agent: &str,
) -> Result<ex::EvalRequest, DecodeError> {
    same_job(&w.job_id, job.job_id)?;
    if w.agent_id != agent {
        return invalid(format!("request for {:?} on {agent:?}'s key", w.agent_id));
    }
    if !job.worlds.contains(&w.world) {
        return invalid(format!("evaluation on {:?}, not one of the job's worlds", w.world));
    }
    if w.trials == 0 || w.trials as u64 > SANITY_LIMIT {
        return invalid(format!("{} evaluation trials", w.trials));
    }
    if w.verify_trials as u64 > SANITY_LIMIT || w.verify_laps > w.trials {
        return invalid(format!("a chained verification of {} trials needing {} laps", w.verify_trials, w.verify_laps));
    }
    if w.verify_trials > 0 && w.verify_id == w.id {
        return invalid(format!("a chained verification with its evaluation's id {}", w.id));
    }
    let then_verify = (w.verify_trials > 0).then_some(ex::ChainedVerify {
        id: w.verify_id,
        trials: w.verify_trials,
        seed: w.verify_seed,
        laps: w.verify_laps,
    });
    Ok(ex::EvalRequest {
        id: w.id,
        worker: w.agent_id,
        version: w.policy_version,
        world: w.world,
        trials: w.trials,
        seed: w.seed,
        then_verify,
    })
}

/// An evaluation report on the wire.
pub fn eval_report_to_wire(job: &str, r: &ex::EvalReport) -> crate::EvalReport {
    let (trials, error) = match &r.trials {
        Ok(t) => (
            t.iter()
                .map(|t| {
                    let (discrete_actions, continuous_actions) = crate::choices_to_wire(&t.choices);
                    crate::EvalTrial {
                        progress: t.progress,
                        lap_time: t.lap_time,
                        off_track: t.off_track,
                        crashes: t.crashes,
                        overtakes: t.overtakes,
                        reward: t.reward,
                        steps: t.steps,
                        status: t.status.clone(),
                        discrete_actions,
                        continuous_actions,
                        rewards: t.rewards.clone(),
                        trace: crate::trace_to_wire(&t.trace),
                        track_len: t.track_len,
                        frames: t.frames.iter().map(|f| frame_to_wire(job, &r.worker, f)).collect(),
                    }
                })
                .collect(),
            String::new(),
        ),
        Err(e) => (Vec::new(), e.clone()),
    };
    crate::EvalReport {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        id: r.id,
        agent_id: r.worker.clone(),
        policy_version: r.version,
        world: r.world.clone(),
        trials,
        error,
    }
}

/// An evaluation report back: for `job`, from `agent` (the key's).
pub fn eval_report_from_wire(
    w: crate::EvalReport,
    job: &JobView<'_>,
    agent: &str,
) -> Result<ex::EvalReport, DecodeError> {
    same_job(&w.job_id, job.job_id)?;
    if w.agent_id != agent {
        return invalid(format!("report from {:?} on {agent:?}'s key", w.agent_id));
    }
    if !job.worlds.contains(&w.world) {
        return invalid(format!("report for {:?}, not one of the job's worlds", w.world));
    }
    let ok = |t: &crate::EvalTrial| {
        t.progress.is_finite()
            && crate::limits::PROGRESS.contains(&t.progress)
            && t.lap_time.is_none_or(|l| l.is_finite() && l >= 0.0)
            && t.reward.is_finite()
            && t.overtakes.is_none_or(|o| u64::from(o) <= t.steps)
    };
    if w.trials.len() as u64 > SANITY_LIMIT || !w.trials.iter().all(ok) {
        return invalid(
            "evaluation trials out of range (progress -100–100 %, finite lap times and rewards, overtakes at most \
             one a step)"
                .into(),
        );
    }
    let trials = if w.error.is_empty() {
        let mut trials = Vec::with_capacity(w.trials.len());
        for t in w.trials {
            let n = t.rewards.len();
            if n as u64 > SANITY_LIMIT * 10 || !t.rewards.iter().all(|r| r.is_finite() && r.abs() <= limits::REWARD) {
                return invalid("evaluation trial rewards out of range".into());
            }
            if !(t.track_len.is_finite() && (0.0..=1e5).contains(&t.track_len)) {
                return invalid(format!("track length {} out of range", t.track_len));
            }
            let choices = if n == 0 && t.trace.is_none() {
                Vec::new()
            } else {
                crate::choices_from_wire(&t.discrete_actions, &t.continuous_actions, n, job.actions)?
            };
            if t.frames.len() as u64 > SANITY_LIMIT / 10 {
                return invalid(format!("{} frames in one trial", t.frames.len()));
            }
            let frames =
                t.frames.into_iter().map(|f| frame_from_wire(f, job.job_id, agent)).collect::<Result<Vec<_>, _>>()?;
            trials.push(ex::Trial {
                frames,
                progress: t.progress,
                lap_time: t.lap_time,
                off_track: t.off_track,
                crashes: t.crashes,
                overtakes: t.overtakes,
                reward: t.reward,
                steps: t.steps,
                status: t.status,
                choices,
                rewards: t.rewards,
                trace: crate::trace_from_wire(t.trace, n)?,
                track_len: t.track_len,
            });
        }
        Ok(trials)
    } else {
        Err(w.error)
    };
    Ok(ex::EvalReport { id: w.id, worker: w.agent_id, version: w.policy_version, world: w.world, trials })
}

/// Experience on the wire.
pub fn experience_to_wire(job: &str, e: &ex::Experience, obs_size: usize) -> crate::ExperienceBatch {
    crate::ExperienceBatch {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        agent_id: e.worker.clone(),
        seq: e.seq,
        trajectories: e.trajectories.iter().map(|t| trajectory_to_wire(t, obs_size)).collect(),
        env_steps: e.env_steps,
        seconds: e.seconds,
        credit_version: e.credit.0,
        credit_round: e.credit.1,
    }
}

/// Experience back: for `job`, from `agent` (the key's). Trajectories that do not fit the job
/// (observation size, world, lengths, non-finite numbers) are left out and returned as errors
/// for the caller to count; the rest are kept.
pub fn experience_from_wire(
    b: crate::ExperienceBatch,
    job: &JobView<'_>,
    agent: &str,
) -> Result<(ex::Experience, Vec<DecodeError>), DecodeError> {
    same_job(&b.job_id, job.job_id)?;
    if b.agent_id != agent {
        return invalid(format!("experience from {:?} on {agent:?}'s key", b.agent_id));
    }
    if b.trajectories.len() as u64 > SANITY_LIMIT || b.env_steps > SANITY_LIMIT * 100_000 || !b.seconds.is_finite() {
        return invalid("batch figures out of range".into());
    }
    let mut kept = Vec::with_capacity(b.trajectories.len());
    let mut refused = Vec::new();
    for w in b.trajectories {
        match trajectory_from_wire(w, job.obs_size, job.actions) {
            Ok(t) if !job.worlds.contains(&t.world) => {
                refused.push(DecodeError::Invalid(format!("episode on {:?}, not one of the job's worlds", t.world)))
            }
            Ok(t) => kept.push(t),
            Err(e) => refused.push(e),
        }
    }
    Ok((
        ex::Experience {
            worker: b.agent_id,
            seq: b.seq,
            credit: (b.credit_version, b.credit_round),
            trajectories: kept,
            env_steps: b.env_steps,
            seconds: b.seconds,
            frame: None,
        },
        refused,
    ))
}

/// A camera frame on the wire, for watchers.
pub fn frame_to_wire(job: &str, agent: &str, f: &ex::Frame) -> crate::CameraFrame {
    crate::CameraFrame {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        agent_id: agent.into(),
        world: f.world.clone(),
        width: f.width,
        height: f.height,
        gray: f.gray.clone(),
        policy_version: f.policy_version,
        step: f.step,
    }
}

/// A camera frame back: for `job`, from `agent` (the key's), its size what it says (at most
/// 4096 × 4096).
pub fn frame_from_wire(w: crate::CameraFrame, job: &str, agent: &str) -> Result<ex::Frame, DecodeError> {
    same_job(&w.job_id, job)?;
    if w.agent_id != agent {
        return invalid(format!("frame from {:?} on {agent:?}'s key", w.agent_id));
    }
    if w.width == 0
        || w.height == 0
        || w.width > 4096
        || w.height > 4096
        || w.gray.len() as u64 != w.width as u64 * w.height as u64
    {
        return invalid(format!("frame of {}×{} with {} pixels", w.width, w.height, w.gray.len()));
    }
    Ok(ex::Frame {
        world: w.world,
        width: w.width,
        height: w.height,
        gray: w.gray,
        policy_version: w.policy_version,
        step: w.step,
    })
}

/// A policy version on the wire (the model folder's three files).
pub fn policy_to_wire(
    job: &str,
    p: &ex::PolicyVersion,
    manifest: &Manifest,
    signer: Option<&policy::signature::Signer>,
) -> crate::PolicyUpdate {
    let parts = policy::ModelParts::new(&p.metadata, &p.model, manifest, signer);
    crate::PolicyUpdate {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version: p.version,
        weights: parts.weights,
        model_metadata_json: parts.metadata_json,
        manifest_json: parts.manifest_json,
        signature_json: parts.signature.map(|s| serde_json::to_string(&s).expect("JSON")).unwrap_or_default(),
    }
}

/// A model folder's files, as they are (signature included), as a publication.
pub fn parts_to_wire(job: &str, policy_version: u64, parts: &policy::ModelParts) -> crate::PolicyUpdate {
    crate::PolicyUpdate {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version,
        weights: parts.weights.clone(),
        model_metadata_json: parts.metadata_json.clone(),
        manifest_json: parts.manifest_json.clone(),
        signature_json: parts.signature.as_ref().map(|s| serde_json::to_string(s).expect("JSON")).unwrap_or_default(),
    }
}

/// A published model's signature, if it carries one.
pub fn policy_signature(u: &crate::PolicyUpdate) -> Result<Option<policy::signature::ModelSignature>, DecodeError> {
    if u.signature_json.is_empty() {
        return Ok(None);
    }
    serde_json::from_str(&u.signature_json)
        .map(Some)
        .map_err(|e| DecodeError::Invalid(format!("signature_json is not a signature: {e}")))
}

/// A published model's files as they came (signature included), for a verifier; only the
/// message's own consistency is checked here (its version against the manifest's is left to
/// the model's decoding).
pub fn policy_parts(u: &crate::PolicyUpdate) -> Result<policy::ModelParts, DecodeError> {
    let signature = policy_signature(u)?;
    Ok(policy::ModelParts {
        metadata_json: u.model_metadata_json.clone(),
        manifest_json: u.manifest_json.clone(),
        weights: u.weights.clone(),
        signature,
    })
}

/// A policy version back: for `job`, its weights matching its metadata and checksum, and
/// taking the job's observation size.
pub fn policy_from_wire(u: crate::PolicyUpdate, job: &JobView<'_>) -> Result<ex::PolicyVersion, DecodeError> {
    same_job(&u.job_id, job.job_id)?;
    let f = folder::from_parts(&u.model_metadata_json, &u.manifest_json, &u.weights, std::path::Path::new("<network>"))
        .map_err(|e| DecodeError::Invalid(e.to_string()))?;
    if f.manifest.obs_size != job.obs_size {
        return invalid(format!(
            "policy takes {} inputs, the job's observation has {}",
            f.manifest.obs_size, job.obs_size
        ));
    }
    if f.manifest.policy_version != u.policy_version {
        return invalid(format!("policy v{} whose manifest says v{}", u.policy_version, f.manifest.policy_version));
    }
    Ok(ex::PolicyVersion { version: u.policy_version, model: Arc::new(f.model), metadata: Arc::new(f.metadata) })
}

/// The most members a learner team may have, and tensors a state may hold.
pub const TEAM_LIMIT: usize = 64;

/// A learner team's plan for one update (see `TeamPlan` in the `.proto`).
#[derive(Clone, Debug, PartialEq)]
pub struct TeamPlan {
    /// The leader (rank 0).
    pub leader: String,
    /// This plan's number.
    pub plan: u64,
    /// The plan whose result a member must hold to take part.
    pub base: u64,
    /// The version the update starts from.
    pub policy_version: u64,
    /// Members in rank order, the leader first.
    pub members: Vec<String>,
    /// The minibatch shuffle seed.
    pub seed: u64,
    /// The update's learning rate (the job's schedule, worked out by the leader).
    pub lr: f64,
    /// What to train on.
    pub trajectories: Vec<policy::Trajectory>,
    /// The state after `base`, for members that do not hold it.
    pub state: Option<TeamState>,
}

/// A learner's weights and optimiser moments, as named tensors.
#[derive(Clone, Debug, PartialEq)]
pub struct TeamState {
    /// Policy version.
    pub policy_version: u64,
    /// Named tensors.
    pub tensors: Vec<(String, Vec<f32>)>,
    /// The size of the replay memory (SAC's) that completes the state, sent in
    /// [`crate::TeamMemory`] parts before the plan; 0: none.
    pub memory_bytes: u64,
}

/// The most bytes of a replay memory one [`crate::TeamMemory`] carries.
pub const MEMORY_PART: usize = 32 << 20;
/// The most parts of one replay memory (a 64 GB memory).
pub const MEMORY_PARTS: u32 = 2048;

/// A replay memory of `bytes` for the plan based on `base`, in parts.
pub fn memory_to_wire(job: &str, leader: &str, base: u64, bytes: &[u8]) -> Vec<crate::TeamMemory> {
    let parts = bytes.len().div_ceil(MEMORY_PART).max(1);
    (0..parts)
        .map(|i| crate::TeamMemory {
            protocol_version: crate::PROTOCOL_VERSION,
            job_id: job.into(),
            leader: leader.into(),
            base,
            part: i as u32,
            parts: parts as u32,
            total: bytes.len() as u64,
            data: bytes[(i * MEMORY_PART).min(bytes.len())..((i + 1) * MEMORY_PART).min(bytes.len())].to_vec(),
        })
        .collect()
}

/// A replay memory's parts as they arrive, put together per (leader, base). A part that does
/// not fit the others of its memory, or the size a learner accepts, is refused; only the
/// newest memory is kept.
#[derive(Debug)]
pub struct MemoryParts {
    limit: u64,
    key: Option<(String, u64)>,
    total: u64,
    parts: Vec<Option<Vec<u8>>>,
}

impl MemoryParts {
    /// Parts of memories of at most `limit` bytes.
    pub fn new(limit: u64) -> MemoryParts {
        MemoryParts { limit, key: None, total: 0, parts: Vec::new() }
    }

    /// Take a part received on `job`'s key.
    pub fn insert(&mut self, w: crate::TeamMemory, job: &str) -> Result<(), DecodeError> {
        same_job(&w.job_id, job)?;
        if !keys::is_valid_name(&w.leader) {
            return invalid(format!("replay memory part from {:?}: not a learner's name", w.leader));
        }
        if w.parts == 0 || w.parts > MEMORY_PARTS || w.part >= w.parts {
            return invalid(format!("replay memory part {} of {} (at most {MEMORY_PARTS} parts)", w.part, w.parts));
        }
        if w.total > self.limit || w.total > w.parts as u64 * MEMORY_PART as u64 {
            return invalid(format!(
                "a replay memory of {} bytes in {} parts (this learner takes at most {} bytes)",
                w.total, w.parts, self.limit
            ));
        }
        let (start, end) =
            (w.part as u64 * MEMORY_PART as u64, ((w.part as u64 + 1) * MEMORY_PART as u64).min(w.total));
        if w.data.len() as u64 != end.saturating_sub(start) {
            return invalid(format!(
                "replay memory part {} of {} holds {} bytes, expected {}",
                w.part,
                w.parts,
                w.data.len(),
                end.saturating_sub(start)
            ));
        }
        let key = (w.leader, w.base);
        if self.key.as_ref() != Some(&key) {
            if self.key.as_ref().is_some_and(|k| k.0 == key.0 && k.1 > key.1) {
                return Ok(());
            }
            self.key = Some(key);
            self.total = w.total;
            self.parts = vec![None; w.parts as usize];
        } else if self.total != w.total || self.parts.len() != w.parts as usize {
            return invalid(format!(
                "replay memory part {} says {} bytes in {} parts, its other parts {} in {}",
                w.part,
                w.total,
                w.parts,
                self.total,
                self.parts.len()
            ));
        }
        self.parts[w.part as usize] = Some(w.data);
        Ok(())
    }

    /// The whole memory of `leader`'s plan based on `base` of `total` bytes, once every part
    /// came (the parts are then let go).
    pub fn take(&mut self, leader: &str, base: u64, total: u64) -> Option<Vec<u8>> {
        let ours = self.key.as_ref().is_some_and(|(l, b)| l == leader && *b == base) && self.total == total;
        if !ours || self.parts.iter().any(|p| p.is_none()) {
            return None;
        }
        self.key = None;
        let mut out = Vec::with_capacity(total as usize);
        for p in self.parts.drain(..) {
            out.extend_from_slice(&p.expect("every part came"));
        }
        Some(out)
    }
}

/// Little-endian bytes of `values`.
pub fn f32_bytes(values: &[f32]) -> Vec<u8> {
    if cfg!(target_endian = "little") {
        // One copy: gradients of the camera network are 47 MB per minibatch.
        return bytemuck::cast_slice::<f32, u8>(values).to_vec();
    }
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// `values` back from little-endian bytes.
pub fn f32_values(bytes: &[u8]) -> Result<Vec<f32>, DecodeError> {
    if !bytes.len().is_multiple_of(4) {
        return invalid(format!("{} bytes of f32 values: not a multiple of 4", bytes.len()));
    }
    if cfg!(target_endian = "little") {
        return Ok(bytemuck::pod_collect_to_vec::<u8, f32>(bytes));
    }
    Ok(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// `values` without their `+0.0`s: a bit per value (least significant bit first, set where the
/// value is kept) and the kept values' little-endian bytes. Every other value, `-0.0` and NaNs
/// included, keeps its bits. A ReLU layer's inputs and output gradients are zero in about half
/// their places: a team's shares are the big dense layers' factors.
pub fn f32_sparse(values: &[f32]) -> (Vec<u8>, Vec<u8>) {
    let mut mask = vec![0u8; values.len().div_ceil(8)];
    // Every value is written and the end moves on past the kept ones only: no branch per
    // value (about two thirds of a share's factors are zero, in no pattern).
    let mut kept = vec![0u8; values.len() * 4 + 4];
    let mut end = 0;
    for (chunk, m) in values.chunks(8).zip(mask.iter_mut()) {
        for (j, v) in chunk.iter().enumerate() {
            let keep = v.to_bits() != 0;
            kept[end..end + 4].copy_from_slice(&v.to_le_bytes());
            end += 4 * keep as usize;
            *m |= (keep as u8) << j;
        }
    }
    kept.truncate(end);
    (mask, kept)
}

/// [`f32_sparse`]'s `len` values back from the mask and the kept values' bytes.
pub fn f32_from_sparse(len: u64, mask: &[u8], kept: &[u8]) -> Result<Vec<f32>, DecodeError> {
    // The mask holds a bit per value, so `len` is bounded by the message's own size.
    let n = usize::try_from(len).ok().filter(|n| n.div_ceil(8) == mask.len());
    let Some(n) = n else {
        return invalid(format!("a sparse f32 mask of {} bytes for {len} values", mask.len()));
    };
    if !n.is_multiple_of(8) && mask.last().is_some_and(|b| b >> (n % 8) != 0) {
        return invalid(format!("a sparse f32 mask with bits past its {len} values"));
    }
    let ones: usize = mask.iter().map(|b| b.count_ones() as usize).sum();
    if kept.len() != ones * 4 {
        return invalid(format!("{} bytes of kept f32 values where the mask keeps {ones}", kept.len()));
    }
    // Eight values a mask byte: its kept values into a small array (with a zero at the end),
    // then each place reads its value, or the zero, through a table: no branch per value.
    // (Eight are copied whatever the byte keeps: a fixed-size copy; the table never reads
    // past the byte's own. The eight zeros at the end keep the last copy in bounds.)
    let mut kept = f32_values(kept)?;
    kept.extend_from_slice(&[0.0; 8]);
    let mut out = vec![0.0f32; n];
    let mut at = 0;
    for (o8, &m) in out.chunks_mut(8).zip(mask) {
        let mut local = [0.0f32; 9];
        local[..8].copy_from_slice(&kept[at..at + 8]);
        at += m.count_ones() as usize;
        for (o, &k) in o8.iter_mut().zip(&EXPAND[m as usize]) {
            *o = local[k as usize];
        }
    }
    Ok(out)
}

/// For each mask byte, where each of its eight places finds its value among the byte's kept
/// ones (8: the zero).
static EXPAND: [[u8; 8]; 256] = {
    let mut t = [[8u8; 8]; 256];
    let mut m = 0;
    while m < 256 {
        let (mut j, mut k) = (0, 0);
        while j < 8 {
            if m >> j & 1 == 1 {
                t[m][j] = k;
                k += 1;
            }
            j += 1;
        }
        m += 1;
    }
    t
};

/// A plan on the wire.
pub fn team_plan_to_wire(job: &str, p: &TeamPlan, obs_size: usize) -> crate::TeamPlan {
    crate::TeamPlan {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        leader: p.leader.clone(),
        plan: p.plan,
        base: p.base,
        policy_version: p.policy_version,
        members: p.members.clone(),
        seed: p.seed,
        lr: p.lr,
        trajectories: p.trajectories.iter().map(|t| trajectory_to_wire(t, obs_size)).collect(),
        state: p.state.as_ref().map(|s| crate::TeamState {
            policy_version: s.policy_version,
            tensors: s.tensors.iter().map(|(n, v)| crate::Tensor { name: n.clone(), data: f32_bytes(v) }).collect(),
            memory_bytes: s.memory_bytes,
        }),
    }
}

/// A plan back, for `job`. Every member must train on the same data, so one trajectory that
/// does not fit the job refuses the whole plan.
pub fn team_plan_from_wire(w: crate::TeamPlan, job: &JobView<'_>) -> Result<TeamPlan, DecodeError> {
    same_job(&w.job_id, job.job_id)?;
    if w.members.is_empty() || w.members.len() > TEAM_LIMIT || w.members[0] != w.leader {
        return invalid(format!(
            "team of {} members led by {:?}: the leader must come first",
            w.members.len(),
            w.leader
        ));
    }
    let mut seen = std::collections::BTreeSet::new();
    for m in &w.members {
        if !keys::is_valid_name(m) || !seen.insert(m.as_str()) {
            return invalid(format!("team member {m:?} is not a name or comes twice"));
        }
    }
    if !(w.lr.is_finite() && w.lr >= 0.0) {
        return invalid(format!("a learning rate of {}: expected a finite number, 0 or more", w.lr));
    }
    if w.trajectories.len() as u64 > SANITY_LIMIT || w.plan <= w.base {
        return invalid(format!("plan {} on base {} with {} episodes", w.plan, w.base, w.trajectories.len()));
    }
    let mut trajectories = Vec::with_capacity(w.trajectories.len());
    for t in w.trajectories {
        let t = trajectory_from_wire(t, job.obs_size, job.actions)?;
        if !job.worlds.contains(&t.world) {
            return invalid(format!("episode on {:?}, not one of the job's worlds", t.world));
        }
        trajectories.push(t);
    }
    let state = match w.state {
        None => None,
        Some(s) => {
            if s.tensors.len() > TEAM_LIMIT {
                return invalid(format!("a state of {} tensors", s.tensors.len()));
            }
            let tensors = s
                .tensors
                .into_iter()
                .map(|t| Ok((t.name, f32_values(&t.data)?)))
                .collect::<Result<Vec<_>, DecodeError>>()?;
            Some(TeamState { policy_version: s.policy_version, tensors, memory_bytes: s.memory_bytes })
        }
    };
    Ok(TeamPlan {
        leader: w.leader,
        plan: w.plan,
        base: w.base,
        policy_version: w.policy_version,
        members: w.members,
        seed: w.seed,
        lr: w.lr,
        trajectories,
        state,
    })
}

/// A gradient share on the wire.
pub fn share_to_wire(
    job: &str,
    learner: &str,
    plan: u64,
    step: u64,
    values: &[f32],
    factors: &[f32],
) -> crate::GradShare {
    // Sparse when that saves a tenth or more (the mask costs 1/32 of the dense size).
    let (mask, kept) = f32_sparse(factors);
    let (factors, factors_mask, factors_len) = if kept.len() + mask.len() <= factors.len() * 4 * 9 / 10 {
        (kept, mask, factors.len() as u64)
    } else {
        (f32_bytes(factors), Vec::new(), 0)
    };
    crate::GradShare {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        learner: learner.into(),
        plan,
        step,
        values: f32_bytes(values),
        factors,
        factors_mask,
        factors_len,
    }
}

/// A gradient share, decoded: plan, step, summed values, factors.
pub type Share = (u64, u64, Vec<f32>, Vec<f32>);

/// A gradient share back: for `job`, from `learner` (the key's). The sizes depend on the
/// exchange (a step's two differ) and on the member's share of the minibatch: the learner
/// checks them against its own share of the same exchange.
pub fn share_from_wire(w: crate::GradShare, job: &str, learner: &str) -> Result<Share, DecodeError> {
    same_job(&w.job_id, job)?;
    if w.learner != learner {
        return invalid(format!("gradient share from {:?} on {learner:?}'s key", w.learner));
    }
    let factors = if w.factors_mask.is_empty() && w.factors_len == 0 {
        f32_values(&w.factors)?
    } else {
        f32_from_sparse(w.factors_len, &w.factors_mask, &w.factors)?
    };
    Ok((w.plan, w.step, f32_values(&w.values)?, factors))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job() -> (String, Vec<String>) {
        ("job1".into(), vec!["reinvent_wood".into(), "reinvent_carpet".into()])
    }

    /// Issue 32: a replay memory travels to a joiner in parts and a part that does not fit is
    /// refused.
    #[test]
    fn a_replay_memory_travels_to_a_joiner_in_parts_and_a_part_that_does_not_fit_is_refused() {
        let memory: Vec<u8> = (0..2 * MEMORY_PART + 5).map(|i| (i * 7 % 251) as u8).collect();
        let parts = memory_to_wire("job1", "l0", 8, &memory);
        assert_eq!(parts.len(), 3);
        assert!(parts.iter().all(|p| p.data.len() <= MEMORY_PART && p.total == memory.len() as u64));
        // Through the encoding, out of order: whole once the last part came, and only then.
        let mut got = MemoryParts::new(1 << 40);
        for i in [2, 0] {
            let w: crate::TeamMemory = crate::decode(&crate::encode(&parts[i])).unwrap();
            got.insert(w, "job1").unwrap();
            assert_eq!(got.take("l0", 8, memory.len() as u64), None, "part 1 is missing");
        }
        got.insert(parts[1].clone(), "job1").unwrap();
        assert_eq!(got.take("l0", 9, memory.len() as u64), None, "another plan's memory");
        assert!(got.take("l0", 8, memory.len() as u64) == Some(memory.clone()), "the memory, byte for byte");
        // An empty memory is one empty part.
        let empty = memory_to_wire("job1", "l0", 3, &[]);
        assert_eq!(empty.len(), 1);
        got.insert(empty[0].clone(), "job1").unwrap();
        assert_eq!(got.take("l0", 3, 0), Some(Vec::new()));
        // Refused, naming what is wrong: another job's, a torn part, a part past the count,
        // a memory larger than the learner takes, a part that disagrees with the others.
        let p = parts[0].clone();
        let refused = |w: crate::TeamMemory, got: &mut MemoryParts| got.insert(w, "job1").unwrap_err().to_string();
        let mut got = MemoryParts::new(1 << 40);
        assert!(refused(crate::TeamMemory { job_id: "job2".into(), ..p.clone() }, &mut got).contains("job2"));
        let mut torn = p.clone();
        torn.data.pop();
        assert!(refused(torn, &mut got).contains("holds 33554431 bytes, expected 33554432"));
        assert!(refused(crate::TeamMemory { part: 3, ..p.clone() }, &mut got).contains("part 3 of 3"));
        assert!(refused(p.clone(), &mut MemoryParts::new(1000)).contains("at most 1000 bytes"));
        got.insert(p.clone(), "job1").unwrap();
        let other = crate::TeamMemory { total: p.total - 1, part: 2, data: vec![0; 4], ..p.clone() };
        assert!(refused(other, &mut got).contains("its other parts"));
    }

    /// Issue 8: team messages round trip and refuse what does not fit.
    #[test]
    fn team_messages_round_trip_and_refuse_what_does_not_fit() {
        let (id, worlds) = job();
        let view = JobView { job_id: &id, obs_size: 3, worlds: &worlds, actions: crate::Actions::Discrete(5) };
        let t = policy::Trajectory {
            world: "reinvent_wood".into(),
            obs: vec![0.5; 6],
            choices: vec![policy::Choice::Discrete(1); 2],
            logp: vec![-1.0; 2],
            values: vec![0.25; 2],
            rewards: vec![1.0; 2],
            done: true,
            ..Default::default()
        };
        let plan = TeamPlan {
            leader: "l0".into(),
            plan: 9,
            base: 8,
            policy_version: 3,
            members: vec!["l0".into(), "l1".into()],
            seed: 42,
            lr: 1.5e-4,
            trajectories: vec![t.clone()],
            state: Some(TeamState {
                policy_version: 3,
                tensors: vec![("pi".into(), vec![1.5, -2.0, f32::MIN_POSITIVE])],
                memory_bytes: 5,
            }),
        };
        let wire = team_plan_to_wire(&id, &plan, 3);
        let bytes = crate::encode(&wire);
        assert_eq!(team_plan_from_wire(crate::decode(&bytes).unwrap(), &view).unwrap(), plan);
        // The leader not first, a member twice, another job, an episode off the job's worlds:
        // refused whole (members must train on the same data).
        let mut w = wire.clone();
        w.members.reverse();
        assert!(team_plan_from_wire(w, &view).is_err());
        let mut w = wire.clone();
        w.members.push("l1".into());
        assert!(team_plan_from_wire(w, &view).is_err());
        assert!(team_plan_from_wire(wire.clone(), &JobView { job_id: "job2", ..view }).is_err());
        let mut w = wire.clone();
        w.trajectories[0].world = "Vegas_track".into();
        assert!(team_plan_from_wire(w, &view).is_err());
        let mut w = wire.clone();
        w.state.as_mut().unwrap().tensors[0].data.pop();
        assert!(team_plan_from_wire(w, &view).is_err());
        // A learning rate every member could not apply alike (the job's lr schedule travels
        // in the plan): refused, naming it.
        for lr in [f64::NAN, f64::INFINITY, -1e-4] {
            let e = team_plan_from_wire(crate::TeamPlan { lr, ..wire.clone() }, &view).unwrap_err().to_string();
            assert!(e.contains("learning rate"), "{lr}: {e}");
        }

        let share = share_to_wire(&id, "l1", 9, 4, &[1.0, 2.0], &[3.0]);
        assert_eq!(share_from_wire(share.clone(), &id, "l1").unwrap(), (9, 4, vec![1.0, 2.0], vec![3.0]));
        assert!(share_from_wire(share.clone(), &id, "l0").is_err(), "another sender than the key names");
        assert!(share_from_wire(share.clone(), "job2", "l1").is_err(), "another job's");
        let mut torn = share;
        torn.values.pop();
        assert!(share_from_wire(torn, &id, "l1").is_err(), "values that are not whole f32s");
        // Factors that are mostly +0.0 travel sparse, and come back bit for bit (-0.0, NaN,
        // the smallest subnormal and the largest finite value included).
        let mut factors = vec![0.0f32; 1003];
        for (i, v) in [(0, -0.0), (7, f32::NAN), (8, f32::from_bits(1)), (500, f32::MAX), (1002, -1.5)] {
            factors[i] = v;
        }
        let sparse = share_to_wire(&id, "l1", 9, 5, &[1.0], &factors);
        assert!(!sparse.factors_mask.is_empty() && sparse.factors.len() == 5 * 4, "{:?}", sparse.factors.len());
        let (_, _, _, back) = share_from_wire(sparse.clone(), &id, "l1").unwrap();
        assert_eq!(
            back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            factors.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        // Dense factors stay dense.
        let dense = share_to_wire(&id, "l1", 9, 5, &[1.0], &[2.0; 100]);
        assert!(dense.factors_mask.is_empty() && dense.factors.len() == 400);
        // A mask that does not fit its count or its values is refused.
        for (what, bad) in [
            ("a count the mask does not cover", crate::GradShare { factors_len: 1100, ..sparse.clone() }),
            ("a count of u64::MAX", crate::GradShare { factors_len: u64::MAX, ..sparse.clone() }),
            ("bits past the count", crate::GradShare { factors_len: 1001, ..sparse.clone() }),
            ("a value missing", crate::GradShare { factors: sparse.factors[4..].to_vec(), ..sparse.clone() }),
            (
                "a value too many",
                crate::GradShare { factors: [&sparse.factors[..], &[0; 4]].concat(), ..sparse.clone() },
            ),
            ("a count without a mask", crate::GradShare { factors_mask: Vec::new(), ..sparse.clone() }),
        ] {
            assert!(share_from_wire(bad, &id, "l1").is_err(), "{what}");
        }
    }

    #[test]
    fn messages_that_do_not_fit_the_job_are_refused() {
        let (id, worlds) = job();
        let view = JobView { job_id: &id, obs_size: 3, worlds: &worlds, actions: crate::Actions::Discrete(5) };
        let t = policy::Trajectory {
            world: "reinvent_wood".into(),
            obs: vec![0.0; 6],
            choices: vec![policy::Choice::Discrete(0); 2],
            logp: vec![-1.0; 2],
            values: vec![0.0; 2],
            rewards: vec![1.0; 2],
            done: true,
            ..Default::default()
        };
        let mut off_world = t.clone();
        off_world.world = "Vegas_track".into();
        let e = ex::Experience {
            worker: "a1".into(),
            seq: 1,
            credit: (3, 1),
            trajectories: vec![t.clone(), off_world],
            env_steps: 4,
            seconds: 0.5,
            frame: None,
        };
        let wire = experience_to_wire(&id, &e, 3);
        let (back, refused) = experience_from_wire(wire.clone(), &view, "a1").unwrap();
        assert_eq!(back.trajectories, vec![t]);
        assert_eq!(refused.len(), 1, "the episode on a world the job does not train is dropped");
        assert_eq!(back.credit, (3, 1));
        // Another job's id, another sender than the key names: refused whole.
        assert!(experience_from_wire(wire.clone(), &JobView { job_id: "job2", ..view }, "a1").is_err());
        assert!(experience_from_wire(wire, &view, "a2").is_err());

        let c =
            ex::Credit { version: 4, round: 2, episodes: [("a1".to_string(), 10u64)].into(), checks_closed_through: 3 };
        assert_eq!(credit_from_wire(credit_to_wire(&id, &c), &id).unwrap(), c);
        let mut huge = credit_to_wire(&id, &c);
        huge.grants[0].episodes = u64::MAX;
        assert!(credit_from_wire(huge, &id).is_err());

        let r = ex::EvalRequest {
            id: 7,
            worker: "a1".into(),
            version: 4,
            world: "reinvent_carpet".into(),
            trials: 3,
            seed: 9,
            then_verify: None,
        };
        assert_eq!(eval_request_from_wire(eval_request_to_wire(&id, &r), &view, "a1").unwrap(), r);
        let elsewhere = ex::EvalRequest { world: "Vegas_track".into(), ..r.clone() };
        assert!(eval_request_from_wire(eval_request_to_wire(&id, &elsewhere), &view, "a1").is_err());
        // A chained verification travels whole; one needing more laps than the evaluation has
        // trials, past the sanity limit, or answering under the evaluation's own id is refused.
        let chain = ex::ChainedVerify { id: 8, trials: 10, seed: 11, laps: 3 };
        let chained = ex::EvalRequest { then_verify: Some(chain), ..r.clone() };
        assert_eq!(eval_request_from_wire(eval_request_to_wire(&id, &chained), &view, "a1").unwrap(), chained);
        for bad in [
            ex::ChainedVerify { laps: 4, ..chain },
            ex::ChainedVerify { trials: u32::MAX, ..chain },
            ex::ChainedVerify { id: 7, ..chain },
        ] {
            let w = eval_request_to_wire(&id, &ex::EvalRequest { then_verify: Some(bad), ..r.clone() });
            assert!(eval_request_from_wire(w, &view, "a1").is_err(), "{bad:?}");
        }

        let rep = ex::EvalReport {
            id: 7,
            worker: "a1".into(),
            version: 4,
            world: "reinvent_carpet".into(),
            trials: Ok(vec![ex::Trial {
                progress: 100.0,
                lap_time: Some(9.5),
                off_track: 0,
                crashes: 2,
                overtakes: Some(1),
                reward: 1.5,
                steps: 2,
                status: "lap_complete".into(),
                choices: vec![policy::Choice::Discrete(1), policy::Choice::Discrete(0)],
                rewards: vec![0.0, 1.5],
                trace: vec![
                    policy::StepTrace { x: 1.0, y: 2.0, tstamp: 0.066, wall_clock: 1.8e9, ..Default::default() },
                    policy::StepTrace {
                        x: 1.1,
                        progress: 100.0,
                        status: policy::EpisodeStatus::LapComplete,
                        closest_waypoint: 7,
                        ..Default::default()
                    },
                ],
                track_len: 17.6,
                frames: vec![ex::Frame {
                    world: "reinvent_carpet".into(),
                    width: 2,
                    height: 2,
                    gray: vec![0, 80, 160, 240],
                    policy_version: 4,
                    step: 1,
                }],
            }]),
        };
        assert_eq!(eval_report_from_wire(eval_report_to_wire(&id, &rep), &view, "a1").unwrap(), rep);
        let mut lie = eval_report_to_wire(&id, &rep);
        lie.trials[0].progress = 1e9;
        assert!(eval_report_from_wire(lie, &view, "a1").is_err(), "progress over 100 % is refused");
        // A car that backed over its start line has a little below 0 %, as in DeepRacer: taken
        // (refused, the learner asked for the same evaluation again and again and the job
        // stalled: issue 34's schedule bench, seed 3).
        let mut backed = eval_report_to_wire(&id, &rep);
        backed.trials[0].progress = -1.5;
        for row in backed.trials[0].trace.iter_mut().flat_map(|t| t.progress.iter_mut()) {
            *row = -1.5;
        }
        assert_eq!(eval_report_from_wire(backed, &view, "a1").unwrap().trials.unwrap()[0].progress, -1.5);
        // The trial's sim-trace rows are checked like experience.
        type Lie = (&'static str, fn(&mut crate::EvalTrial));
        let lies: [Lie; 7] = [
            ("more overtakes than steps", |t| t.overtakes = Some(3)),
            ("a frame whose pixels are not its size", |t| t.frames[0].gray.push(9)),
            ("a column short", |t| {
                t.trace.as_mut().unwrap().x.pop();
            }),
            ("an unknown status", |t| t.trace.as_mut().unwrap().status[1] = 99),
            ("a position at infinity", |t| t.trace.as_mut().unwrap().y[0] = f64::INFINITY),
            ("an action outside the space", |t| t.discrete_actions[0] = 99),
            ("a reward beyond ±1e5", |t| t.rewards[0] = 1e9),
        ];
        for (what, lie) in lies {
            let mut w = eval_report_to_wire(&id, &rep);
            lie(&mut w.trials[0]);
            assert!(eval_report_from_wire(w, &view, "a1").is_err(), "{what} is refused");
        }
    }
}
