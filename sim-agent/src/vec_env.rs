//! N environments stepped together on all cores, each with its own seed.
//!
//! Physics, params, rules, built-in rewards and observations run in parallel (rayon); a
//! Python reward is called for the whole batch between the parallel phases, under one GIL
//! acquisition. Finished episodes reset automatically; the step's outcome still reports
//! the episode that ended. Same seed, same actions ⇒ same bits, whatever the thread count.

use crate::config::{ObservationKind, SimConfig};
use crate::env::{Env, EnvError, EnvSpec, Mode, StepOutcome};
use crate::obs::{obs_dim, observe};
use crate::reward::{RewardError, RewardFn};
use policy::Action;
use rayon::prelude::*;
use std::sync::Arc;

/// The seed of environment `index` in a vector seeded with `seed`.
pub fn env_seed(seed: u64, index: usize) -> u64 {
    seed ^ (index as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// A vector of environments.
pub struct VecEnv {
    envs: Vec<Env>,
    reward: RewardFn,
    dim: usize,
    obs: Vec<f32>,
    outcomes: Vec<StepOutcome>,
    rewards: Vec<f64>,
    pool: rayon::ThreadPool,
    renderer: Option<crate::camera::Pooled>,
    /// Per environment: (episode the draw is for, its camera randomisation, its RNG).
    camera_draws: Vec<(u64, CameraDraw, rand_chacha::ChaCha8Rng)>,
}

/// One episode's camera randomisation.
#[derive(Clone, Copy, Debug, Default)]
struct CameraDraw {
    intensity: f64,
    elevation_deg: f64,
    texture_seed: u32,
    jitter: [f64; 2],
}

impl VecEnv {
    /// `specs[i]` is environment i's world; starts are spread evenly round the track.
    pub fn new(
        specs: Vec<EnvSpec>,
        cfg: Arc<SimConfig>,
        seed: u64,
        reward: RewardFn,
        threads: usize,
    ) -> Result<VecEnv, EnvError> {
        VecEnv::with_mode(specs, cfg, seed, reward, threads, Mode::Training)
    }

    /// Environments under the given rules (evaluation trials all start at the line).
    pub fn with_mode(
        specs: Vec<EnvSpec>,
        cfg: Arc<SimConfig>,
        seed: u64,
        reward: RewardFn,
        threads: usize,
        mode: Mode,
    ) -> Result<VecEnv, EnvError> {
        let members = specs.into_iter().enumerate().map(|(i, spec)| (spec, mode.clone(), env_seed(seed, i))).collect();
        VecEnv::with_members(members, cfg, reward, threads)
    }

    /// Environments each with its own world, rules and seed (`env_seed` of its own vector's
    /// seed and its place there): several evaluations' trials stepped as one batch, each
    /// trial the same bits as in a vector of its own.
    pub fn with_members(
        members: Vec<(EnvSpec, Mode, u64)>,
        cfg: Arc<SimConfig>,
        reward: RewardFn,
        threads: usize,
    ) -> Result<VecEnv, EnvError> {
        let n = members.len();
        let seeds: Vec<u64> = members.iter().map(|m| m.2).collect();
        let envs = members
            .into_iter()
            .enumerate()
            .map(|(i, (spec, mode, seed))| Env::new(spec, cfg.clone(), mode, seed, i as f64 / n as f64))
            .collect::<Result<Vec<_>, _>>()?;
        let dim = obs_dim(&cfg.observation);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .build()
            .map_err(|e| EnvError::Config(format!("thread pool: {e}")))?;
        let renderer = if cfg.observation.kind.is_camera() {
            Some(crate::camera::Renderer::pooled().map_err(|e| EnvError::Config(e.to_string()))?)
        } else {
            None
        };
        let mut v = VecEnv {
            envs,
            reward,
            dim,
            obs: vec![0.0; n * dim],
            outcomes: Vec::with_capacity(n),
            rewards: Vec::with_capacity(n),
            pool,
            renderer,
            camera_draws: seeds
                .iter()
                .map(|&s| {
                    (
                        0,
                        CameraDraw::default(),
                        <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(s ^ 0x00CA_3E7A),
                    )
                })
                .collect(),
        };
        let VecEnv { envs, obs, .. } = &mut v;
        for (e, o) in envs.iter().zip(obs.chunks_mut(dim.max(1))) {
            observe(e, o);
        }
        v.render();
        Ok(v)
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.envs.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// Observation length per environment.
    pub fn obs_dim(&self) -> usize {
        self.dim
    }

    /// Current observations, `len() × obs_dim()` values, environment-major.
    pub fn observations(&self) -> &[f32] {
        &self.obs
    }

    /// Environment `i` drives `spec`'s world from the episode it has just begun
    /// ([`Env::set_world`]); its observation is taken again.
    pub fn set_world(&mut self, i: usize, spec: EnvSpec) -> Result<(), EnvError> {
        self.envs[i].set_world(spec)?;
        let dim = self.dim.max(1);
        observe(&self.envs[i], &mut self.obs[i * dim..(i + 1) * dim]);
        // A new draw of the camera's randomisation for the new world's episode.
        self.camera_draws[i].0 = u64::MAX;
        self.render();
        Ok(())
    }

    /// The environments (read-only).
    pub fn envs(&self) -> &[Env] {
        &self.envs
    }

    /// Step every environment with its action. A reward error stops the batch.
    pub fn step(&mut self, actions: &[Action]) -> Result<&[StepOutcome], RewardError> {
        self.step_some(actions, None)
    }

    /// Step the environments `active` marks (every one with `None`); the others stand still:
    /// not simulated, rewarded or rendered, their observations as they were and their
    /// outcomes empty (`done` false, no steps). What an active environment does is the same
    /// bits either way: each has its own seed. Evaluation trials that have ended stand still
    /// while the rest finish.
    pub fn step_some(&mut self, actions: &[Action], active: Option<&[bool]>) -> Result<&[StepOutcome], RewardError> {
        assert_eq!(actions.len(), self.envs.len(), "one action per environment");
        if let Some(a) = active {
            assert_eq!(a.len(), self.envs.len(), "one mark per environment");
        }
        let on = |i: usize| active.is_none_or(|a| a[i]);
        let VecEnv { envs, reward, dim, obs, outcomes, rewards, pool, .. } = self;
        let dim = (*dim).max(1);
        outcomes.clear();
        outcomes.resize(envs.len(), placeholder());
        pool.install(|| -> Result<(), RewardError> {
            match reward {
                RewardFn::Builtin(b) => {
                    let b = *b;
                    envs.par_iter_mut()
                        .zip(actions)
                        .zip(outcomes.par_iter_mut())
                        .zip(obs.par_chunks_mut(dim))
                        .enumerate()
                        .filter(|(i, _)| on(*i))
                        .try_for_each(|(_, (((e, a), out), o))| {
                            e.advance(*a);
                            let r = if e.needs_reward() { b.reward(e.params(), e.line())? } else { 0.0 };
                            *out = close(e, r, o);
                            Ok(())
                        })
                }
                RewardFn::Python(py) => {
                    envs.par_iter_mut().zip(actions).enumerate().filter(|(i, _)| on(*i)).for_each(|(_, (e, a))| {
                        e.advance(*a);
                    });
                    let asks = |(i, e): &(usize, &Env)| on(*i) && e.needs_reward();
                    rewards.clear();
                    py.call_batch(
                        envs.iter().enumerate().filter(asks).map(|(i, e)| (i, e.episode(), &**e.track(), e.params())),
                        rewards,
                    )?;
                    let mut next = rewards.iter();
                    let per_env: Vec<f64> = envs
                        .iter()
                        .enumerate()
                        .map(|ie| if asks(&ie) { *next.next().expect("one per call") } else { 0.0 })
                        .collect();
                    envs.par_iter_mut()
                        .zip(per_env)
                        .zip(outcomes.par_iter_mut())
                        .zip(obs.par_chunks_mut(dim))
                        .enumerate()
                        .filter(|(i, _)| on(*i))
                        .for_each(|(_, (((e, r), out), o))| *out = close(e, r, o));
                    Ok(())
                }
            }
        })?;
        self.render_some(active);
        Ok(&self.outcomes)
    }

    /// Camera observations: every environment's frame in one batch (with the episode's
    /// domain randomisation, and image noise, when configured).
    fn render(&mut self) {
        self.render_some(None)
    }

    /// The frames of the environments `active` marks (every one with `None`), in one batch.
    fn render_some(&mut self, active: Option<&[bool]>) {
        let on = |i: usize| active.is_none_or(|a| a[i]);
        let Some(r) = self.renderer.as_mut() else { return };
        if !(0..self.envs.len()).any(on) {
            return;
        }
        use rand::Rng;
        use rand_distr::{Distribution, Normal};
        let cfg = self.envs.first().map(|e| e.config().camera.clone()).unwrap_or_default();
        for (_, (e, (episode, draw, rng))) in
            self.envs.iter().zip(self.camera_draws.iter_mut()).enumerate().filter(|(i, _)| on(*i))
        {
            if *episode != e.episode() {
                *episode = e.episode();
                let l = e.spec().lighting;
                *draw = if cfg.randomize {
                    let pick = |rng: &mut rand_chacha::ChaCha8Rng, r: [f64; 2]| {
                        if r[1] > r[0] { rng.random_range(r[0]..r[1]) } else { r[0] }
                    };
                    let h = cfg.height_jitter.abs();
                    let p = cfg.pitch_jitter_deg.abs().to_radians();
                    CameraDraw {
                        intensity: pick(rng, cfg.light_intensity),
                        elevation_deg: pick(rng, cfg.light_elevation_deg),
                        texture_seed: if cfg.texture_variation { rng.random_range(1..1000) } else { 0 },
                        jitter: [
                            if h > 0.0 { rng.random_range(-h..h) } else { 0.0 },
                            if p > 0.0 { rng.random_range(-p..p) } else { 0.0 },
                        ],
                    }
                } else {
                    CameraDraw {
                        intensity: l.intensity,
                        elevation_deg: l.elevation_deg,
                        texture_seed: 0,
                        jitter: [0.0, 0.0],
                    }
                };
            }
        }
        // One camera, or the stereo pair: left then right per environment.
        let stereo = self.envs.first().is_some_and(|e| e.config().observation.kind == ObservationKind::Stereo);
        let lateral: &[f64] =
            if stereo { &[crate::camera::STEREO_OFFSET, -crate::camera::STEREO_OFFSET] } else { &[0.0] };
        let views: Vec<crate::camera::View<'_>> = self
            .envs
            .iter()
            .zip(&self.camera_draws)
            .flat_map(|(e, (_, d, _))| {
                let p = e.pose();
                let mut lighting = e.spec().lighting;
                lighting.intensity = d.intensity;
                lighting.elevation_deg = d.elevation_deg;
                lateral.iter().map(move |&side| crate::camera::View {
                    track: e.track(),
                    surface: e.spec().surface,
                    lighting,
                    pose: crate::camera::beside([p.x, p.y, p.yaw], side),
                    jitter: d.jitter,
                    texture_seed: d.texture_seed,
                    objects: e.objects(),
                })
            })
            .collect();
        // Every environment keeps its own place in the renderer's atlas (a frame's bits depend
        // on where it is drawn); those standing still are not drawn.
        let drawn: Option<Vec<bool>> =
            active.map(|a| a.iter().flat_map(|&on| std::iter::repeat_n(on, lateral.len())).collect());
        let frames = r.render_some(&views, drawn.as_deref(), false);
        let frame = frames.len() / self.envs.len().max(1);
        let channels = lateral.len();
        let noise = if cfg.randomize && cfg.image_noise > 0.0 { Normal::new(0.0, cfg.image_noise).ok() } else { None };
        // The pixels' place in each observation (a LiDAR's values may come first).
        let at = self.envs.first().map_or(0, |e| crate::obs::camera_offset(&e.config().observation));
        let dim = self.dim.max(1);
        let VecEnv { obs, camera_draws, pool, .. } = self;
        let rendered: Vec<_> = obs
            .chunks_mut(dim)
            .zip(frames.chunks(frame))
            .zip(camera_draws.iter_mut())
            .enumerate()
            .filter(|(i, _)| on(*i))
            .map(|(_, both)| both)
            .collect();
        // Each environment's pixels on the environments' threads (its noise from its own RNG:
        // the same bits on any number of them).
        pool.install(|| {
            rendered.into_par_iter().for_each(|((o, px), (_, _, rng))| {
                let o = &mut o[at..at + frame];
                // The frames of one environment, one after the other, to its channels (HWC).
                let plane = frame / channels;
                for (k, o) in o.iter_mut().enumerate() {
                    let p = px[(k % channels) * plane + k / channels] as f64;
                    *o = match &noise {
                        Some(n) => (p + n.sample(rng)).round().clamp(0.0, 255.0) as f32,
                        None => p as f32,
                    };
                }
            })
        });
    }

    /// The renderer's adapter, when the observation is the camera.
    pub fn renderer(&self) -> Option<&str> {
        self.renderer.as_ref().map(|r| r.adapter())
    }

    /// How the policy's forward pass over these environments may split: over the
    /// environments' threads for a camera network (its convolutions split the samples), on one
    /// thread for the state vector's small network, which is slower split.
    pub fn acting_par(&self) -> faer::Par {
        let n = self.pool.current_num_threads();
        if self.renderer.is_some() && n > 1 { faer::Par::rayon(n) } else { faer::Par::Seq }
    }

    /// Run `f` on the environments' threads: the policy's forward pass (with
    /// [`VecEnv::acting_par`]) then shares the cores that step the environments, between steps,
    /// and not the pool of the learner that may run in the same process.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.pool.install(f)
    }
}

fn close(e: &mut Env, reward: f64, obs: &mut [f32]) -> StepOutcome {
    let out = e.finish(reward);
    if out.done {
        e.reset();
    }
    observe(e, obs);
    out
}

fn placeholder() -> StepOutcome {
    StepOutcome {
        reward: 0.0,
        done: false,
        truncated: false,
        status: crate::env::EpisodeStatus::Prepare,
        progress: 0.0,
        steps: 0,
        sim_time: 0.0,
        lap_time: None,
        episode_reward: 0.0,
        resets: 0,
        crashes: 0,
        laps: 0,
        overtakes: None,
        trace: policy::StepTrace::default(),
    }
}
