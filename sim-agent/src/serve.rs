//! `sim-agent serve`: the network role, a thin shell over [`sim_agent::worker::Worker`].
//!
//! It announces itself with a liveliness token (and its host, cores and renderer on an info
//! queryable), takes its assignment from the coordinator (the job's worlds, all driven at
//! once), and hands the worker what arrives over Zenoh: policy versions, grants and
//! evaluation requests, each checked against the job before it is believed. The worker's
//! experience and evaluation reports go back the same way. When the coordinator or learner
//! goes away it keeps its state and carries on when they return; an assignment not refreshed
//! for a while is dropped.

use crate::gate::{GateJob, PolicyGate, Trust};
use anyhow::{Context, Result};
use protocol::Job;
use protocol::exchange::{self as wire, JobView};
use protocol::net::{self, DropCounters, NetArgs, Sub, try_next, zenoh};
use protocol::secure::Role;
use protocol::{AgentInfo, AgentReport, Assignment, PROTOCOL_VERSION, PolicyUpdate, keys};
use sim_agent::config::{SimConfig, parse_toml};
use sim_agent::worker::{Worker, WorkerError, WorkerInbound, WorkerLink, WorkerOutbound, WorkerSetup};
use sim_agent::{EnvSpec, RewardFn};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// How long an assignment stays valid without being re-sent.
const ASSIGNMENT_TTL: Duration = Duration::from_secs(5);

/// The least time between two reports of this agent's refusals.
const REFUSAL_REPORT: Duration = Duration::from_secs(2);

/// Refusal reasons a report carries (the most frequent).
const REFUSAL_REASONS: usize = 16;

