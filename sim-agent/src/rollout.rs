//! Acting: a policy drives a vector of environments and the steps become trajectories;
//! and evaluation trials with the policy's most likely actions.

use crate::env::{EpisodeStatus, Mode};
use crate::reward::{RewardError, RewardFn};
use crate::vec_env::VecEnv;
use crate::{EnvSpec, EvalRules, SimConfig};
use faer::Par;
use policy::{ActionSpace, ActorCritic, Trajectory};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

/// Collects complete episodes from a vector of environments. Each episode is driven start
/// to end by the policy version that was current when it began: new weights are taken at
/// episode boundaries, as DeepRacer's workers take them.
pub struct Collector {
    vec: VecEnv,
    space: ActionSpace,
    open: Vec<Trajectory>,
    pinned: Vec<Option<Arc<ActorCritic>>>,
    rng: ChaCha8Rng,
    /// Environment steps taken so far.
    pub env_steps: u64,
    /// Episodes completed so far.
    pub episodes: u64,
    /// Keep each step's sim-trace fields in the trajectories (`SimConfig::record_trace`).
    pub record: bool,
    /// The GPU the policy acts on (`None`: faer on the environments' threads).
    gpu: Option<gpu::Acting>,
    /// Worlds environments move to when their running episode ends.
    moves: Vec<Option<EnvSpec>>,
}

impl Collector {
    /// A collector over `vec`, choosing actions from `space`.
    pub fn new(vec: VecEnv, space: ActionSpace, seed: u64) -> Collector {
        let open = (0..vec.len())
            .map(|i| Trajectory {
                world: vec.envs()[i].spec().name.clone(),
                env: i as u32,
                episode: vec.envs()[i].episode(),
                track_len: vec.envs()[i].track().length(),
                ..Default::default()
            })
            .collect();
        let pinned = vec![None; vec.len()];
        let record = vec.envs().first().is_some_and(|e| e.config().record_trace);
        Collector {
            record,
            vec,
            space,
            open,
            pinned,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xC011_EC70),
            env_steps: 0,
            episodes: 0,
            gpu: None,
            moves: Vec::new(),
        }
    }

    /// Environment `i` drives `spec`'s world from its next episode (the running one ends
    /// where it is, so nothing simulated is thrown away).
    pub fn move_at_episode_end(&mut self, i: usize, spec: EnvSpec) {
        if self.moves.len() < self.vec.len() {
            self.moves.resize(self.vec.len(), None);
        }
        self.moves[i] = Some(spec);
    }

    /// Act with the policy's forward passes on `gpu`.
    pub fn with_gpu(mut self, gpu: Arc<gpu::Gpu>) -> Collector {
        self.gpu = Some(gpu::Acting::new(gpu));
        self
    }

    /// The GPU the policy acts on, if any (evaluation trials act there too).
    pub fn gpu_mut(&mut self) -> Option<&mut gpu::Acting> {
        self.gpu.as_mut()
    }

    /// `model`'s actions on `batch` observations `x`: on the GPU when there is one; a GPU that
    /// failed (a lost device, a buffer larger than it binds) leaves the policy acting on the
    /// CPU from then on, and the log says so.
    fn act(&mut self, model: &Arc<ActorCritic>, x: &[f32], batch: usize) -> Vec<policy::ActOutput> {
        if let Some(g) = &mut self.gpu {
            match g.outputs(model, x, batch) {
                // The policy's outputs alone, as on the CPU (`act_policy`): nothing uses the values.
                Ok((out, _)) => return model.choose(&out, &vec![0.0; batch], batch, false, &mut self.rng),
                Err(e) => {
                    tracing::warn!("the policy acts on the CPU from now on: {e}");
                    self.gpu = None;
                }
            }
        }
        let (par, rng) = (self.vec.acting_par(), &mut self.rng);
        self.vec.install(|| model.act_policy(x, batch, false, rng, par))
    }

    /// The environments.
    pub fn vec_env(&self) -> &VecEnv {
        &self.vec
    }

    /// Step until at least `episodes` episodes have completed; return them. An episode that
    /// is running keeps the model it started with; episodes that start now get `model`.
    pub fn collect(
        &mut self,
        model: &Arc<ActorCritic>,
        version: u64,
        episodes: usize,
    ) -> Result<Vec<Trajectory>, RewardError> {
        let n = self.vec.len();
        let dim = self.vec.obs_dim();
        let mut done = Vec::new();
        for (t, pin) in self.open.iter_mut().zip(&mut self.pinned) {
            if t.is_empty() {
                t.policy_version = version;
                *pin = Some(model.clone());
            }
        }
        let mut acts = vec![None; n];
        while done.len() < episodes {
            let obs = self.vec.observations().to_vec();
            // One batched forward pass per policy version in use (usually one, briefly two).
            let mut versions: Vec<u64> = self.open.iter().map(|t| t.policy_version).collect();
            versions.sort_unstable();
            versions.dedup();
            for v in versions {
                let rows: Vec<usize> = (0..n).filter(|&i| self.open[i].policy_version == v).collect();
                let m = self.pinned[rows[0]].clone().expect("every open episode has a model");
                let mut x = Vec::with_capacity(rows.len() * dim);
                for &i in &rows {
                    x.extend_from_slice(&obs[i * dim..(i + 1) * dim]);
                }
                for (a, &i) in self.act(&m, &x, rows.len()).into_iter().zip(&rows) {
                    acts[i] = Some(a);
                }
            }
            let acts_now: Vec<policy::ActOutput> = acts.iter().map(|a| a.expect("acted")).collect();
            let actions: Vec<policy::Action> = acts_now.iter().map(|a| a.choice.to_action(&self.space)).collect();
            for (i, a) in acts_now.iter().enumerate() {
                let t = &mut self.open[i];
                t.obs.extend_from_slice(&obs[i * dim..(i + 1) * dim]);
                t.choices.push(a.choice);
                t.logp.push(a.logp);
                t.values.push(a.value);
            }
            let outcomes = self.vec.step(&actions)?.to_vec();
            self.env_steps += n as u64;
            let wall_clock = if self.record { unix_now() } else { 0.0 };
            for (i, o) in outcomes.iter().enumerate() {
                let t = &mut self.open[i];
                t.rewards.push(o.reward as f32);
                if self.record {
                    t.trace.push(policy::StepTrace { wall_clock, ..o.trace });
                }
                if o.done {
                    t.done = true;
                    t.progress = o.progress;
                    t.lap_complete = o.status == EpisodeStatus::LapComplete;
                    if let Some(spec) = self.moves.get_mut(i).and_then(Option::take) {
                        self.vec.set_world(i, spec).map_err(|e| RewardError::Load {
                            origin: "moving an environment to another world".into(),
                            msg: e.to_string(),
                        })?;
                    }
                    let t = &mut self.open[i];
                    let next = Trajectory {
                        world: self.vec.envs()[i].spec().name.clone(),
                        env: i as u32,
                        episode: self.vec.envs()[i].episode(),
                        track_len: self.vec.envs()[i].track().length(),
                        policy_version: version,
                        ..Default::default()
                    };
                    done.push(std::mem::replace(t, next));
                    self.pinned[i] = Some(model.clone());
                    self.episodes += 1;
                }
            }
        }
        Ok(done)
    }
}

