//! `learner serve`: the network role, a thin shell over [`learner::run::run`].
//!
//! It takes the running job from the coordinator's job table and runs it with a Zenoh
//! [`Link`]: policy versions are published (and answered on the "latest model" queryable),
//! grants and evaluation requests go to the agents, experience and evaluation reports come
//! back, each checked against the job before it is believed (and counted when dropped).
//! The workers are the agents the coordinator assigned to the job. A restarted learner
//! resumes from the run folder's last checkpoint. Other learners serving the same job join
//! its team and share every update ([`crate::team`]).

use crate::team::{self, FollowEnd, TeamLead};
use anyhow::{Context, Result};
use faer::Par;
use learner::Hyperparameters;
use learner::algorithm::{Shared, Team};
use learner::device::Device;
use learner::run::{Inbound, Link, LinkError, Quiet, RunSpec, Start, StopRules, TargetLaps, run};
use learner::update::LearnerState;
use policy::ModelMetadata;
use policy::exchange::{Credit, EvalRequest, PolicyVersion};
use policy::folder::Manifest;
use policy::signature::Signer;
use protocol::Job;
use protocol::exchange::{self as wire, JobView};
use protocol::job::JobStop;
use protocol::net::{self, DropCounters, NetArgs, Sub, try_next, zenoh};
use protocol::{AgentStats, AssignmentTable, ExperienceBatch, LearnerStatus, PROTOCOL_VERSION, WorldStats, keys};
use std::collections::BTreeSet;
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
    /// Threads for the update.
    pub threads: usize,
    /// Seconds between evaluations/checkpoints.
    pub checkpoint_seconds: f64,
    /// The signing key (default: the run folder's).
    pub signing_key: Option<PathBuf>,
    /// Where the network maths run.
    pub device: learner::DeviceChoice,
    /// The agents share this machine's cores ([`learner::run::RunSpec::checks_first`]).
    pub checks_first: bool,
    /// No other learner can reach this coordinator: lead a job at once, without first
    /// waiting to hear the others.
    pub alone: bool,
}

