//! `sim-agent serve`: the network role, a thin shell over the simulator library.
//!
//! It announces itself with a liveliness token (and its host, cores and renderer on an info
//! queryable), takes its world assignment from the coordinator, runs N environments with the
//! latest policy (taken at episode boundaries), and streams experience to the learner. When
//! the coordinator or learner goes away it keeps its state and carries on when they return;
//! an assignment not refreshed for a while is dropped.

use anyhow::{Context, Result};
use policy::folder;
use protocol::net::{self, DropCounters, NetArgs, decode_sample, zenoh};
use protocol::{AgentInfo, AgentReport, Assignment, ExperienceBatch, PROTOCOL_VERSION, PolicyUpdate, keys};
use sim_agent::config::{SimConfig, parse_toml};
use sim_agent::rollout::Collector;
use sim_agent::{EnvSpec, RewardFn, VecEnv};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// This process's experience batch counter: one sequence per agent, across assignments, so
/// the learner can drop duplicates.
static SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// How long an assignment stays valid without being re-sent.
const ASSIGNMENT_TTL: Duration = Duration::from_secs(5);

/// Options of `sim-agent serve`.
pub struct ServeArgs {
    /// Network endpoints.
    pub net: NetArgs,
    /// Environments to run.
    pub envs: usize,
    /// Agent id (default: host-pid).
    pub id: Option<String>,
    /// Threads for the environments.
    pub threads: usize,
    /// Episodes per experience batch.
    pub episodes_per_batch: usize,
}

struct Work {
    job: String,
    world: String,
    generation: u64,
    collector: Collector,
    obs_size: usize,
    model: Option<(Arc<policy::ActorCritic>, u64)>,
    policy_sub: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    last_query: Option<Instant>,
    steps_reported: u64,
    _reward_dir: Option<PathBuf>,
}