pub use policy::simtrace::unix_now;

/// One evaluation trial's result.
#[derive(Clone, Debug, PartialEq)]
pub struct TrialResult {
    /// Progress reached (%).
    pub progress: f64,
    /// Lap time if the lap was completed (s, penalties included).
    pub lap_time: Option<f64>,
    /// Times the car left the track (resets, plus a final off-track).
    pub off_track: u32,
    /// Times the car crashed (resets, plus a final crash).
    pub crashes: u32,
    /// Bots overtaken, in a race with bots.
    pub overtakes: Option<u32>,
    /// The trial's reward (its steps' summed).
    pub reward: f64,
    /// Steps taken.
    pub steps: u64,
    /// How the trial ended.
    pub status: EpisodeStatus,
    /// Per step, when the configuration records (`record_trace`): the choice, the reward
    /// and the sim-trace fields (DeepRacer's evaluation sim-trace).
    pub log: TrialLog,
}

/// A trial's steps, as its sim-trace needs them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrialLog {
    /// What the policy chose.
    pub choices: Vec<policy::Choice>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// The sim-trace fields.
    pub trace: Vec<policy::StepTrace>,
    /// Camera jobs, first trial: what the car saw every second step (before acting).
    pub frames: Vec<policy::exchange::Frame>,
}