/// Run the learner until the process is stopped.
pub fn serve(args: ServeArgs) -> Result<()> {
    // The id: --id, else the one this machine's own certificate carries, else learner-pid.
    let id = args
        .id
        .clone()
        .or_else(|| args.net.own_id(protocol::secure::Role::Learner))
        .unwrap_or_else(|| format!("learner-{}", std::process::id()));
    let session = net::open_retrying(&args.net.clone().as_machine(protocol::secure::Role::Learner, &id))?;
    let _token =
        session.liveliness().declare_token(keys::learner_alive(&id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let jobs = net::subscribe(&session, keys::JOBS)?;
    let drops = Arc::new(DropCounters::default());
    let device = Device::new(args.device);
    // Who else serves: the other learners' tokens reach a new session over a few hundred
    // milliseconds; no job is led before they had the time to (two leaders would split it).
    let roster = team::Roster::new(&session)?;
    let born = Instant::now();
    let hear_others = if args.alone { Duration::ZERO } else { Duration::from_secs(3) };
    tracing::info!(learner = %id, "learner up; waiting for a job");
    let mut finished: BTreeSet<String> = BTreeSet::new();
    let mut docs: std::collections::HashMap<String, Job> = Default::default();
    let mut adopt: Option<(String, Adopted)> = None;
    let mut standby_note: Option<String> = None;
    loop {
        let Some((_, table)) = try_next::<AssignmentTable>(&jobs, &drops) else {
            std::thread::sleep(Duration::from_millis(200));
            continue;
        };
        if !table.running || finished.contains(&table.job_id) {
            continue;
        }
        if !keys::is_valid_name(&table.job_id) {
            continue;
        }
        // The job's document, fetched once from the coordinator.
        let doc: Job = match docs.get(&table.job_id) {
            Some(d) => d.clone(),
            None => match protocol::job::fetch(&session, &table.job_id, Duration::from_secs(2), &drops) {
                Some(d) => {
                    docs.insert(d.id.clone(), d.clone());
                    d
                }
                None => {
                    tracing::warn!(job = %table.job_id, "the coordinator did not send the job's document; asking again");
                    continue;
                }
            },
        };
        // The lowest id among the live learners leads the job; the others join its team and
        // share every update (and one of them leads if it goes away).
        if born.elapsed() < hear_others {
            std::thread::sleep(hear_others - born.elapsed());
        }
        let ids = roster.ids();
        match ids {
            ids if ids.iter().any(|other| other.as_str() < id.as_str()) => {
                if standby_note.as_deref() != Some(doc.id.as_str()) {
                    tracing::info!(job = %doc.id, learners = ?ids, "another learner leads this job; joining its team");
                    standby_note = Some(doc.id.clone());
                }
                match follow_job(&session, &id, &doc, (&args, &device), &jobs, drops.clone()) {
                    Ok((FollowEnd::Stopped, _)) => {
                        finished.insert(doc.id.clone());
                    }
                    Ok((FollowEnd::LeaderGone, state)) => {
                        tracing::info!(job = %doc.id, "the team's leader is gone");
                        // Should this learner lead next, it goes on from the team's state.
                        adopt = state.map(|s| (doc.id.clone(), s));
                    }
                    Err(e) => {
                        tracing::warn!(job = %doc.id, "could not follow the job's leader: {e:#}");
                        std::thread::sleep(Duration::from_millis(500));
                    }
                }
                continue;
            }
            _ => {}
        }
        finished.insert(doc.id.clone());
        let result = (|| -> Result<()> {
            let mut spec = spec_of(&doc, &args, &device)?;
            spec.adopt = adopt.take().filter(|(job, _)| *job == doc.id).map(|(_, s)| s);
            let mut link = ZenohLink::new(&session, &id, &doc, &jobs, drops.clone(), table)?;
            run(&spec, &mut link, &mut Quiet)?;
            Ok(())
        })();
        if let Err(e) = result {
            tracing::error!(job = %doc.id, "{e:#}");
            let status = LearnerStatus {
                protocol_version: PROTOCOL_VERSION,
                job_id: doc.id.clone(),
                learner_id: id.clone(),
                finished: true,
                failure: format!("{e:#}"),
                ..Default::default()
            };
            let _ = net::put(&session, &keys::learner_status(&doc.id), &status);
        }
    }
}

/// A team's state a follower keeps when its leader goes: the weights and optimisers, and
/// SAC's replay memory as bytes.
type Adopted = (LearnerState, Option<Vec<u8>>);

/// Share `doc`'s updates as a member of its leader's team, until the job stops or the
/// leader goes.
fn follow_job(
    session: &zenoh::Session,
    id: &str,
    doc: &Job,
    (args, device): (&ServeArgs, &Device),
    jobs: &Sub,
    drops: Arc<DropCounters>,
) -> Result<(FollowEnd, Option<Adopted>)> {
    let spec = spec_of(doc, args, device)?;
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(spec.seed);
    let model = policy::ActorCritic::new(&spec.metadata, spec.obs_size, &mut rng);
    let mut algo: Box<dyn Shared> = if spec.metadata.training_algorithm == policy::TrainingAlgorithm::Sac {
        Box::new(
            learner::sac::SacTrainer::new(model, &spec.metadata, spec.obs_size, &spec.hyper, 0, spec.seed, spec.par)
                .map_err(anyhow::Error::msg)?,
        )
    } else {
        Box::new(learner::Ppo::new(model, spec.hyper.clone(), 0, spec.seed, spec.par))
    };
    let view = JobView {
        job_id: &doc.id,
        obs_size: spec.obs_size,
        worlds: &spec.worlds,
        actions: protocol::Actions::of(&spec.metadata.action_space),
    };
    let d = drops.clone();
    // Until the job stops (or its table is no longer published: it ended).
    let mut seen = Instant::now();
    let mut keep_going = || {
        let mut running = true;
        while let Some((_, t)) = try_next::<AssignmentTable>(jobs, &d) {
            if t.job_id == doc.id {
                seen = Instant::now();
                running &= t.running;
            }
        }
        running && seen.elapsed() < Duration::from_secs(15)
    };
    let mut updates = 0u64;
    let mut on_update = |algo: &dyn Shared, result: &Result<learner::UpdateStats, learner::Refused>| {
        updates += 1;
        match result {
            Ok(stats) => {
                tracing::info!(job = %doc.id, version = algo.version(), samples = stats.samples(), updates, "team update")
            }
            Err(why) => tracing::warn!(job = %doc.id, version = algo.version(), updates, "team update refused: {why}"),
        }
    };
    let limit = learner::sac::trainer::memory_limit();
    let follower = team::Follower { session, me: id, memory_limit: limit, drops };
    let end = team::follow(follower, &view, algo.as_mut(), &mut keep_going, &mut on_update)?;
    // The team's state, if this learner took part at all.
    Ok((end, (updates > 0).then(|| (algo.state(), algo.memory()))))
}

/// The stop rules a job's `[stop]` table asks for.
fn stop_rules(s: &JobStop) -> StopRules {
    StopRules {
        minutes: s.minutes,
        max_episodes: Some(s.max_episodes),
        target_progress: s.target_progress,
        target_reward: s.target_reward,
        window: s.window,
        env_steps_budget: s.env_steps_budget,
        target_laps: s.target_laps.map(|l| TargetLaps {
            laps: l as usize,
            evaluations: s.target_evals.max(1) as usize,
            verify_trials: s.verify_trials as usize,
        }),
        plateau_evals: (s.plateau_evals > 0).then_some(s.plateau_evals as usize),
        stop_on_collapse: s.stop_on_collapse,
    }
}

/// The simulator's observation settings in a job's sim config (its `[observation]` table,
/// the sensors set from the model's), for the model's manifest; the simulator's defaults
/// where the table is absent.
fn observation_of(sim_config_toml: &str) -> Result<serde_json::Value> {
    let sim: toml::Table = toml::from_str(sim_config_toml).context("the job's sim config")?;
    Ok(match sim.get("observation") {
        Some(o) => serde_json::to_value(o)?,
        None => serde_json::Value::Null,
    })
}

/// The run a job describes.
fn spec_of(doc: &Job, args: &ServeArgs, device: &Device) -> Result<RunSpec> {
    let metadata = ModelMetadata::parse(&doc.model_metadata_json, "job model_metadata.json")?;
    let hyper = Hyperparameters::parse(&doc.hyperparameters_json, "job hyperparameters.json")?.hyperparameters;
    let camera = !metadata.sensor.contains(&policy::Sensor::StateVector);
    let gpu = device.gpu().context("--device")?;
    Ok(RunSpec {
        name: doc.id.clone(),
        metadata,
        hyper,
        obs_size: doc.obs_size as usize,
        observation: observation_of(&doc.sim_config_toml)?,
        sim_toml: doc.sim_config_toml.clone(),
        worlds: doc.worlds.clone(),
        out: PathBuf::from(&doc.out),
        start: Start::ResumeOrNew { clone_from: doc.clone_from.as_ref().map(PathBuf::from) },
        seed: doc.seed,
        max_policy_lag: doc.max_policy_lag,
        eval_trials: doc.eval_trials.max(1),
        eval_seconds: args.checkpoint_seconds,
        stop: stop_rules(&doc.stop()),
        checks_first: args.checks_first,
        par: if camera { Par::rayon(args.threads) } else { Par::Seq },
        gpu,
        adopt: None,
        signing_key: args.signing_key.clone(),
        tracks: doc.track_lines(),
    })
}

/// The run's link over Zenoh.
struct ZenohLink<'a> {
    session: &'a zenoh::Session,
    learner: String,
    job: String,
    obs_size: usize,
    worlds: Vec<String>,
    actions: protocol::Actions,
    jobs: &'a Sub,
    exp_sub: Sub,
    eval_sub: Sub,
    drops: Arc<DropCounters>,
    latest: Arc<Mutex<Vec<u8>>>,
    _queryable: zenoh::query::Queryable<()>,
    best: Arc<Mutex<Vec<u8>>>,
    _best_queryable: zenoh::query::Queryable<()>,
    promotion: Arc<Mutex<Promotion>>,
    _promote_queryable: zenoh::query::Queryable<()>,
    agents: Vec<String>,
    team: TeamLead<'a>,
    last_table: Instant,
    stop_sent: bool,
    refused: u64,
}

impl<'a> ZenohLink<'a> {
    fn new(
        session: &'a zenoh::Session,
        learner: &str,
        doc: &Job,
        jobs: &'a Sub,
        drops: Arc<DropCounters>,
        table: AssignmentTable,
    ) -> Result<ZenohLink<'a>> {
        let (latest, queryable) = answer_last(session, &keys::policy(&doc.id))?;
        let (best, best_queryable) = answer_last(session, &keys::best(&doc.id))?;
        let promotion: Arc<Mutex<Promotion>> = Arc::default();
        let promote_queryable = {
            let (run, job, best, promotion) =
                (PathBuf::from(&doc.out), doc.id.clone(), best.clone(), promotion.clone());
            session
                .declare_queryable(keys::promote(&doc.id))
                .callback(move |q| {
                    let payload = q.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
                    let reply = promote(&run, &job, &payload, &best, &promotion);
                    let _ = q.reply(q.key_expr().clone(), protocol::encode(&reply)).wait();
                })
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))?
        };
        Ok(ZenohLink {
            session,
            learner: learner.into(),
            job: doc.id.clone(),
            obs_size: doc.obs_size as usize,
            worlds: doc.worlds.clone(),
            actions: protocol::Actions::of(
                &policy::ModelMetadata::parse(&doc.model_metadata_json, "the job's model_metadata.json")?.action_space,
            ),
            jobs,
            exp_sub: net::subscribe(session, &keys::experience_all(&doc.id))?,
            eval_sub: net::subscribe(session, &keys::eval_reports(&doc.id))?,
            drops: drops.clone(),
            latest,
            _queryable: queryable,
            best,
            _best_queryable: best_queryable,
            promotion,
            _promote_queryable: promote_queryable,
            agents: table.assignments.iter().map(|a| a.agent_id.clone()).collect(),
            team: TeamLead::new(session, &doc.id, learner, doc.obs_size as usize, drops.clone())?,
            last_table: Instant::now(),
            stop_sent: false,
            refused: 0,
        })
    }

    fn view(&self) -> JobView<'_> {
        JobView { job_id: &self.job, obs_size: self.obs_size, worlds: &self.worlds, actions: self.actions }
    }

    fn refuse(&mut self, e: &protocol::DecodeError, what: &str) {
        self.drops.refuse(what, e);
        self.refused += 1;
    }
}

