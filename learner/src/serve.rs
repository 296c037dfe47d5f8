//! `learner serve`: the network role, a thin shell over the learner library.
//!
//! It takes the running job from the coordinator's job table, gathers that job's experience
//! (dropping duplicates by agent and sequence number, stale experience beyond the job's
//! policy-lag bound, and anything malformed), trains when `num_episodes_between_training`
//! episodes have arrived, publishes every policy version, answers "latest model" queries, and
//! writes checkpoints and the best model. A restarted learner resumes from the run folder's
//! last checkpoint.

use anyhow::{Context, Result};
use faer::Par;
use learner::checkpoints::{CheckpointRecord, OpenMode, RunDir};
use learner::{Hyperparameters, Ppo};
use policy::folder::{self, Manifest};
use policy::{ActorCritic, ModelFolder, ModelMetadata, Trajectory};
use protocol::job::JobDoc;
use protocol::net::{self, DropCounters, NetArgs, decode_sample, zenoh};
use protocol::{
    AgentStats, AssignmentTable, ExperienceBatch, LearnerStatus, PROTOCOL_VERSION, PolicyUpdate, WorldStats, keys,
};
use rand::SeedableRng;
use sim_agent::config::{ObservationKind, SimConfig, parse_toml};
use std::collections::{BTreeSet, HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// Options of `learner serve`.
pub struct ServeArgs {
    /// Network endpoints.
    pub net: NetArgs,
    /// Learner id.
    pub id: Option<String>,
    /// Threads for evaluation.
    pub threads: usize,
    /// Seconds between evaluations/checkpoints.
    pub checkpoint_seconds: f64,
}

/// Run the learner until the process is stopped.
pub fn serve(args: ServeArgs) -> Result<()> {
    let session = net::open_retrying(&args.net)?;
    let id = args.id.clone().unwrap_or_else(|| format!("learner-{}", std::process::id()));
    let _token =
        session.liveliness().declare_token(keys::learner_alive(&id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let jobs = session.declare_subscriber(keys::JOBS).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let drops = Arc::new(DropCounters::default());
    tracing::info!(learner = %id, "learner up; waiting for a job");
    let mut finished: BTreeSet<String> = BTreeSet::new();
    loop {
        let Ok(Some(s)) = jobs.recv_timeout(Duration::from_millis(500)) else { continue };
        let Some(table) = decode_sample::<AssignmentTable>(&s, &drops) else { continue };
        if !table.running || finished.contains(&table.job_id) {
            continue;
        }
        let doc: JobDoc = match serde_json::from_str(&table.job_json) {
            Ok(d) => d,
            Err(e) => {
                tracing::warn!("job table for {} holds an unreadable job: {e}", table.job_id);
                continue;
            }
        };
        match run_job(&session, &id, &args, &doc, &jobs, &drops) {
            Ok(()) => {
                finished.insert(doc.id.clone());
            }
            Err(e) => {
                tracing::error!(job = %doc.id, "{e:#}");
                finished.insert(doc.id.clone());
                let status = LearnerStatus {
                    protocol_version: PROTOCOL_VERSION,
                    job_id: doc.id.clone(),
                    learner_id: id.clone(),
                    finished: true,
                    run_dir: format!("error: {e:#}"),
                    ..Default::default()
                };
                let _ = net::put(&session, &keys::learner_status(&doc.id), &status);
            }
        }
    }
}

/// Per-world figures over the last 10 seconds.
#[derive(Default)]
struct WorldWindow {
    recent: VecDeque<(Instant, String, f64, f64)>, // (when, agent, progress, reward) per episode
    steps: VecDeque<(Instant, u64)>,               // environment steps per batch, trained on or not
    episodes: u64,
}

fn hyper_of(doc: &JobDoc) -> Result<Hyperparameters> {
    let parsed = Hyperparameters::parse(&doc.hyperparameters_json, "job hyperparameters.json")?;
    Ok(parsed.hyperparameters)
}

fn run_job(
    session: &zenoh::Session,
    id: &str,
    args: &ServeArgs,
    doc: &JobDoc,
    jobs: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    drops: &Arc<DropCounters>,
) -> Result<()> {
    let start = Instant::now();
    let meta = ModelMetadata::parse(&doc.model_metadata_json, "job model_metadata.json")?;
    let hyper = hyper_of(doc)?;
    let mut cfg: SimConfig = parse_toml(&doc.sim_config_toml, "job sim config")?;
    cfg.observation.kind = sim_agent::config::observation_kind_for(&meta).map_err(|e| anyhow::anyhow!("{e}"))?;
    let obs_size = sim_agent::obs::obs_dim(&cfg.observation);
    let cfg = Arc::new(cfg);
    let out = PathBuf::from(&doc.out);
    let resuming = out.join("model").join("manifest.json").exists();
    let run = RunDir::open(&out, if resuming { OpenMode::Resume } else { OpenMode::New })?;
    let (model, version, parent) = if resuming {
        let index = run.index()?;
        let dir = index
            .last_checkpoint
            .map(|l| run.checkpoint_dir(&l.name))
            .filter(|d| d.exists())
            .unwrap_or_else(|| run.model_dir());
        let f = folder::load(&dir)?;
        tracing::info!(job = %doc.id, from = %dir.display(), version = f.manifest.policy_version, "resuming the job's run");
        (f.model, f.manifest.policy_version, f.manifest.parent)
    } else if let Some(from) = &doc.clone_from {
        let f = folder::load(std::path::Path::new(from))?;
        f.metadata.compatible_with(&meta).map_err(|why| anyhow::anyhow!("{from}: {why}"))?;
        let parent = folder::Parent {
            path: from.clone(),
            policy_version: f.manifest.policy_version,
            weights_sha256: f.manifest.weights_sha256.clone(),
        };
        (f.model, f.manifest.policy_version, Some(parent))
    } else {
        (ActorCritic::new(&meta, obs_size, &mut rand_chacha::ChaCha8Rng::seed_from_u64(doc.seed)), 0, None)
    };
    run.write_file("model_metadata.json", meta.to_json().as_bytes())?;
    run.write_file("hyperparameters.json", hyper.to_json().as_bytes())?;
    run.write_file("sim.toml", doc.sim_config_toml.as_bytes())?;
    let par = if cfg.observation.kind == ObservationKind::Camera { Par::rayon(args.threads) } else { Par::Seq };
    let mut ppo = Ppo::new(model, hyper.clone(), version, doc.seed, par);

    let manifest_for = |ppo: &Ppo, training: serde_json::Value| Manifest {
        format: "paddock-model-1".into(),
        policy_version: ppo.version,
        parent: parent.clone(),
        weights_sha256: String::new(),
        obs_size,
        observation: serde_json::to_value(&cfg.observation).expect("JSON"),
        training,
    };
    let latest: Arc<Mutex<Vec<u8>>> = Arc::new(Mutex::new(Vec::new()));
    let publish = |ppo: &Ppo| -> Result<()> {
        let f = ModelFolder {
            metadata: meta.clone(),
            model: ppo.model.clone(),
            manifest: manifest_for(ppo, serde_json::json!({"job": doc.id})),
        };
        let (m, man, w) = folder::to_parts(&f);
        let u = PolicyUpdate {
            protocol_version: PROTOCOL_VERSION,
            job_id: doc.id.clone(),
            policy_version: ppo.version,
            weights: w,
            model_metadata_json: m,
            manifest_json: man,
        };
        let bytes = protocol::encode(&u);
        *latest.lock().expect("lock") = bytes.clone();
        session
            .put(keys::policy(&doc.id), bytes)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(())
    };
    let latest_q = latest.clone();
    let _queryable = session
        .declare_queryable(keys::policy(&doc.id))
        .callback(move |q| {
            let bytes = latest_q.lock().expect("lock").clone();
            if !bytes.is_empty() {
                let _ = q.reply(q.key_expr().clone(), bytes).wait();
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let exp = session.declare_subscriber(keys::experience_all(&doc.id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    publish(&ppo)?;
    tracing::info!(job = %doc.id, version = ppo.version, run = %out.display(), "training");

    let eval_world = tracks::world(doc.worlds.first().context("the job names no world")?)?;
    let eval_spec = sim_agent::EnvSpec::from_world(&eval_world, tracks::Direction::Forward);
    let mut buffer: Vec<Trajectory> = Vec::new();
    let mut seen: HashMap<String, BTreeSet<u64>> = HashMap::new();
    let mut windows: HashMap<String, WorldWindow> = HashMap::new();
    let mut per_agent: HashMap<String, (String, VecDeque<(Instant, u64)>)> = HashMap::new();
    let mut recent: VecDeque<(f64, f64)> = VecDeque::new();
    let (mut dup, mut stale, mut bad) = (0u64, 0u64, 0u64);
    let (mut episodes, mut env_steps, mut iteration, mut max_lag) =
        (0u64, 0u64, run.index()?.last_checkpoint.map(|l| l.iteration).unwrap_or(0), 0u64);
    let mut last_eval = Instant::now() - Duration::from_secs(3600);
    let mut eval_progress = 0.0;
    let mut running = true;
    let mut last_table = Instant::now();
    let mut last_status = Instant::now() - Duration::from_secs(60);
    loop {
        // Is the job still running?
        while let Ok(Some(s)) = jobs.try_recv() {
            if let Some(t) = decode_sample::<AssignmentTable>(&s, drops) {
                if t.job_id == doc.id {
                    last_table = Instant::now();
                    running = t.running;
                }
            }
        }
        if last_table.elapsed() > Duration::from_secs(15) {
            tracing::warn!(job = %doc.id, "no word from the coordinator for 15 s; carrying on");
            last_table = Instant::now();
        }
        let finishing = !running;
        if let Ok(Some(s)) = exp.recv_timeout(Duration::from_millis(50)) {
            if let Some(b) = decode_sample::<ExperienceBatch>(&s, drops) {
                let fresh = seen.entry(b.agent_id.clone()).or_default().insert(b.seq);
                if !fresh {
                    dup += 1;
                } else {
                    env_steps += b.env_steps;
                    let w = windows.entry(b.world.clone()).or_default();
                    w.steps.push_back((Instant::now(), b.env_steps));
                    let a = per_agent.entry(b.agent_id.clone()).or_insert_with(|| (b.world.clone(), VecDeque::new()));
                    a.0 = b.world.clone();
                    a.1.push_back((Instant::now(), b.env_steps));
                    for wt in b.trajectories {
                        match protocol::trajectory_from_wire(wt, obs_size) {
                            // Too old, or from a version this learner never published (before a restart).
                            Ok(t)
                                if ppo.version.saturating_sub(t.policy_version) > doc.max_policy_lag
                                    || t.policy_version > ppo.version =>
                            {
                                stale += 1
                            }
                            Ok(t) => {
                                let r: f64 = t.rewards.iter().map(|x| *x as f64).sum();
                                w.recent.push_back((Instant::now(), b.agent_id.clone(), t.progress, r));
                                w.episodes += 1;
                                recent.push_back((t.progress, r));
                                while recent.len() as u64 > doc.stop.window.max(1) {
                                    recent.pop_front();
                                }
                                max_lag = max_lag.max(ppo.version - t.policy_version);
                                buffer.push(t);
                            }
                            Err(e) => {
                                bad += 1;
                                tracing::warn!("dropped a trajectory from {}: {e}", b.agent_id);
                            }
                        }
                    }
                }
            }
        }
        let enough = buffer.len() >= hyper.num_episodes_between_training;
        if enough {
            let trajs = std::mem::take(&mut buffer);
            episodes += trajs.len() as u64;
            let stats = ppo.update(&trajs);
            iteration += 1;
            if let Some(why) = &stats.refused {
                tracing::warn!(job = %doc.id, iteration, "{why}");
            }
            publish(&ppo)?;
            let mean = |f: &dyn Fn(&Trajectory) -> f64| trajs.iter().map(f).sum::<f64>() / trajs.len() as f64;
            run.append_metrics(&serde_json::json!({
                "iteration": iteration, "policy_version": ppo.version, "time_s": start.elapsed().as_secs_f64(),
                "episodes": trajs.len(), "total_episodes": episodes, "env_steps": env_steps,
                "mean_reward": mean(&|t| t.rewards.iter().map(|x| *x as f64).sum()), "mean_progress": mean(&|t| t.progress),
                "policy_loss": stats.policy_loss, "value_loss": stats.value_loss, "entropy": stats.entropy,
                "approx_kl": stats.approx_kl, "clip_fraction": stats.clip_fraction, "explained_variance": stats.explained_variance,
                "max_policy_lag": max_lag, "dropped_stale": stale, "dropped_duplicate": dup, "dropped_bad": bad + drops.total(),
                "refused": stats.refused,
            }))?;
        }
        let due = last_eval.elapsed().as_secs_f64() >= args.checkpoint_seconds;
        if (enough && due) || finishing {
            last_eval = Instant::now();
            let trials = sim_agent::rollout::evaluate(
                &ppo.model,
                &meta.action_space,
                &eval_spec,
                &cfg,
                sim_agent::EvalRules::default(),
                doc.eval_trials.max(1) as usize,
                doc.seed ^ iteration,
                args.threads,
            )?;
            let n = trials.len() as f64;
            eval_progress = trials.iter().map(|t| t.progress).sum::<f64>() / n;
            let lap = trials
                .iter()
                .all(|t| t.lap_time.is_some())
                .then(|| trials.iter().filter_map(|t| t.lap_time).sum::<f64>() / n);
            let name = RunDir::checkpoint_name(iteration);
            let manifest = manifest_for(
                &ppo,
                serde_json::json!({"job": doc.id, "iteration": iteration, "episodes": episodes, "env_steps": env_steps, "eval_progress": eval_progress, "eval_lap_time": lap, "hyperparameters": hyper}),
            );
            folder::save(&run.checkpoint_dir(&name), &meta, &ppo.model, &manifest)?;
            let rec = CheckpointRecord {
                name,
                iteration,
                policy_version: ppo.version,
                avg_eval_metric: eval_progress,
                avg_lap_time: lap,
                time_stamp: start.elapsed().as_secs_f64(),
            };
            if run.record(rec)? || !run.model_dir().join("manifest.json").exists() {
                folder::save(&run.model_dir(), &meta, &ppo.model, &manifest)?;
            }
        }
        if enough || finishing || last_status.elapsed() >= Duration::from_secs(1) {
            last_status = Instant::now();
            let now = Instant::now();
            let worlds = windows
                .iter_mut()
                .map(|(name, w)| {
                    while w.recent.front().is_some_and(|r| now.duration_since(r.0) > Duration::from_secs(10)) {
                        w.recent.pop_front();
                    }
                    while w.steps.front().is_some_and(|r| now.duration_since(r.0) > Duration::from_secs(10)) {
                        w.steps.pop_front();
                    }
                    let span =
                        w.steps.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
                    let n = w.recent.len().max(1) as f64;
                    let agents: BTreeSet<&String> = w.recent.iter().map(|r| &r.1).collect();
                    WorldStats {
                        world: name.clone(),
                        agents: agents.len() as u32,
                        episodes: w.episodes,
                        mean_progress: w.recent.iter().map(|r| r.2).sum::<f64>() / n,
                        mean_reward: w.recent.iter().map(|r| r.3).sum::<f64>() / n,
                        steps_per_s: w.steps.iter().map(|r| r.1).sum::<u64>() as f64 / span,
                    }
                })
                .collect();
            let k = recent.len().max(1) as f64;
            let agents = per_agent
                .iter_mut()
                .filter_map(|(id, (world, q))| {
                    while q.front().is_some_and(|r| now.duration_since(r.0) > Duration::from_secs(10)) {
                        q.pop_front();
                    }
                    let span = q.front().map(|f| now.duration_since(f.0).as_secs_f64()).unwrap_or(0.0).clamp(1.0, 10.0);
                    (!q.is_empty()).then(|| AgentStats {
                        agent_id: id.clone(),
                        world: world.clone(),
                        steps_per_s: q.iter().map(|r| r.1).sum::<u64>() as f64 / span,
                    })
                })
                .collect();
            let status = LearnerStatus {
                protocol_version: PROTOCOL_VERSION,
                job_id: doc.id.clone(),
                policy_version: ppo.version,
                iteration,
                episodes,
                env_steps,
                mean_reward: recent.iter().map(|r| r.1).sum::<f64>() / k,
                mean_progress: recent.iter().map(|r| r.0).sum::<f64>() / k,
                max_lag,
                dropped_stale: stale,
                dropped_duplicate: dup,
                dropped_bad: bad + drops.total(),
                eval_progress,
                finished: finishing,
                run_dir: out.display().to_string(),
                worlds,
                window_progress: recent.iter().map(|r| r.0).sum::<f64>() / k,
                window_reward: recent.iter().map(|r| r.1).sum::<f64>() / k,
                learner_id: id.into(),
                agents,
            };
            net::put(session, &keys::learner_status(&doc.id), &status)?;
        }
        if finishing {
            tracing::info!(job = %doc.id, version = ppo.version, "job stopped: final checkpoint and best model written");
            return Ok(());
        }
    }
}