/// How an evaluation runs: its rules, how many trials, their seed and the threads that step
/// them.
#[derive(Clone, Debug)]
pub struct EvalPlan {
    /// Resets, penalties and time limit.
    pub rules: EvalRules,
    /// Trials, run side by side.
    pub count: usize,
    /// The environments' and the action sampling's seed.
    pub seed: u64,
    /// Threads stepping the environments.
    pub threads: usize,
    /// The policy's forward pass on those threads too ([`VecEnv::acting_par`]), for trials
    /// nothing else is computing beside; else on one thread, as when a worker evaluates while
    /// its learner updates in the same process (a forward pass on every core slowed a `train`
    /// run's updates by 30 %, docs/benchmarks.md).
    pub spread: bool,
    /// With a recording configuration, keep what the car saw in every trial (a live race
    /// replays each lap's); otherwise in the first only.
    pub all_frames: bool,
    /// Stop once more trials than this have ended without a lap (a verification that can no
    /// longer hold): the trials still running are dropped, and fewer trials come back.
    pub give_up_after_misses: Option<usize>,
}

/// Run `plan.count` evaluation trials in parallel from the start line, with the policy's
/// most likely action at every step (a trial that has ended is not simulated further; with
/// `plan.give_up_after_misses`, the trials end once that many and one more have missed); its
/// forward passes on `gpu` when one is given (a GPU that fails leaves the rest of the trials
/// on the CPU, and the log says so), else on faer as `plan.spread` says.
pub fn evaluate(
    model: &Arc<ActorCritic>,
    space: &ActionSpace,
    spec: &EnvSpec,
    cfg: &Arc<SimConfig>,
    plan: &EvalPlan,
    gpu: Option<&mut gpu::Acting>,
) -> Result<Vec<TrialResult>, RewardError> {
    let mut groups = evaluate_groups(model, space, &[(spec.clone(), plan.clone())], cfg, gpu, &mut || true)?;
    Ok(groups.pop().map(|g| g.trials).unwrap_or_default())
}

/// One evaluation's trials from a batch ([`evaluate_groups`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GroupTrials {
    /// The trials that ended, in order.
    pub trials: Vec<TrialResult>,
    /// Every trial the plan asked for ended (false when a group gave up, and for the groups
    /// it stopped).
    pub complete: bool,
}