/// Options of `sim-agent serve`.
pub struct ServeArgs {
    /// Network endpoints.
    pub net: NetArgs,
    /// Environments to run (unless the job says).
    pub envs: usize,
    /// Agent id (default: host-pid).
    pub id: Option<String>,
    /// Threads for the environments.
    pub threads: usize,
    /// Where the policy acts: a GPU (`gpu::Gpu::open`'s rules) or the CPU.
    pub device: gpu::DeviceChoice,
    /// Whose policies it runs.
    pub trust: Trust,
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
    // One device for every assignment this agent takes.
    let gpu = gpu::Gpu::open(args.device).context("--device")?.map(Arc::new);
    // The id: --id, else the one this machine's own certificate carries, else host-pid.
    let id = args
        .id
        .clone()
        .or_else(|| args.net.own_id(Role::Agent))
        .unwrap_or_else(|| format!("{}-{}", host(), std::process::id()));
    anyhow::ensure!(keys::is_valid_name(&id), "agent id '{id}' may hold only letters, digits, '-', '_' and '.'");
    let session = net::open_retrying(&args.net.clone().as_machine(Role::Agent, &id))?;
    // This process's life, drawn at random: the coordinator tells an agent started again
    // under its id by it (its liveliness token may outlast the process it came from), and
    // the learner its batches from its earlier life's.
    let life = rand::random::<u32>();
    let info = AgentInfo {
        protocol_version: PROTOCOL_VERSION,
        agent_id: id.clone(),
        host: host(),
        cores: std::thread::available_parallelism().map(|n| n.get() as u32).unwrap_or(1),
        renderer: "none".into(),
        envs: args.envs as u32,
        life,
    };
    let info_bytes = protocol::encode(&info);
    // Answered on its own key, whatever the query's (the coordinator asks every agent at once).
    let info_key = keys::agent_info(&id);
    let _info_q = session
        .declare_queryable(info_key.clone())
        .callback(move |q| {
            let _ = q.reply(info_key.clone(), info_bytes.clone()).wait();
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _token =
        session.liveliness().declare_token(keys::agent_alive(&id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let assign_sub = net::subscribe(&session, &keys::assignment(&id))?;
    let drops = DropCounters::default();
    // One gate for every assignment: a job's pinned key outlives a change of worlds.
    let gate = PolicyGate::start(args.trust.clone()).context("starting the policy check")?;
    tracing::info!(agent = %id, envs = args.envs, "sim agent up; waiting for an assignment");
    let mut failed: Option<(String, u64)> = None;
    let mut docs: Vec<Job> = Vec::new();
    let mut next: Option<Assignment> = None;
    // Batches are numbered upwards within this process's life, its number in the high 32
    // bits: an agent started again under its id (killed, joined again) is a new life to the
    // learner, whose batches are not taken for its earlier life's repeats.
    let mut seq = u64::from(life) << 32;
    loop {
        let a = match next.take() {
            Some(a) => a,
            None => match try_next::<Assignment>(&assign_sub, &drops) {
                Some((_, a)) => a,
                None => {
                    std::thread::sleep(Duration::from_millis(100));
                    continue;
                }
            },
        };
        if a.agent_id != id
            || !keys::is_valid_name(&a.job_id)
            || failed.as_ref().is_some_and(|(j, g)| *j == a.job_id && *g == a.generation)
        {
            continue;
        }
        // The job's document, fetched once from the coordinator (assignments name the job).
        let doc = match docs.iter().find(|d| d.id == a.job_id) {
            Some(d) => d.clone(),
            None => match protocol::job::fetch(&session, &a.job_id, Duration::from_secs(2), &drops) {
                Some(d) => {
                    if docs.len() >= 8 {
                        docs.remove(0);
                    }
                    docs.push(d.clone());
                    d
                }
                None => {
                    tracing::warn!(job = %a.job_id, "the coordinator did not send the job's document; asking again");
                    continue;
                }
            },
        };
        let mut link = match AgentLink::new(&session, &id, &a, &doc, &assign_sub, &drops, &gate) {
            Ok(l) => l,
            Err(e) => {
                report(&session, &a.job_id, &id, &format!("{e:#}"));
                failed = Some((a.job_id.clone(), a.generation));
                continue;
            }
        };
        let result = start(&args, &id, &a, &doc, seq, gpu.clone()).and_then(|mut w| {
            tracing::info!(job = %a.job_id, worlds = ?w_names(&a), generation = a.generation, "assignment taken");
            let r = w.drive(&mut link).map_err(anyhow::Error::from);
            seq = w.seq();
            r
        });
        match result {
            Ok(()) => next = link.next_assignment.take(),
            Err(e) => {
                report(&session, &a.job_id, &id, &format!("{e:#}"));
                failed = Some((a.job_id.clone(), a.generation));
            }
        }
    }
}

fn w_names(a: &Assignment) -> Vec<String> {
    a.worlds.iter().map(|w| w.name.clone()).collect()
}

fn report(session: &zenoh::Session, job: &str, agent: &str, error: &str) {
    tracing::error!(job, "{error}");
    let r = AgentReport {
        protocol_version: PROTOCOL_VERSION,
        job_id: job.into(),
        agent_id: agent.into(),
        error: error.into(),
        refused: vec![],
        hostile_peers: vec![],
    };
    if let Err(e) = net::put(session, &keys::agent_report(job, agent), &r) {
        tracing::warn!("could not send the failure report: {e}");
    }
}

/// The job's simulator configuration, its observation set from the model's sensors.
fn job_config(doc: &Job) -> Result<SimConfig> {
    let mut cfg: SimConfig = parse_toml(&doc.sim_config_toml, "the job's sim config")?;
    let meta = policy::ModelMetadata::parse(&doc.model_metadata_json, "the job's model_metadata.json")?;
    cfg.observation.set_sensors(&meta)?;
    Ok(cfg)
}

fn start(
    args: &ServeArgs,
    id: &str,
    a: &Assignment,
    doc: &Job,
    first_seq: u64,
    gpu: Option<Arc<gpu::Gpu>>,
) -> Result<Worker> {
    anyhow::ensure!(!a.worlds.is_empty(), "assignment without a world");
    let cfg = job_config(doc)?;
    let meta = policy::ModelMetadata::parse(&doc.model_metadata_json, "the job's model_metadata.json")?;
    // Compiled in memory; the file keeps its name in tracebacks.
    let reward = RewardFn::from_source(reward_file_name(&doc.reward_name), &doc.reward_source)?
        .with_time_limit(cfg.reward_time_limit());
    let mut worlds = Vec::new();
    for w in &a.worlds {
        let world = tracks::world(&w.name).with_context(|| format!("assigned world {:?}", w.name))?;
        let mut spec = EnvSpec::from_world(
            &world,
            if w.reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward },
        );
        spec.noise = Some(sim_agent::config::NoiseConfig {
            steering_deg: w.steering_noise_deg,
            speed_fraction: w.speed_noise_fraction,
        });
        worlds.push(spec);
    }
    let envs = if a.envs > 0 { a.envs as usize } else { args.envs };
    Ok(Worker::new(WorkerSetup {
        id: id.into(),
        worlds,
        offset: a.offset as usize,
        weights: a.weights.clone(),
        envs,
        threads: args.threads,
        cfg: Arc::new(cfg),
        reward,
        space: meta.action_space.clone(),
        seed: a.seed,
        first_seq,
        gpu,
    })?)
}

/// The name a job's reward file shows in tracebacks.
pub fn reward_file_name(name: &str) -> &str {
    if name.ends_with(".py") { name } else { "reward_function.py" }
}

/// The worker's link over Zenoh for one assignment.
struct AgentLink<'a> {
    session: &'a zenoh::Session,
    id: String,
    job: String,
    generation: u64,
    /// The schedule's weights last taken.
    weights: Vec<f64>,
    /// The job's worlds (what its messages may name).
    worlds: Vec<String>,
    obs_size: usize,
    actions: protocol::Actions,
    assign_sub: &'a Sub,
    policy_sub: Sub,
    credit_sub: Sub,
    eval_sub: Sub,
    drops: &'a DropCounters,
    gate: &'a PolicyGate,
    /// What the gate checks this job's policies against.
    gate_job: Arc<GateJob>,
    /// Refusals last reported to the coordinator (their total) and when.
    reported: (u64, Option<Instant>),
    last_seen: Instant,
    last_query: Option<Instant>,
    queue: VecDeque<WorkerInbound>,
    next_assignment: Option<Assignment>,
}

impl<'a> AgentLink<'a> {
    fn new(
        session: &'a zenoh::Session,
        id: &str,
        a: &Assignment,
        doc: &Job,
        assign_sub: &'a Sub,
        drops: &'a DropCounters,
        gate: &'a PolicyGate,
    ) -> Result<AgentLink<'a>> {
        let cfg = job_config(doc)?;
        let worlds = if a.job_worlds.is_empty() { w_names(a) } else { a.job_worlds.clone() };
        let obs_size = sim_agent::obs::obs_dim(&cfg.observation);
        let actions = protocol::Actions::of(
            &policy::ModelMetadata::parse(&doc.model_metadata_json, "the job's model_metadata.json")?.action_space,
        );
        Ok(AgentLink {
            session,
            id: id.into(),
            job: a.job_id.clone(),
            generation: a.generation,
            weights: a.weights.clone(),
            gate_job: Arc::new(GateJob { job_id: a.job_id.clone(), obs_size, worlds: worlds.clone(), actions }),
            worlds,
            obs_size,
            actions,
            assign_sub,
            policy_sub: net::subscribe(session, &keys::policy(&a.job_id))?,
            credit_sub: net::subscribe(session, &keys::credit(&a.job_id))?,
            eval_sub: net::subscribe(session, &keys::eval_request(&a.job_id, id))?,
            drops,
            gate,
            reported: (0, None),
            last_seen: Instant::now(),
            last_query: None,
            queue: VecDeque::new(),
            next_assignment: None,
        })
    }

    fn view(&self) -> JobView<'_> {
        JobView { job_id: &self.job, obs_size: self.obs_size, worlds: &self.worlds, actions: self.actions }
    }