/// A person's promotion: the version cars following "best" drive, and its publication, which
/// the run's thread sends (nothing blocking runs in a Zenoh callback).
#[derive(Default)]
struct Promotion {
    version: Option<u64>,
    pending: Option<Vec<u8>>,
}

/// Answer a promotion request: find the checkpoint (or model) folder of that version in the run
/// folder, signed, and make it the job's best model.
fn promote(
    run: &std::path::Path,
    job: &str,
    payload: &[u8],
    best: &Mutex<Vec<u8>>,
    promotion: &Mutex<Promotion>,
) -> protocol::JobReply {
    let reply =
        |ok: bool, text: String| protocol::JobReply { protocol_version: PROTOCOL_VERSION, ok, text, body: None };
    let req = match protocol::decode::<protocol::JobPromote>(payload) {
        Ok(r) if r.job_id == job => r,
        Ok(r) => return reply(false, format!("this learner runs job '{job}', not '{}'", r.job_id)),
        Err(e) => return reply(false, format!("not a promotion request: {e}")),
    };
    let v = req.policy_version;
    let mut folders: Vec<PathBuf> = std::fs::read_dir(run.join("checkpoints"))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    folders.push(run.join("model"));
    let mut have = Vec::new();
    for f in folders {
        let Ok(parts) = policy::ModelParts::read(&f) else { continue };
        let Ok(m) = serde_json::from_str::<Manifest>(&parts.manifest_json) else { continue };
        if m.policy_version != v {
            have.push(m.policy_version);
            continue;
        }
        if parts.signature.is_none() {
            return reply(false, format!("{}: v{v} is not signed; cars would refuse it", f.display()));
        }
        let bytes = protocol::encode(&wire::parts_to_wire(job, v, &parts));
        if let Ok(mut b) = best.lock() {
            *b = bytes.clone();
        }
        if let Ok(mut p) = promotion.lock() {
            p.version = Some(v);
            p.pending = Some(bytes);
        }
        tracing::info!(job, version = v, folder = %f.display(), "promoted: cars following best drive it");
        return reply(true, format!("job {job}: v{v} promoted ({}); cars following best drive it", f.display()));
    }
    have.sort_unstable();
    have.dedup();
    reply(false, format!("job {job} has no checkpoint of v{v} in {}; it has {have:?}", run.display()))
}

