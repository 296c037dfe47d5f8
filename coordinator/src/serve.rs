//! `coordinator serve`: jobs in an embedded database (redb), agent liveliness, world
//! assignment, stop conditions, and the job-control queryable the CLI talks to.
//!
//! The oldest running job gets every live agent, placed by [`coordinator::assign`]; jobs
//! live in [`coordinator::jobs::Db`].
//!
//! Stop conditions are the learner's (the one training loop checks them); the coordinator
//! records the reason the learner reports, stops a job the user stops, and keeps the job's
//! wall-clock limit as a backstop should the learner be gone.

use anyhow::{Context, Result};
use coordinator::assign::{Queued, WorldEval, assign, assignment, capped, queue, weights};
use coordinator::jobs::{AgentWork, Db, JobRecord, JobState, now_unix};
use coordinator::join::Office;
use protocol::job_reply::Body;
use protocol::net::{self, DropCounters, NetArgs, decode_sample, zenoh};
use protocol::secure::Role;
use protocol::{
    AgentInfo, AgentList, AgentReport, AgentRow, AssignmentTable, DropCount, DropCounts, Job, JobList, JobLog,
    JobReply, JobRequest, JobStatus, JobSummary, LearnerStatus, PROTOCOL_VERSION, job_request::Kind, keys,
};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// How long past its time limit a job may run before the coordinator stops it without the
/// learner's word (the learner's own clock starts when it picks the job up, and it looks at
/// it between updates, which take a minute on a camera model late in a job).
const GRACE_S: f64 = 120.0;
const TICK: Duration = Duration::from_millis(500);
/// How often the coordinator asks every agent who it is: an agent started again under its id
/// while its old connection lingers (a power or network loss) keeps the id's liveliness token
/// alive throughout, and only its new life number tells the restart.
const CENSUS_EVERY: Duration = Duration::from_secs(5);

struct Alive {
    since: Instant,
    info: Option<AgentInfo>,
}

struct State {
    jobs: BTreeMap<String, JobRecord>,
    agents: BTreeMap<String, Alive>,
    learners: BTreeMap<String, Instant>,
    /// Each world's racing-line lap (s), the adaptive schedule's yardstick, worked out once.
    line_laps: BTreeMap<String, f64>,
    /// When each owner's job last got the cluster (the queue's round-robin).
    served: BTreeMap<String, f64>,
}

/// How often the revocation list is re-sent (nodes that joined since take it).
const REVOKED_EVERY: Duration = Duration::from_secs(10);