    /// Hand a policy to the gate (its verdict comes back in [`Self::poll`]).
    fn take_policy(&mut self, u: PolicyUpdate) {
        if let Err(e) = self.gate.offer(&self.gate_job, u) {
            self.drops.refuse("a policy", &e);
        }
    }

    /// The gate's verdicts on this job's policies: the ones that passed go to the worker.
    fn take_verdicts(&mut self) {
        while let Some(v) = self.gate.next() {
            if v.job_id != self.job {
                continue;
            }
            match v.result {
                Ok(p) => {
                    tracing::info!(version = p.policy.version, key = %p.key, "new policy");
                    self.queue.push_back(WorkerInbound::Policy(p.policy));
                }
                Err(e) => self.drops.refuse("a policy", &e),
            }
        }
    }

    /// Tell the coordinator what this agent has refused (its checks' and its network's), when
    /// that changed, at most every [`REFUSAL_REPORT`].
    fn report_refusals(&mut self) {
        let total = self.drops.total() + protocol::secure::REFUSED.total();
        if total == self.reported.0 || self.reported.1.is_some_and(|t| t.elapsed() < REFUSAL_REPORT) {
            return;
        }
        let mut refused = protocol::secure::drop_counts(self.drops.reasons());
        refused.extend(protocol::secure::drop_counts(protocol::secure::REFUSED.reasons()));
        refused.sort_by(|a, b| b.count.cmp(&a.count).then_with(|| a.reason.cmp(&b.reason)));
        refused.truncate(REFUSAL_REASONS);
        let r = AgentReport {
            protocol_version: PROTOCOL_VERSION,
            job_id: self.job.clone(),
            agent_id: self.id.clone(),
            error: String::new(),
            refused,
            hostile_peers: protocol::secure::drop_counts(protocol::secure::HOSTILE.named())
                .into_iter()
                .take(REFUSAL_REASONS)
                .collect(),
        };
        self.reported = (total, Some(Instant::now()));
        if let Err(e) = net::put(self.session, &keys::agent_report(&self.job, &self.id), &r) {
            tracing::warn!("could not report the refusals: {e}");
        }
    }