/// Bytes a queryable answers with, replaced as they change.
type Cell = Arc<Mutex<Vec<u8>>>;

/// A queryable on `key` that answers with the last bytes stored in the returned cell.
fn answer_last(session: &zenoh::Session, key: &str) -> Result<(Cell, zenoh::query::Queryable<()>)> {
    let cell: Cell = Arc::new(Mutex::new(Vec::new()));
    let c = cell.clone();
    let queryable = session
        .declare_queryable(key)
        .callback(move |q| {
            let bytes = c.lock().map(|b| b.clone()).unwrap_or_default();
            if !bytes.is_empty() {
                let _ = q.reply(q.key_expr().clone(), bytes).wait();
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok((cell, queryable))
}

fn link_err(e: impl std::fmt::Display) -> LinkError {
    LinkError(e.to_string())
}

impl Link for ZenohLink<'_> {
    fn publish(&mut self, p: &PolicyVersion, manifest: &Manifest, signer: &Signer) -> Result<(), LinkError> {
        let bytes = protocol::encode(&wire::policy_to_wire(&self.job, p, manifest, Some(signer)));
        if let Ok(mut l) = self.latest.lock() {
            *l = bytes.clone();
        }
        self.session
            .put(keys::policy(&self.job), bytes)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            // Bulk: never ahead of a car's camera frames or commands on a shared link.
            .priority(zenoh::qos::Priority::DataLow)
            .wait()
            .map_err(link_err)
    }

    fn best(&mut self, p: &PolicyVersion, manifest: &Manifest, signer: &Signer) -> Result<(), LinkError> {
        if let Some(v) = self.promotion.lock().ok().and_then(|pr| pr.version) {
            tracing::info!(job = %self.job, promoted = v, best = p.version, "a new best model; cars keep the promoted one");
            return Ok(());
        }
        let bytes = protocol::encode(&wire::policy_to_wire(&self.job, p, manifest, Some(signer)));
        if let Ok(mut l) = self.best.lock() {
            *l = bytes.clone();
        }
        self.session
            .put(keys::best(&self.job), bytes)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            // Bulk: never ahead of a car's camera frames or commands on a shared link.
            .priority(zenoh::qos::Priority::DataLow)
            .wait()
            .map_err(link_err)
    }

    fn grant(&mut self, credit: &Credit) -> Result<(), LinkError> {
        net::put(self.session, &keys::credit(&self.job), &wire::credit_to_wire(&self.job, credit)).map_err(link_err)
    }

    fn request_eval(&mut self, req: &EvalRequest) -> Result<(), LinkError> {
        let key = keys::eval_request(&self.job, &req.worker);
        net::put(self.session, &key, &wire::eval_request_to_wire(&self.job, req)).map_err(link_err)
    }

    fn next(&mut self, timeout: Duration) -> Result<Option<Inbound>, LinkError> {
        let pending = self.promotion.lock().ok().and_then(|mut p| p.pending.take());
        if let Some(bytes) = pending {
            self.session
                .put(keys::best(&self.job), bytes)
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .priority(zenoh::qos::Priority::DataLow)
                .wait()
                .map_err(link_err)?;
        }
        let deadline = Instant::now() + timeout;
        loop {
            // The job table: who works on the job, and whether it still runs.
            while let Some((_, t)) = try_next::<AssignmentTable>(self.jobs, &self.drops) {
                if t.job_id == self.job {
                    self.last_table = Instant::now();
                    self.agents = t.assignments.iter().map(|a| a.agent_id.clone()).collect();
                    if !t.running && !self.stop_sent {
                        self.stop_sent = true;
                        return Ok(Some(Inbound::Stop("stopped by the coordinator".into())));
                    }
                }
            }
            if self.last_table.elapsed() > Duration::from_secs(15) {
                tracing::warn!(job = %self.job, "no word from the coordinator for 15 s; carrying on");
                self.last_table = Instant::now();
            }
            // Reports first: they are few, and experience can arrive faster than it is taken
            // (SAC's next round comes in while an update runs), which would starve them.
            if let Some((key, r)) = try_next::<protocol::EvalReport>(&self.eval_sub, &self.drops) {
                let agent = keys::last(&key).to_string();
                match wire::eval_report_from_wire(r, &self.view(), &agent) {
                    Ok(r) => return Ok(Some(Inbound::Eval(r))),
                    Err(e) => self.refuse(&e, "an evaluation report"),
                }
            }
            if let Some((key, b)) = try_next::<ExperienceBatch>(&self.exp_sub, &self.drops) {
                let agent = keys::last(&key).to_string();
                match wire::experience_from_wire(b, &self.view(), &agent) {
                    Ok((e, refused)) => {
                        for r in &refused {
                            self.refuse(r, "an episode");
                        }
                        return Ok(Some(Inbound::Experience(e)));
                    }
                    Err(e) => self.refuse(&e, "an experience batch"),
                }
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            std::thread::sleep(Duration::from_millis(2).min(deadline - Instant::now()));
        }
    }

    fn status(&mut self, s: &learner::run::RunStatus) -> Result<(), LinkError> {
        let status = LearnerStatus {
            protocol_version: PROTOCOL_VERSION,
            job_id: self.job.clone(),
            policy_version: s.policy_version,
            iteration: s.iteration,
            episodes: s.episodes,
            env_steps: s.env_steps,
            mean_reward: s.window_reward,
            mean_progress: s.window_progress,
            max_lag: s.max_lag,
            dropped_stale: s.dropped_stale,
            dropped_duplicate: s.dropped_duplicate,
            dropped_bad: s.dropped_bad + self.drops.total(),
            drops: self
                .drops
                .reasons()
                .into_iter()
                .map(|(reason, count)| protocol::DropCount { reason, count })
                .collect(),
            write_failures: s.write_failures,
            write_error: s.write_error.clone(),
            trend: s.trend.clone(),
            failure: String::new(),
            refused: protocol::secure::drop_counts(protocol::secure::REFUSED.reasons()),
            hostile_peers: protocol::secure::drop_counts(protocol::secure::HOSTILE.named()),
            eval_progress: s.eval_progress,
            finished: s.finished,
            run_dir: s.run_dir.clone(),
            worlds: s
                .worlds
                .iter()
                .map(|w| WorldStats {
                    world: w.world.clone(),
                    agents: w.workers,
                    episodes: w.episodes,
                    mean_progress: w.mean_progress,
                    mean_reward: w.mean_reward,
                    steps_per_s: w.steps_per_s,
                    crashes: w.crashes,
                    evaluated: w.eval.is_some(),
                    eval_progress: w.eval.map_or(0.0, |e| e.0),
                    eval_lap_time: w.eval.and_then(|e| e.1).unwrap_or(0.0),
                })
                .collect(),
            window_progress: s.window_progress,
            window_reward: s.window_reward,
            learner_id: self.learner.clone(),
            agents: s
                .workers
                .iter()
                .map(|(a, sps)| AgentStats { agent_id: a.clone(), world: String::new(), steps_per_s: *sps })
                .collect(),
            episodes_received: s.episodes_received,
            eval_laps: s.eval_laps,
            stop_reason: s.stop_reason.clone().unwrap_or_default(),
            learners: self.team.members(),
            team_updates: self.team.team_updates,
            team_failures: self.team.failures,
        };
        net::put(self.session, &keys::learner_status(&self.job), &status).map_err(link_err)
    }

    fn workers(&mut self) -> Vec<String> {
        self.agents.clone()
    }

    fn team(&mut self) -> Option<&mut dyn Team> {
        Some(&mut self.team)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 29: each field of a job's stop table reaches its rule across the wire.
    #[test]
    fn each_field_of_a_jobs_stop_table_reaches_its_rule_across_the_wire() {
        // The rules themselves are tested through a whole run (learner/tests/it/run_scripted.rs);
        // here, that a job's `[stop]` table, sent as the `Job` message, asks for the same.
        let base = protocol::job::default_stop();
        let table: Vec<(JobStop, StopRules)> = vec![
            (base, StopRules { minutes: 10.0, max_episodes: Some(1_000_000), ..StopRules::default() }),
            (JobStop { max_episodes: 60, ..base }, StopRules { max_episodes: Some(60), ..StopRules::default() }),
            (
                JobStop { minutes: 0.1, ..base },
                StopRules { minutes: 0.1, max_episodes: Some(1_000_000), ..StopRules::default() },
            ),
            (
                JobStop { target_progress: Some(25.0), window: 7, ..base },
                StopRules {
                    target_progress: Some(25.0),
                    window: 7,
                    max_episodes: Some(1_000_000),
                    ..StopRules::default()
                },
            ),
            (
                JobStop { target_reward: Some(15.0), ..base },
                StopRules { target_reward: Some(15.0), max_episodes: Some(1_000_000), ..StopRules::default() },
            ),
            (
                JobStop { env_steps_budget: Some(15000), ..base },
                StopRules { env_steps_budget: Some(15000), max_episodes: Some(1_000_000), ..StopRules::default() },
            ),
            (
                JobStop { target_laps: Some(3), target_evals: 3, ..base },
                StopRules {
                    target_laps: Some(TargetLaps { laps: 3, evaluations: 3, verify_trials: 10 }),
                    max_episodes: Some(1_000_000),
                    ..StopRules::default()
                },
            ),
            (
                JobStop { target_laps: Some(3), target_evals: 1, verify_trials: 0, ..base },
                StopRules {
                    target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 0 }),
                    max_episodes: Some(1_000_000),
                    ..StopRules::default()
                },
            ),
            (
                JobStop { plateau_evals: 2, ..base },
                StopRules { plateau_evals: Some(2), max_episodes: Some(1_000_000), ..StopRules::default() },
            ),
            (
                JobStop { stop_on_collapse: true, ..base },
                StopRules { stop_on_collapse: true, max_episodes: Some(1_000_000), ..StopRules::default() },
            ),
        ];
        for (stop, want) in table {
            let doc = Job {
                protocol_version: protocol::PROTOCOL_VERSION,
                id: "j".into(),
                worlds: vec!["reinvent_base".into()],
                stop: Some(stop),
                obs_size: 12,
                ..Default::default()
            };
            let back: Job = protocol::decode(&protocol::encode(&doc)).unwrap();
            protocol::job::check(&back, "j").unwrap();
            assert_eq!(stop_rules(&back.stop()), want, "{stop:?}");
        }
    }

    /// Issue 29: the manifest's observation comes from the job's simulator configuration.
    #[test]
    fn the_manifest_observation_comes_from_the_jobs_sim_config() {
        let toml = "control_hz = 15\n[observation]\nkind = \"camera\"\nlookahead_points = 10\nlidar_range = 2.0\n";
        let o = observation_of(toml).unwrap();
        assert_eq!(o, serde_json::json!({"kind": "camera", "lookahead_points": 10, "lidar_range": 2.0}));
        assert_eq!(observation_of("").unwrap(), serde_json::Value::Null);
        let e = format!("{:#}", observation_of("observation = [").unwrap_err());
        assert!(e.contains("the job's sim config"), "{e}");
    }
}