fn host() -> String {
    std::fs::read_to_string("/etc/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "host".into())
}

/// Run the agent until the process is stopped.
pub fn serve(args: ServeArgs) -> Result<()> {
    let session = net::open_retrying(&args.net)?;
    let id = args.id.clone().unwrap_or_else(|| format!("{}-{}", host(), std::process::id()));
    anyhow::ensure!(keys::is_valid_name(&id), "agent id '{id}' may hold only letters, digits, '-', '_' and '.'");
    let info = AgentInfo {
        protocol_version: PROTOCOL_VERSION,
        agent_id: id.clone(),
        host: host(),
        cores: std::thread::available_parallelism().map(|n| n.get() as u32).unwrap_or(1),
        renderer: "none".into(),
        envs: args.envs as u32,
    };
    let info_bytes = protocol::encode(&info);
    let _info_q = session
        .declare_queryable(keys::agent_info(&id))
        .callback(move |q| {
            let _ = q.reply(q.key_expr().clone(), info_bytes.clone()).wait();
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _token =
        session.liveliness().declare_token(keys::agent_alive(&id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let assign_sub = session.declare_subscriber(keys::assignment(&id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let drops = DropCounters::default();
    tracing::info!(agent = %id, envs = args.envs, "sim agent up; waiting for an assignment");
    let mut work: Option<Work> = None;
    let mut last_seen = Instant::now();
    let mut failed: Option<(String, u64)> = None;
    loop {
        let mut latest = None;
        while let Ok(Some(s)) = assign_sub.try_recv() {
            if let Some(a) = decode_sample::<Assignment>(&s, &drops) {
                latest = Some(a);
            }
        }
        if let Some(a) = latest {
            last_seen = Instant::now();
            let same = work.as_ref().is_some_and(|w| w.job == a.job_id && w.generation == a.generation);
            let known_bad = failed.as_ref().is_some_and(|(j, g)| *j == a.job_id && *g == a.generation);
            if !same && !known_bad {
                work = None;
                match start(&session, &args, &a) {
                    Ok(w) => {
                        tracing::info!(job = %a.job_id, world = %w.world, generation = a.generation, "assignment taken");
                        work = Some(w);
                    }
                    Err(e) => {
                        report(&session, &a.job_id, &id, &format!("{e:#}"));
                        failed = Some((a.job_id.clone(), a.generation));
                    }
                }
            }
        } else if work.is_some() && last_seen.elapsed() > ASSIGNMENT_TTL {
            tracing::info!("no assignment for {ASSIGNMENT_TTL:?}: stopping work and waiting");
            work = None;
        }
        match work.as_mut() {
            Some(w) => {
                if let Err(e) = step(&session, &id, &args, w, &drops) {
                    let job = w.job.clone();
                    report(&session, &job, &id, &format!("{e:#}"));
                    failed = Some((job, w.generation));
                    work = None;
                }
            }
            None => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}

fn report(session: &zenoh::Session, job: &str, agent: &str, error: &str) {
    tracing::error!(job, "{error}");
    let r = AgentReport {
        protocol_version: PROTOCOL_VERSION,
        job_id: job.into(),
        agent_id: agent.into(),
        error: error.into(),
    };
    if let Err(e) = net::put(session, &keys::agent_report(job, agent), &r) {
        tracing::warn!("could not send the failure report: {e}");
    }
}

fn start(session: &zenoh::Session, args: &ServeArgs, a: &Assignment) -> Result<Work> {
    let world_spec = a.world.clone().context("assignment without a world")?;
    let world = tracks::world(&world_spec.name)?;
    let mut cfg: SimConfig = parse_toml(&a.sim_config_toml, "assignment sim config")?;
    let meta = policy::ModelMetadata::parse(&a.model_metadata_json, "assignment model_metadata.json")?;
    cfg.observation.kind = sim_agent::config::observation_kind_for(&meta).map_err(|e| anyhow::anyhow!("{e}"))?;
    let (reward, reward_dir) = if a.reward_source.starts_with("builtin:") {
        (RewardFn::from_spec(&a.reward_source)?, None)
    } else {
        let dir =
            std::env::temp_dir().join(format!("paddock-agent-{}-{}-{}", std::process::id(), a.job_id, a.generation));
        std::fs::create_dir_all(&dir)?;
        let file = dir.join(if a.reward_name.ends_with(".py") { a.reward_name.as_str() } else { "reward_function.py" });
        std::fs::write(&file, &a.reward_source)?;
        (RewardFn::from_spec(&file.display().to_string())?, Some(dir))
    };
    let mut spec = EnvSpec::from_world(
        &world,
        if world_spec.reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward },
    );
    spec.noise = Some(sim_agent::config::NoiseConfig {
        steering_deg: world_spec.steering_noise_deg,
        speed_fraction: world_spec.speed_noise_fraction,
    });
    let cfg = Arc::new(cfg);
    let obs_size = sim_agent::obs::obs_dim(&cfg.observation);
    let vec = VecEnv::new(vec![spec; args.envs], cfg, a.seed, reward, args.threads)?;
    let collector = Collector::new(vec, meta.action_space.clone(), a.seed);
    let policy_sub = session.declare_subscriber(keys::policy(&a.job_id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(Work {
        job: a.job_id.clone(),
        world: world.name.clone(),
        generation: a.generation,
        collector,
        obs_size,
        model: None,
        policy_sub,
        last_query: None,
        steps_reported: 0,
        _reward_dir: reward_dir,
    })
}

fn take_policy(w: &mut Work, u: PolicyUpdate) {
    // Any version other than the current one is taken: a restarted learner resumes at an
    // older version than the agents may hold, and its word is the one that counts.
    if w.model.as_ref().is_some_and(|(_, v)| *v == u.policy_version) {
        return;
    }
    match folder::from_parts(&u.model_metadata_json, &u.manifest_json, &u.weights, std::path::Path::new("<network>")) {
        Ok(f) if f.manifest.obs_size == w.obs_size => {
            tracing::info!(version = u.policy_version, "new policy");
            w.model = Some((Arc::new(f.model), u.policy_version));
        }
        Ok(f) => tracing::warn!(
            "policy v{} takes {} inputs, this world gives {}: ignored",
            u.policy_version,
            f.manifest.obs_size,
            w.obs_size
        ),
        Err(e) => tracing::warn!("policy v{} refused: {e}", u.policy_version),
    }
}

fn step(session: &zenoh::Session, id: &str, args: &ServeArgs, w: &mut Work, drops: &DropCounters) -> Result<()> {
    while let Ok(Some(s)) = w.policy_sub.try_recv() {
        if let Some(u) = decode_sample::<PolicyUpdate>(&s, drops) {
            take_policy(w, u);
        }
    }
    if w.model.is_none() {
        if w.last_query.is_none_or(|t| t.elapsed() > Duration::from_secs(1)) {
            w.last_query = Some(Instant::now());
            for u in net::query::<PolicyUpdate>(session, &keys::policy(&w.job), None, Duration::from_secs(2), drops)? {
                take_policy(w, u);
            }
        }
        if w.model.is_none() {
            std::thread::sleep(Duration::from_millis(100));
            return Ok(());
        }
    }
    let (model, version) = w.model.clone().expect("checked");
    let t0 = Instant::now();
    let trajs = w.collector.collect(&model, version, args.episodes_per_batch)?;
    let seq = SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
    let steps = w.collector.env_steps - w.steps_reported;
    w.steps_reported = w.collector.env_steps;
    let batch = ExperienceBatch {
        protocol_version: PROTOCOL_VERSION,
        job_id: w.job.clone(),
        agent_id: id.into(),
        world: w.world.clone(),
        seq,
        trajectories: trajs.iter().map(|t| protocol::trajectory_to_wire(t, w.obs_size)).collect(),
        env_steps: steps,
        seconds: t0.elapsed().as_secs_f64(),
    };
    net::put(session, &keys::experience(&w.job, &w.world, id), &batch)?;
    Ok(())
}