    /// Move what arrived into the queue; false when the assignment ended.
    fn poll(&mut self, need_policy: bool) -> Result<bool, WorkerError> {
        while let Some((_, a)) = try_next::<Assignment>(self.assign_sub, self.drops) {
            if a.agent_id != self.id {
                continue;
            }
            if a.job_id == self.job && a.generation == self.generation {
                self.last_seen = Instant::now();
                if a.weights != self.weights && a.weights.len() == a.worlds.len() {
                    self.weights = a.weights.clone();
                    self.queue.push_back(WorkerInbound::Weights(a.weights));
                }
            } else {
                self.next_assignment = Some(a);
                return Ok(false);
            }
        }
        if self.last_seen.elapsed() > ASSIGNMENT_TTL {
            tracing::info!("no assignment for {ASSIGNMENT_TTL:?}: stopping work and waiting");
            return Ok(false);
        }
        while let Some((_, u)) = try_next::<PolicyUpdate>(&self.policy_sub, self.drops) {
            self.take_policy(u);
        }
        self.take_verdicts();
        self.report_refusals();
        if need_policy && self.queue.is_empty() && self.last_query.is_none_or(|t| t.elapsed() > Duration::from_secs(1))
        {
            self.last_query = Some(Instant::now());
            let key = keys::policy(&self.job);
            let latest = net::query::<PolicyUpdate>(self.session, &key, None, Duration::from_secs(2), self.drops)
                .map_err(|e| WorkerError::Link(e.to_string()))?;
            for u in latest {
                self.take_policy(u);
            }
        }
        while let Some((_, c)) = try_next::<protocol::Credit>(&self.credit_sub, self.drops) {
            match wire::credit_from_wire(c, &self.job) {
                Ok(c) => self.queue.push_back(WorkerInbound::Credit(c)),
                Err(e) => self.drops.refuse("a credit", &e),
            }
        }
        while let Some((_, r)) = try_next::<protocol::EvalRequest>(&self.eval_sub, self.drops) {
            match wire::eval_request_from_wire(r, &self.view(), &self.id) {
                Ok(r) => self.queue.push_back(WorkerInbound::Eval(r)),
                Err(e) => {
                    self.drops.refuse("an evaluation request", &e);
                }
            }
        }
        Ok(true)
    }
}

impl WorkerLink for AgentLink<'_> {
    fn next(&mut self, timeout: Duration, need_policy: bool) -> Result<Option<WorkerInbound>, WorkerError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Ok(Some(m));
            }
            if !self.poll(need_policy)? {
                return Ok(Some(WorkerInbound::End));
            }
            if let Some(m) = self.queue.pop_front() {
                return Ok(Some(m));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            std::thread::sleep(Duration::from_millis(5).min(deadline - Instant::now()));
        }
    }

    fn send(&mut self, out: WorkerOutbound) -> Result<(), WorkerError> {
        let r = match out {
            WorkerOutbound::Experience(e) => {
                if let Some(f) = &e.frame {
                    // For watchers only: a lost frame is no loss.
                    let _ = net::put(
                        self.session,
                        &keys::camera(&self.job, &self.id),
                        &wire::frame_to_wire(&self.job, &self.id, f),
                    );
                }
                net::put(
                    self.session,
                    &keys::experience(&self.job, &self.id),
                    &wire::experience_to_wire(&self.job, &e, self.obs_size),
                )
            }
            WorkerOutbound::Eval(r) => net::put(
                self.session,
                &keys::eval_report(&self.job, &self.id),
                &wire::eval_report_to_wire(&self.job, &r),
            ),
        };
        r.map_err(|e| WorkerError::Link(e.to_string()))
    }
}