/// Hand the credentials folder's revocation list to every node: answer queries for it, and
/// publish it when `certs revoke` changes the file (looked at every second) and every
/// [`REVOKED_EVERY`]. This node takes it first (its own links to a revoked peer close).
fn distribute_revocations(
    session: &zenoh::Session,
    dir: &std::path::Path,
    net: &NetArgs,
) -> Result<zenoh::query::Queryable<()>> {
    use protocol::revocation::{self, CRL_FILE};
    use protocol::secure::{Credentials, Role};
    let creds = Credentials::from_dir(dir, Role::Coordinator, net.own_id(Role::Coordinator).as_deref())?;
    let queryable = session
        .declare_queryable(keys::REVOKED)
        .callback(|q| {
            if let Some((_, der)) = revocation::held() {
                let _ = q.reply(keys::REVOKED, der).wait();
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    if let Some((number, _)) = revocation::held() {
        tracing::info!(number, "revocation list in force, from {}", dir.join(CRL_FILE).display());
    }
    let (s, file) = (session.clone(), dir.join(CRL_FILE));
    let modified = |f: &std::path::Path| std::fs::metadata(f).and_then(|m| m.modified()).ok();
    std::thread::Builder::new().name("revocations".into()).spawn(move || {
        let mut seen = modified(&file);
        let mut sent = Instant::now() - REVOKED_EVERY;
        loop {
            let now = modified(&file);
            let changed = now != seen;
            if changed {
                seen = now;
                match std::fs::read(&file) {
                    Ok(bytes) => match revocation::take(&creds, &bytes) {
                        Err(e) => tracing::error!("{}: {e}; the list in force stays", file.display()),
                        Ok(revocation::Taken::Installed { number, revoked, closed, .. }) => tracing::info!(
                            number,
                            revoked,
                            closed,
                            "revocation list in force, from {}; handing it to every node",
                            file.display()
                        ),
                        Ok(revocation::Taken::Unchanged) => {}
                    },
                    Err(e) => tracing::error!("{}: {e}", file.display()),
                }
            }
            if (changed || sent.elapsed() >= REVOKED_EVERY)
                && let Some((_, der)) = revocation::held()
            {
                let _ = s.put(keys::REVOKED, der).wait();
                sent = Instant::now();
            }
            std::thread::sleep(Duration::from_secs(1));
        }
    })?;
    Ok(queryable)
}

/// Options of `coordinator serve`.
pub struct ServeArgs {
    /// Network endpoints.
    pub net: NetArgs,
    /// The database file.
    pub db: std::path::PathBuf,
    /// Where the join door listens (with credentials holding the CA's key); `none`: shut;
    /// unset: port [`protocol::join::DOOR_PORT`] of every interface, if free.
    pub join_listen: Option<String>,
}

/// Open the join door when the credentials folder holds the CA's key: machines join with a
/// token (`protocol::join`), answered by [`coordinator::join::Office`]. Returns the office
/// and the address a token should carry (none when the door listens on every interface).
fn open_door(net: &NetArgs, db: &Arc<Db>, listen: &str) -> Result<Option<(Office, Option<String>)>> {
    use rustls_pki_types::pem::PemObject;
    let Some(dir) = &net.certs else { return Ok(None) };
    if !dir.join("ca.key").exists() {
        tracing::info!("no CA key in {}: this coordinator takes no joins", dir.display());
        return Ok(None);
    }
    let office = Office::new(dir, db.clone(), net.listen.clone())?;
    let creds =
        protocol::secure::Credentials::from_dir(dir, Role::Coordinator, net.own_id(Role::Coordinator).as_deref())?;
    let mut chain: Vec<rustls_pki_types::CertificateDer<'static>> =
        rustls_pki_types::CertificateDer::pem_file_iter(&creds.cert)
            .with_context(|| creds.cert.display().to_string())?
            .collect::<Result<_, _>>()
            .with_context(|| creds.cert.display().to_string())?;
    chain.extend(
        rustls_pki_types::CertificateDer::pem_file_iter(&creds.ca)
            .with_context(|| creds.ca.display().to_string())?
            .collect::<Result<Vec<_>, _>>()
            .with_context(|| creds.ca.display().to_string())?,
    );
    let key =
        rustls_pki_types::PrivateKeyDer::from_pem_file(&creds.key).with_context(|| creds.key.display().to_string())?;
    let listener =
        std::net::TcpListener::bind(listen).with_context(|| format!("--join-listen {listen}: cannot listen"))?;
    let bound = listener.local_addr()?;
    let handler = {
        let office = office.clone();
        Arc::new(move |req, peer| office.answer(req, peer))
    };
    protocol::join::serve(listener, chain, key, handler)?;
    tracing::info!(%bound, "join door open: machines join with `coordinator token create` tokens");
    let address = (!bound.ip().is_unspecified()).then(|| bound.to_string());
    Ok(Some((office, address)))
}

/// A token request (`token create|list|revoke`), answered by the join office.
fn handle_token(office: Option<&(Office, Option<String>)>, kind: Kind) -> JobReply {
    let Some((office, address)) = office else {
        return reply(
            false,
            "this coordinator takes no joins: start it with --certs DIR where DIR holds the CA's key (ca.key)".into(),
            None,
        );
    };
    match kind {
        Kind::TokenCreate(t) => {
            let address = if t.address.is_empty() { address.clone() } else { Some(t.address.clone()) };
            match office.create(&t, address) {
                Ok(token) => reply(true, token.clone(), Some(Body::Token(token))),
                Err(e) => reply(false, format!("{e:#}"), None),
            }
        }
        Kind::TokenRevoke(id) => match office.revoke(&id) {
            Ok(true) => reply(true, format!("token {id} revoked"), None),
            Ok(false) => reply(true, format!("token {id} was already revoked"), None),
            Err(e) => reply(false, format!("{e:#}"), None),
        },
        _ => match office.list() {
            Ok(l) => reply(true, coordinator::join::list_text(&l, now_unix()), Some(Body::Tokens(l))),
            Err(e) => reply(false, format!("{e:#}"), None),
        },
    }
}

/// Run the coordinator until the process is stopped.
pub fn serve(args: ServeArgs) -> Result<()> {
    let db = Arc::new(Db::open(&args.db)?);
    let jobs = db.load()?;
    for j in jobs.values().filter(|j| matches!(j.state(), JobState::Running | JobState::Stopping)) {
        tracing::info!(job = %j.id(), state = j.state().name(), "job carried over from the database");
    }
    let door = match args.join_listen.as_deref() {
        Some("none") => None,
        Some(listen) => open_door(&args.net, &db, listen)?,
        None => open_door(&args.net, &db, &format!("[::]:{}", protocol::join::DOOR_PORT)).unwrap_or_else(|e| {
            tracing::warn!("the join door stays shut: {e:#}");
            None
        }),
    };
    let session = net::open_retrying(&args.net)?;
    let _token =
        session.liveliness().declare_token(keys::COORDINATOR_ALIVE).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let state = Arc::new(Mutex::new(State {
        jobs,
        agents: BTreeMap::new(),
        learners: BTreeMap::new(),
        line_laps: BTreeMap::new(),
        served: BTreeMap::new(),
    }));
    let drops = Arc::new(DropCounters::default());

    // Control queryable.
    let (st, dbc, sess) = (state.clone(), db.clone(), session.clone());
    let drops_q = drops.clone();
    let _control = session
        .declare_queryable(keys::CONTROL)
        .callback(move |q| {
            let reply = match q.payload().map(|p| protocol::decode::<JobRequest>(&p.to_bytes())) {
                Some(Ok(JobRequest {
                    kind: Some(kind @ (Kind::TokenCreate(_) | Kind::TokenList(_) | Kind::TokenRevoke(_))),
                    ..
                })) => handle_token(door.as_ref(), kind),
                Some(Ok(req)) => handle(&st, &dbc, &sess, req),
                Some(Err(e)) => {
                    drops_q.refuse("a job request", &e);
                    reply(false, format!("bad request: {e}"), None)
                }
                None => reply(false, "empty request".into(), None),
            };
            let _ = q.reply(q.key_expr().clone(), protocol::encode(&reply)).wait();
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // Each job's document, fetched once by every learner and agent that works on it.
    let st = state.clone();
    let _specs = session
        .declare_queryable(keys::JOB_SPECS)
        .callback(move |q| {
            let Some(id) = keys::job_of(q.key_expr().as_str()) else { return };
            let doc = st.lock().ok().and_then(|s| s.jobs.get(id).map(|j| j.job().clone()));
            if let Some(job) = doc {
                let _ = q.reply(q.key_expr().clone(), protocol::encode(&job)).wait();
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _revoked = match &args.net.certs {
        Some(dir) => Some(distribute_revocations(&session, dir, &args.net)?),
        None => None,
    };
    let agents_sub = session
        .liveliness()
        .declare_subscriber(keys::AGENTS_ALIVE)
        .history(true)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let learners_sub = session
        .liveliness()
        .declare_subscriber(keys::LEARNERS_ALIVE)
        .history(true)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let status_sub = session.declare_subscriber(keys::ALL_LEARNER_STATUS).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let report_sub = session.declare_subscriber(keys::ALL_REPORTS).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    tracing::info!(db = %args.db.display(), "coordinator up");
    let mut next_census = Instant::now();
    loop {
        let tick = Instant::now();
        // Agents coming and going, and who each is: asked outside the state lock (the query
        // waits on the network), when one comes and every few seconds.
        let mut came_went = Vec::new();
        while let Ok(Some(s)) = agents_sub.try_recv() {
            came_went.push((keys::last(s.key_expr().as_str()).to_string(), s.kind()));
        }
        let census =
            (tick >= next_census || came_went.iter().any(|(_, k)| *k == zenoh::sample::SampleKind::Put)).then(|| {
                next_census = tick + CENSUS_EVERY;
                agent_census(&session, &drops)
            });
        let mut st = state.lock().expect("state lock");
        for (id, kind) in came_went {
            if kind == zenoh::sample::SampleKind::Put {
                if !st.agents.contains_key(&id) {
                    let info = census.as_ref().and_then(|c| c.get(&id).cloned());
                    for j in st.jobs.values_mut().filter(|j| j.state() == JobState::Running) {
                        j.event(format!(
                            "agent {id} joined{}",
                            info.as_ref()
                                .map(|i| format!(" ({}, {} cores, {} envs)", i.host, i.cores, i.envs))
                                .unwrap_or_default()
                        ));
                    }
                    st.agents.insert(id, Alive { since: Instant::now(), info });
                }
            } else if st.agents.remove(&id).is_some() {
                for j in st.jobs.values_mut().filter(|j| j.state() == JobState::Running) {
                    j.event(format!("agent {id} lost (liveliness dropped)"));
                }
            }
        }
        for (id, info) in census.into_iter().flatten() {
            let Some(a) = st.agents.get_mut(&id) else { continue };
            let again = a.info.as_ref().is_some_and(|old| old.life != info.life);
            a.info = Some(info);
            if again {
                a.since = Instant::now();
                for j in st.jobs.values_mut().filter(|j| j.state() == JobState::Running) {
                    j.event(format!("agent {id} started again (its liveliness held over from its last run)"));
                }
            }
        }
        while let Ok(Some(s)) = learners_sub.try_recv() {
            let id = keys::last(s.key_expr().as_str()).to_string();
            if s.kind() == zenoh::sample::SampleKind::Put {
                st.learners.insert(id, Instant::now());
            } else {
                st.learners.remove(&id);
                for j in st.jobs.values_mut().filter(|j| j.state() == JobState::Running) {
                    j.event(format!("learner {id} lost"));
                }
            }
        }
        while let Ok(Some(s)) = status_sub.try_recv() {
            if let Some(ls) = decode_sample::<LearnerStatus>(&s, &drops) {
                on_status(&mut st, &db, ls);
            }
        }
        while let Ok(Some(s)) = report_sub.try_recv() {
            let Some(r) = decode_sample::<AgentReport>(&s, &drops) else { continue };
            if r.error.is_empty() {
                on_refusals(&mut st, r, &drops);
            } else if let Some(j) = st.jobs.get_mut(&r.job_id).filter(|j| j.state() == JobState::Running) {
                j.event(format!("agent {} failed: {}", r.agent_id, r.error));
                j.set_state(JobState::Failed);
                j.stop_reason = Some(format!("agent {} failed: {}", r.agent_id, r.error));
                j.ended = Some(now_unix());
                db.save_or_log(j);
            }
        }
        schedule(&mut st, &db, &session);
        drop(st);
        std::thread::sleep(TICK.saturating_sub(tick.elapsed()));
    }
}

/// Every live agent's [`AgentInfo`] by id, each answered on its own key (a reply whose id is
/// not its key's is dropped), less the ids two processes answer for ([`census_of`]), each
/// counted as refused.
fn agent_census(session: &zenoh::Session, drops: &DropCounters) -> BTreeMap<String, AgentInfo> {
    let answers =
        net::query_keyed::<AgentInfo>(session, &keys::agent_info("*"), None, Duration::from_millis(500), drops)
            .unwrap_or_default();
    let (census, twice) = census_of(answers);
    for id in twice {
        drops.refuse(
            "an agent's info",
            &protocol::DecodeError::Invalid(format!("two processes answer as agent {id:?} (one id started twice?)")),
        );
    }
    census
}

/// The census from the answers (key, info): each agent's info by id, an answer whose id is
/// not its key's left out; and the ids answered with two life numbers at once. Those are left
/// out too: the two lives would take turns in the census and tell a restart every time.
fn census_of(answers: Vec<(String, AgentInfo)>) -> (BTreeMap<String, AgentInfo>, Vec<String>) {
    let mut census: BTreeMap<String, AgentInfo> = BTreeMap::new();
    let mut twice = Vec::new();
    for (key, info) in answers {
        if keys::agent_info(&info.agent_id) != key {
            continue;
        }
        match census.get(&info.agent_id) {
            Some(seen) if seen.life != info.life => {
                if !twice.contains(&info.agent_id) {
                    twice.push(info.agent_id.clone());
                }
            }
            _ => {
                census.insert(info.agent_id.clone(), info);
            }
        }
    }
    for id in &twice {
        census.remove(id);
    }
    (census, twice)
}

/// Agents whose refusals a job keeps.
const REFUSING_AGENTS: usize = 64;

/// An agent's report of what it refused: kept in the job's record (for `job status`) when the
/// agent works for that job; reasons cut to a bounded size.
fn on_refusals(st: &mut State, r: AgentReport, drops: &DropCounters) {
    let Some(j) = st.jobs.get_mut(&r.job_id) else { return };
    // An agent that works for the job now, or did (its counts are already here).
    let known = j.assignments.contains_key(&r.agent_id) || j.agent_refused.contains_key(&r.agent_id);
    if !known || !j.agent_refused.contains_key(&r.agent_id) && j.agent_refused.len() >= REFUSING_AGENTS {
        drops.refuse(
            "a refusal report",
            &protocol::DecodeError::Invalid(format!("a report from {:?}, which does not work for the job", r.agent_id)),
        );
        return;
    }
    let bounded = |v: Vec<DropCount>| -> Vec<DropCount> {
        v.into_iter()
            .take(16)
            .map(|d| DropCount { reason: d.reason.chars().take(200).collect(), count: d.count })
            .collect()
    };
    let (counts, hostile_peers) = (bounded(r.refused), bounded(r.hostile_peers));
    j.agent_refused.insert(r.agent_id, DropCounts { counts, hostile_peers });
}

fn on_status(st: &mut State, db: &Db, ls: LearnerStatus) {
    let Some(j) = st.jobs.get_mut(&ls.job_id) else { return };
    let first = j.learner.is_none();
    j.learner = Some(ls.clone());
    if first {
        j.event(format!("learner {} is training (policy v{})", ls.learner_id, ls.policy_version));
    }
    if !ls.stop_reason.is_empty() && j.state() == JobState::Running {
        j.event(format!("stopping: {}", ls.stop_reason));
        j.set_state(JobState::Stopping);
        j.stop_reason = Some(ls.stop_reason.clone());
    }
    if ls.finished && matches!(j.state(), JobState::Stopping | JobState::Running) {
        j.ended = Some(now_unix());
        if ls.failure.is_empty() {
            j.set_state(JobState::Finished);
            j.event(format!("learner finished: final checkpoint and best model in {}", ls.run_dir));
        } else {
            j.set_state(JobState::Failed);
            j.stop_reason = Some(ls.failure.clone());
            j.event(format!("learner failed: {}", ls.failure));
        }
    }
    db.save_or_log(j);
}

fn schedule(st: &mut State, db: &Db, session: &zenoh::Session) {
    let agents: Vec<String> = st.agents.keys().cloned().collect();
    // The backstop: a job past its time limit (plus grace) stops even without the learner;
    // its time counts from when it got the cluster.
    for j in st.jobs.values_mut().filter(|j| j.state() == JobState::Running) {
        let Some(began) = j.began else { continue };
        let elapsed_s = now_unix() - began;
        if elapsed_s >= j.job().stop().minutes * 60.0 + GRACE_S {
            let r = format!("time limit of {} min reached (no word from the learner)", j.job().stop().minutes);
            j.event(format!("stopping: {r}"));
            j.set_state(JobState::Stopping);
            j.stop_reason = Some(r);
            db.save_or_log(j);
        }
    }
    // One job at a time has the cluster (the agents and the learners): the first of the queue,
    // which a job that has begun (running, or finishing its final evaluation) heads until it
    // ends; the others wait their turn, round-robin by owner.
    let live: Vec<Queued> = st
        .jobs
        .values()
        .filter(|j| matches!(j.state(), JobState::Running | JobState::Stopping))
        .map(|j| Queued {
            id: j.id().to_string(),
            owner: j.job().owner.clone(),
            started: j.started,
            // A job from before the queue existed, or one a learner already took, has begun.
            began: j.began.is_some() || j.learner.is_some() || !j.assignments.is_empty(),
        })
        .collect();
    let order = queue(&live, &st.served);
    let active = order.first().cloned();
    for (place, id) in order.iter().enumerate() {
        let j = st.jobs.get_mut(id).expect("listed");
        let queued = place as u32;
        // A job kept from before the queue, already under way: its time ran from its start.
        if j.began.is_none() && (j.learner.is_some() || !j.assignments.is_empty()) {
            j.began = Some(j.started);
        }
        if place == 0 && j.began.is_none() {
            let now = now_unix();
            j.began = Some(now);
            st.served.insert(j.job().owner.clone(), now);
            if j.queued > 0 {
                j.event("its turn: it has the cluster".into());
            }
        }
        if j.queued != queued {
            if queued > 0 {
                j.event(format!("waiting its turn: {queued} in the queue (another job has the cluster)"));
            }
            j.queued = queued;
            db.save_or_log(j);
        }
    }
    if let Some(id) = &active {
        let j = st.jobs.get_mut(id).expect("active");
        let agents = capped(&agents, &j.assignments, j.job().agents);
        // The adaptive schedule: every agent drives every world, the weights split them.
        let plan = if j.job().adaptive {
            agents.iter().map(|a| (a.clone(), j.job().worlds.clone())).collect()
        } else {
            assign(&agents, &j.job().worlds, &j.assignments)
        };
        let mut changed = j.job().adaptive && reweigh(j, &mut st.line_laps);
        for (a, worlds) in &plan {
            if j.assignments.get(a).map(|w| &w.worlds) != Some(worlds) {
                j.generation += 1;
                let old = j.assignments.get(a).map(|w| w.worlds.join("+"));
                j.event(match old {
                    Some(o) => format!("agent {a}: {o} -> {}", worlds.join("+")),
                    None => format!("agent {a} assigned to {}", worlds.join("+")),
                });
                // The smallest offset no other agent uses spreads the environments over the worlds.
                let used: Vec<u32> = j.assignments.iter().filter(|(b, _)| *b != a).map(|(_, w)| w.offset).collect();
                let offset = (0..).find(|o| !used.contains(o)).unwrap_or(0) % worlds.len().max(1) as u32;
                j.assignments.insert(a.clone(), AgentWork { worlds: worlds.clone(), offset, generation: j.generation });
                changed = true;
            }
        }
        let gone: Vec<String> = j.assignments.keys().filter(|a| !plan.contains_key(*a)).cloned().collect();
        for a in gone {
            let w = j.assignments.remove(&a).expect("listed");
            j.event(format!("agent {a} no longer on {}", w.worlds.join("+")));
            changed = true;
        }
        if changed {
            db.save_or_log(j);
        }
    }
    // Publish the job tables of the job that has the cluster and of those finishing; a job
    // waiting its turn has none (no learner takes it before its turn).
    for j in st
        .jobs
        .values()
        .filter(|j| j.state() == JobState::Stopping || (j.state() == JobState::Running && j.queued == 0))
    {
        let mut table = AssignmentTable {
            protocol_version: PROTOCOL_VERSION,
            job_id: j.id().to_string(),
            running: j.state() == JobState::Running,
            assignments: vec![],
        };
        if Some(j.id()) == active.as_deref() {
            for (a, w) in &j.assignments {
                // The job's sim config was checked when it started; should it not parse now,
                // say so rather than send defaults.
                let asg = match assignment(j.job(), a, w, &j.weights) {
                    Ok(asg) => asg,
                    Err(e) => {
                        tracing::error!(job = %j.id(), "cannot assign {a}: {e:#}");
                        continue;
                    }
                };
                if let Err(e) = net::put(session, &keys::assignment(a), &asg) {
                    tracing::warn!("could not send {a} its assignment: {e}");
                }
                table.assignments.push(asg);
            }
        }
        if let Err(e) = net::put(session, keys::JOBS, &table) {
            tracing::warn!("could not publish the job table: {e}");
        }
    }
}

/// The adaptive schedule: the worlds' weights from the learner's last evaluation of each,
/// laps measured against each world's racing line (`line_laps` keeps them). New weights are
/// taken when one moves by 5 points or more (an agent's environments move at their episodes'
/// ends, so small changes are not worth it); true when they were.
fn reweigh(j: &mut JobRecord, line_laps: &mut BTreeMap<String, f64>) -> bool {
    let doc = j.job();
    let direction = if doc.reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward };
    // Kept by world and direction: a track's line laps differently the other way round.
    let key = |w: &str| if doc.reversed { format!("{w} reversed") } else { w.to_string() };
    for w in &doc.worlds {
        if let std::collections::btree_map::Entry::Vacant(slot) = line_laps.entry(key(w)) {
            let lap = tracks::world(w)
                .ok()
                .and_then(|world| {
                    let car = sim_agent::SimConfig::default().car;
                    sim_agent::race_line::LinePlan::new(&world.track(direction), &car, world.surface)
                        .ok()
                        .map(|p| p.lap_time)
                })
                // No line fits: the centre line at 2 m/s stands in.
                .unwrap_or_else(|| doc.tracks.iter().find(|t| &t.world == w).map_or(1.0, |t| t.length / 2.0));
            slot.insert(lap);
        }
    }
    let evals: Vec<Option<WorldEval>> = doc
        .worlds
        .iter()
        .map(|w| {
            let s = j.learner.as_ref()?.worlds.iter().find(|x| &x.world == w).filter(|x| x.evaluated)?;
            Some(WorldEval {
                progress: s.eval_progress,
                lap_time: (s.eval_lap_time > 0.0).then_some(s.eval_lap_time),
                reference: line_laps[&key(w)],
            })
        })
        .collect();
    let next = weights(&evals, doc.schedule_floor);
    let moved = j.weights.len() != next.len() || j.weights.iter().zip(&next).any(|(a, b)| (a - b).abs() >= 0.05);
    if !moved {
        return false;
    }
    let shares: Vec<String> = doc.worlds.iter().zip(&next).map(|(w, x)| format!("{w} {:.0} %", 100.0 * x)).collect();
    let why = if evals.iter().all(Option::is_some) {
        "by the last evaluation"
    } else {
        "even until every world is evaluated"
    };
    j.event(format!("schedule: {} ({why})", shares.join(", ")));
    j.weights = next;
    true
}

fn reply(ok: bool, text: String, body: Option<Body>) -> JobReply {
    JobReply { protocol_version: PROTOCOL_VERSION, ok, text, body }
}

/// A job in a line: how long it has run, what it has trained on, how well.
fn summary(j: &JobRecord) -> JobSummary {
    let l = j.learner.as_ref();
    JobSummary {
        id: j.id().to_string(),
        state: j.state,
        // Its time on the cluster: none while it waits its turn.
        minutes: j.began.map_or(0.0, |b| (j.ended.unwrap_or_else(now_unix) - b).max(0.0) / 60.0),
        episodes: l.map_or(0, |l| l.episodes),
        progress: l.map_or(0.0, |l| l.window_progress),
        worlds: j.job().worlds.clone(),
        queued: j.queued,
    }
}

/// Check a job's reward function before anything trains on it.
fn validate(doc: &Job) -> std::result::Result<(), String> {
    let result = (|| -> Result<()> {
        let name = if doc.reward_name.ends_with(".py") { doc.reward_name.as_str() } else { "reward_function.py" };
        let cfg: sim_agent::config::SimConfig = if doc.sim_config_toml.trim().is_empty() {
            Default::default()
        } else {
            toml::from_str(&doc.sim_config_toml).context("the job's sim config")?
        };
        let mut reward =
            sim_agent::RewardFn::from_source(name, &doc.reward_source)?.with_time_limit(cfg.reward_time_limit());
        let meta = policy::ModelMetadata::parse(&doc.model_metadata_json, "model_metadata.json")?;
        for w in &doc.worlds {
            let world = tracks::world(w)?;
            let track = world.track(tracks::Direction::Forward);
            sim_agent::validate::validate_reward(
                &mut reward,
                &track,
                world.surface,
                &meta.action_space,
                20,
                &cfg.race,
            )?;
        }
        Ok(())
    })();
    result.map_err(|e| format!("{e:#}"))
}

fn handle(st: &Arc<Mutex<State>>, db: &Db, _session: &zenoh::Session, req: JobRequest) -> JobReply {
    let mut st = st.lock().expect("state lock");
    match req.kind {
        // The control queryable hands these to the join office before this.
        Some(Kind::TokenCreate(_) | Kind::TokenList(_) | Kind::TokenRevoke(_)) => {
            reply(false, "token requests go to the join office".into(), None)
        }
        Some(Kind::StartJob(job)) => {
            if let Err(e) = protocol::job::check(&job, &job.id) {
                return reply(false, format!("bad job: {e}"), None);
            }
            let doc = job;
            // The very same document again is the same job: a `job start` retried after its
            // reply was lost (the job started) gets the job's answer, not "taken".
            if let Some(j) = st.jobs.get(&doc.id).filter(|j| j.job() == &doc) {
                let ok = j.state() != JobState::Failed;
                let text = format!("job {} was already started with this very spec: {:?}", doc.id, j.state());
                return reply(ok, text, Some(Body::Job(summary(j))));
            }
            if !keys::is_valid_name(&doc.id) || st.jobs.contains_key(&doc.id) {
                return reply(false, format!("job id '{}' is taken or not a valid name", doc.id), None);
            }
            let mut rec = JobRecord::start(doc);
            let ok = match validate(rec.job()) {
                Ok(()) => {
                    rec.event(format!("started: worlds {:?}, reward {}", rec.job().worlds, rec.job().reward_name));
                    true
                }
                Err(e) => {
                    rec.set_state(JobState::Failed);
                    rec.ended = Some(now_unix());
                    rec.stop_reason = Some(format!("the reward function failed validation: {e}"));
                    rec.event(format!("failed before training: the reward function failed validation:\n{e}"));
                    false
                }
            };
            if let Err(e) = db.save(&rec) {
                return reply(false, format!("could not store the job: {e:#}"), None);
            }
            let text = if ok {
                format!("job {} started", rec.id())
            } else {
                format!("job {} failed: {}", rec.id(), rec.stop_reason.clone().unwrap_or_default())
            };
            let body = Some(Body::Job(summary(&rec)));
            st.jobs.insert(rec.id().to_string(), rec);
            reply(ok, text, body)
        }
        Some(Kind::StopJobId(id)) => match st.jobs.get_mut(&id) {
            // No learner has taken it: there is no checkpoint to wait for, and none would come.
            Some(j) if j.state() == JobState::Running && j.learner.is_none() => {
                j.set_state(JobState::Failed);
                j.ended = Some(now_unix());
                j.stop_reason = Some("stopped by the user before a learner took it: no model".into());
                j.event("stopped: asked by the user before a learner took the job (no model)".into());
                db.save_or_log(j);
                reply(true, format!("job {id} stopped before a learner took it: no model"), Some(Body::Job(summary(j))))
            }
            Some(j) if j.state() == JobState::Running => {
                j.set_state(JobState::Stopping);
                j.stop_reason = Some("stopped by the user".into());
                j.event("stopping: asked by the user".into());
                db.save_or_log(j);
                reply(
                    true,
                    format!("job {id} stopping: the learner writes its final checkpoint and best model"),
                    Some(Body::Job(summary(j))),
                )
            }
            // A retried stop (its first reply lost) finds the job stopping or stopped: that is
            // what was asked, so it succeeds and says why the job stops.
            Some(j)
                if matches!(j.state(), JobState::Stopping | JobState::Finished)
                    || (j.state() == JobState::Failed
                        && j.stop_reason.as_deref().is_some_and(|r| r.starts_with("stopped by the user"))) =>
            {
                reply(
                    true,
                    format!(
                        "job {id} is already {}: {}",
                        match j.state() {
                            JobState::Stopping => "stopping",
                            JobState::Finished => "finished",
                            _ => "stopped",
                        },
                        j.stop_reason.as_deref().unwrap_or("its stop condition")
                    ),
                    Some(Body::Job(summary(j))),
                )
            }
            Some(j) => reply(false, format!("job {id} is {:?}, not running", j.state()), None),
            None => reply(false, format!("no job '{id}'"), None),
        },
        Some(Kind::Event(ev)) => match st.jobs.get_mut(&ev.job_id) {
            Some(j) if ev.text.len() <= 500 && !ev.text.chars().any(|c| c.is_control()) => {
                j.event(ev.text);
                db.save_or_log(j);
                reply(true, "recorded".into(), None)
            }
            Some(_) => reply(false, "an event is one line of at most 500 bytes".into(), None),
            None => reply(false, format!("no job '{}'", ev.job_id), None),
        },
        Some(Kind::StatusJobId(id)) => match st.jobs.get(&id) {
            Some(j) => {
                let coordinator_refused = protocol::secure::drop_counts(protocol::secure::REFUSED.reasons());
                let coordinator_hostile_peers = protocol::secure::drop_counts(protocol::secure::HOSTILE.named());
                let coordinator_live_mb = crate::ALLOCATOR.allocated() as f64 / (1024.0 * 1024.0);
                let status = JobStatus {
                    record: Some(j.clone()),
                    coordinator_refused,
                    coordinator_hostile_peers,
                    coordinator_live_mb,
                };
                reply(true, status_text(j, &st), Some(Body::Status(status)))
            }
            None => reply(false, format!("no job '{id}'"), None),
        },
        Some(Kind::List(_)) => {
            let mut text = format!(
                "{:<28} {:<9} {:>9} {:>9} {:>9}  {}\n",
                "JOB", "STATE", "MINUTES", "EPISODES", "PROGRESS", "WORLDS"
            );
            let mut jobs = vec![];
            for j in st.jobs.values() {
                let row = summary(j);
                text.push_str(&format!(
                    "{:<28} {:<9} {:>9.1} {:>9} {:>8.1}%  {}\n",
                    row.id,
                    j.state().name(),
                    row.minutes,
                    row.episodes,
                    row.progress,
                    row.worlds.join(",")
                ));
                jobs.push(row);
            }
            reply(true, text, Some(Body::Jobs(JobList { jobs })))
        }
        Some(Kind::Agents(_)) => {
            let active = st.jobs.values().find(|j| j.state() == JobState::Running);
            let mut text =
                format!("{:<28} {:<16} {:>5} {:>5} {:>9}  {}\n", "AGENT", "HOST", "CORES", "ENVS", "STEPS/S", "WORLD");
            let mut agents = vec![];
            for (id, a) in &st.agents {
                let world = active
                    .and_then(|j| j.assignments.get(id))
                    .map(|w| w.worlds.join("+"))
                    .unwrap_or_else(|| "-".into());
                let (host, cores, envs) =
                    a.info.as_ref().map(|i| (i.host.clone(), i.cores, i.envs)).unwrap_or_default();
                let steps_per_s = active
                    .and_then(|j| j.learner.as_ref())
                    .and_then(|l| l.agents.iter().find(|x| &x.agent_id == id))
                    .map_or(0.0, |x| x.steps_per_s);
                let up_s = a.since.elapsed().as_secs_f64();
                text.push_str(&format!(
                    "{id:<28} {host:<16} {cores:>5} {envs:>5} {steps_per_s:>9.0}  {world} (up {up_s:.0} s)\n"
                ));
                agents.push(AgentRow { id: id.clone(), host, cores, envs, world, steps_per_s, up_s });
            }
            reply(true, text, Some(Body::Agents(AgentList { agents })))
        }
        Some(Kind::LogsJobId(id)) => match st.jobs.get(&id) {
            Some(j) => reply(true, j.log.join("\n"), Some(Body::Log(JobLog { lines: j.log.clone(), state: j.state }))),
            None => reply(false, format!("no job '{id}'"), None),
        },
        None => reply(false, "empty request".into(), None),
    }
}

fn status_text(j: &JobRecord, st: &State) -> String {
    let mut t = String::new();
    let mins = (j.ended.unwrap_or_else(now_unix) - j.started) / 60.0;
    t.push_str(&format!("job {}: {:?}, {:.1} of {} min", j.id(), j.state(), mins, j.job().stop().minutes));
    if let Some(r) = &j.stop_reason {
        t.push_str(&format!(" ({r})"));
    }
    t.push('\n');
    let l = j.learner.clone().unwrap_or_default();
    for w in &j.job().worlds {
        let agents: Vec<&String> = j.assignments.iter().filter(|(_, x)| x.worlds.contains(w)).map(|(a, _)| a).collect();
        let ws = l.worlds.iter().find(|x| &x.world == w).cloned().unwrap_or_default();
        let share = match j.job().worlds.iter().position(|x| x == w).and_then(|i| j.weights.get(i)) {
            Some(x) if j.job().adaptive => format!(" share {:>3.0} %", 100.0 * x),
            _ => String::new(),
        };
        t.push_str(&format!(
            "  world {w:<20} agents {:<2}{share} episodes {:>6} crashed {:>5} mean progress {:>5.1} % mean reward {:>8.2} steps/s {:>7.0}  [{}]\n",
            agents.len(),
            ws.episodes,
            ws.crashes,
            ws.mean_progress,
            ws.mean_reward,
            ws.steps_per_s,
            agents.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ")
        ));
    }
    let received = l.episodes_received;
    t.push_str(&format!(
        "  experience: {} episodes simulated, {} trained on, {} dropped stale ({:.1} % of simulated)\n",
        received,
        l.episodes,
        l.dropped_stale,
        if received > 0 { 100.0 * l.dropped_stale as f64 / received as f64 } else { 0.0 }
    ));
    t.push_str(&format!(
        "  learner {}: policy v{} iteration {} episodes {} env steps {} lag ≤{} dropped: {} stale, {} duplicate, {} bad; eval progress {:.1} %\n",
        if l.learner_id.is_empty() { "-" } else { &l.learner_id },
        l.policy_version,
        l.iteration,
        l.episodes,
        l.env_steps,
        l.max_lag,
        l.dropped_stale,
        l.dropped_duplicate,
        l.dropped_bad,
        l.eval_progress
    ));
    for d in l.drops.iter().take(8) {
        t.push_str(&format!("  refused {}× : {}\n", d.count, d.reason));
    }
    if l.learners.len() > 1 {
        t.push_str(&format!(
            "  learner team: {} ({} updates made together, {} made again after a member was lost)\n",
            l.learners.join(", "),
            l.team_updates,
            l.team_failures
        ));
    }
    if !l.trend.is_empty() {
        t.push_str(&format!("  WHEN TO STOP: {}\n", l.trend));
    }
    if l.write_failures > 0 {
        t.push_str(&format!("  WRITES FAILED in the run folder: {} (last: {})\n", l.write_failures, l.write_error));
    }
    for d in l.refused.iter().take(8) {
        t.push_str(&format!("  refused at the learner {}× : {}\n", d.count, d.reason));
    }
    for (agent, c) in j.agent_refused.iter().take(8) {
        for d in c.counts.iter().take(8) {
            t.push_str(&format!("  refused at {agent} {}× : {}\n", d.count, d.reason));
        }
    }
    for (reason, count) in protocol::secure::REFUSED.reasons().into_iter().take(8) {
        t.push_str(&format!("  refused at the coordinator {count}× : {reason}\n"));
    }
    // Peers refused again and again, wherever it was.
    let mut hostile: Vec<(String, &str, u64)> = protocol::secure::HOSTILE
        .named()
        .into_iter()
        .map(|(peer, n)| (peer, "the coordinator", n))
        .chain(l.hostile_peers.iter().map(|d| (d.reason.clone(), "the learner", d.count)))
        .collect();
    for (agent, c) in &j.agent_refused {
        hostile.extend(c.hostile_peers.iter().map(|d| (d.reason.clone(), agent.as_str(), d.count)));
    }
    for (peer, at, n) in hostile.iter().take(8) {
        t.push_str(&format!("  HOSTILE PEER {peer}: {n} messages refused at {at}\n"));
    }
    t.push_str(&format!("  agents alive: {}, learners alive: {}\n", st.agents.len(), st.learners.len()));
    t.push_str("  recent events:\n");
    for line in j.log.iter().rev().take(8).rev() {
        t.push_str(&format!("    {line}\n"));
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 54: the census keeps each agent's info answered on its own key; an id two
    /// processes answer for with different lives (one id started twice) is left out and named,
    /// so that the two lives do not take turns telling a restart.
    #[test]
    fn an_id_two_processes_answer_for_is_left_out_of_the_census() {
        let info = |id: &str, life: u32| AgentInfo { agent_id: id.into(), life, ..AgentInfo::default() };
        let on_key = |i: AgentInfo| (keys::agent_info(&i.agent_id), i);
        // (answers, ids in the census, ids answered twice)
        for (answers, kept, twice) in [
            (vec![on_key(info("a", 1)), on_key(info("b", 2))], vec!["a", "b"], vec![]),
            (vec![on_key(info("a", 1)), on_key(info("a", 1))], vec!["a"], vec![]),
            (vec![on_key(info("a", 1)), on_key(info("b", 2)), on_key(info("a", 3))], vec!["b"], vec!["a"]),
            (vec![(keys::agent_info("b"), info("a", 1))], vec![], vec![]),
        ] {
            let (census, both) = census_of(answers.clone());
            assert_eq!(census.keys().map(String::as_str).collect::<Vec<_>>(), kept, "{answers:?}");
            assert_eq!(both, twice, "{answers:?}");
        }
    }
}