/// Several evaluations as one batch: each `(world, plan)` group's trials are stepped side by
/// side with the others', so that small evaluations fill the cores together (three worlds'
/// 3 trials each take about what one world's 9 take, not three times one world's 3). Each
/// trial is the same as in [`evaluate`] of its group alone: its own seed, the same forward
/// pass row by row. The batch runs on the most threads a group asks for, and acts on them
/// when any group may (`spread`). A group that gives up (`give_up_after_misses`) stops the
/// batch: a batch holds the checks of one checkpoint, and one that can no longer hold decides
/// them all. The groups' trials still running are then dropped. `go_on` is asked before every
/// step: false stops the batch the same way (a worker whose learner no longer needs the
/// trials).
pub fn evaluate_groups(
    model: &Arc<ActorCritic>,
    space: &ActionSpace,
    groups: &[(EnvSpec, EvalPlan)],
    cfg: &Arc<SimConfig>,
    mut gpu: Option<&mut gpu::Acting>,
    go_on: &mut dyn FnMut() -> bool,
) -> Result<Vec<GroupTrials>, RewardError> {
    let reward = RewardFn::Builtin(crate::BuiltinReward::CenterLine);
    // Each group's environments, seeded as a vector of its own would seed them.
    let counts: Vec<usize> = groups.iter().map(|(_, p)| p.count).collect();
    let members: Vec<(EnvSpec, Mode, u64)> = groups
        .iter()
        .flat_map(|(spec, p)| {
            (0..p.count).map(|i| (spec.clone(), Mode::Evaluation(p.rules.clone()), crate::vec_env::env_seed(p.seed, i)))
        })
        .collect();
    let trials = members.len();
    // The group each environment belongs to, and its place in it.
    let owner: Vec<(usize, usize)> =
        counts.iter().enumerate().flat_map(|(g, &n)| (0..n).map(move |i| (g, i))).collect();
    let threads = groups.iter().map(|(_, p)| p.threads).max().unwrap_or(1);
    let mut vec = VecEnv::with_members(members, cfg.clone(), reward, threads)
        .map_err(|e| RewardError::Load { origin: "evaluation".into(), msg: e.to_string() })?;
    // Greedy choices draw nothing from it.
    let mut rng = ChaCha8Rng::seed_from_u64(groups.first().map_or(0, |(_, p)| p.seed));
    let mut results: Vec<Option<TrialResult>> = vec![None; trials];
    let mut logs: Vec<TrialLog> = vec![TrialLog::default(); trials];
    let cap = cfg.episode.max_steps;
    let mut steps = 0u64;
    let dim = vec.obs_dim();
    let par = if groups.iter().any(|(_, p)| p.spread) { vec.acting_par() } else { Par::Seq };
    // What the car saw, for the log: the frame, or the stereo pair's left one; in each group's
    // first trial, or in all of a group's that asks.
    let pixels = (crate::camera::WIDTH * crate::camera::HEIGHT) as usize;
    let channels = dim / pixels;
    let camera = cfg.record_trace && vec.renderer().is_some() && dim.is_multiple_of(pixels) && channels >= 1;
    let kept: Vec<bool> = owner.iter().map(|&(g, i)| i == 0 || groups[g].1.all_frames).collect();
    let missed = |results: &[Option<TrialResult>], g: usize| {
        results.iter().zip(&owner).filter(|(r, o)| o.0 == g && r.as_ref().is_some_and(|r| r.lap_time.is_none())).count()
    };
    while results.iter().any(|r| r.is_none()) && steps < cap && go_on() {
        if camera && steps.is_multiple_of(2) {
            for (i, log) in logs.iter_mut().enumerate().filter(|(i, _)| kept[*i] && results[*i].is_none()) {
                log.frames.push(policy::exchange::Frame {
                    world: groups[owner[i].0].0.name.clone(),
                    width: crate::camera::WIDTH,
                    height: crate::camera::HEIGHT,
                    gray: vec.observations()[i * dim..(i + 1) * dim]
                        .iter()
                        .step_by(channels)
                        .map(|&p| p.clamp(0.0, 255.0) as u8)
                        .collect(),
                    policy_version: 0,
                    step: steps + 1,
                });
            }
        }
        let obs = vec.observations();
        let acts = match gpu.as_deref_mut().map(|g| g.outputs(model, obs, trials)) {
            Some(Ok((out, values))) => model.choose(&out, &values, trials, true, &mut rng),
            Some(Err(e)) => {
                tracing::warn!("the evaluation acts on the CPU from now on: {e}");
                gpu = None;
                vec.install(|| model.act_policy(obs, trials, true, &mut rng, par))
            }
            None => vec.install(|| model.act_policy(obs, trials, true, &mut rng, par)),
        };
        let actions: Vec<policy::Action> = acts.iter().map(|a| a.choice.to_action(space)).collect();
        // A trial that has ended stands still (not simulated or rendered) while the rest finish.
        let running: Vec<bool> = results.iter().map(Option::is_none).collect();
        let outcomes = vec.step_some(&actions, Some(&running))?;
        let wall_clock = if cfg.record_trace { unix_now() } else { 0.0 };
        for (((r, o), log), a) in results.iter_mut().zip(outcomes).zip(&mut logs).zip(&acts) {
            if r.is_none() && cfg.record_trace {
                log.choices.push(a.choice);
                log.rewards.push(o.reward as f32);
                log.trace.push(policy::StepTrace { wall_clock, ..o.trace });
            }
            if r.is_none() && o.done {
                *r = Some(TrialResult {
                    progress: o.progress,
                    lap_time: o.lap_time,
                    off_track: o.off_track(),
                    crashes: o.crashes,
                    overtakes: o.overtakes,
                    reward: o.episode_reward,
                    steps: o.steps,
                    status: o.status,
                    log: std::mem::take(log),
                });
            }
        }
        steps += 1;
        let gave_up = groups
            .iter()
            .enumerate()
            .any(|(g, (_, p))| p.give_up_after_misses.is_some_and(|k| missed(&results, g) > k));
        if gave_up {
            break;
        }
    }
    let mut out: Vec<GroupTrials> = counts.iter().map(|_| GroupTrials { trials: Vec::new(), complete: true }).collect();
    for (r, &(g, _)) in results.into_iter().zip(&owner) {
        match r {
            Some(r) => out[g].trials.push(r),
            None => out[g].complete = false,
        }
    }
    Ok(out)
}
