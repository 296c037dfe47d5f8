//! The job-control CLI (`coordinator job …`, `coordinator agents`): requests to
//! `coordinator serve` over Zenoh.

use crate::cli::{JobCommand, NetCli};
use anyhow::{Context, Result, bail};
use protocol::job_reply::Body;
use protocol::net::{self, DropCounters, NetArgs};
use protocol::{JobReply, JobRequest, JobState, JobStatus, PROTOCOL_VERSION, job_request::Kind, keys};
use std::time::Duration;

/// Network arguments for a client: default to a coordinator on this machine.
pub fn net_args(n: &NetCli, default_connect: bool) -> NetArgs {
    n.args(default_connect)
}

/// Send one request and wait for the reply.
pub fn request(session: &zenoh::Session, kind: Kind, timeout: Duration) -> Result<JobReply> {
    let req = JobRequest { protocol_version: PROTOCOL_VERSION, kind: Some(kind) };
    let drops = DropCounters::default();
    let replies = net::query::<JobReply>(session, keys::CONTROL, Some(protocol::encode(&req)), timeout, &drops)?;
    if replies.is_empty() && drops.total() > 0 {
        // Not the same as silence: something answered, and what it said was refused.
        let why: Vec<String> = drops.reasons().into_iter().map(|(r, n)| format!("{n} × {r}")).collect();
        bail!("a reply came but could not be read ({}); is the coordinator the same version?", why.join("; "));
    }
    replies.into_iter().next().context("no coordinator answered (is `coordinator serve` running and reachable?)")
}

use protocol::net::zenoh;

/// A status reply's answer.
pub fn status_of(r: &JobReply) -> Option<&JobStatus> {
    match &r.body {
        Some(Body::Status(s)) => Some(s),
        _ => None,
    }
}

/// The job's state a reply reports (status, logs, start and stop).
pub fn state_of(r: &JobReply) -> Option<JobState> {
    match &r.body {
        Some(Body::Status(s)) => s.record.as_ref().map(|j| j.state()),
        Some(Body::Log(l)) => Some(l.state()),
        Some(Body::Job(j)) => Some(j.state()),
        _ => None,
    }
}

/// The reply's answer as JSON (`--json`): the typed answer, field by field.
pub fn json_of(r: &JobReply) -> String {
    let v = match &r.body {
        Some(Body::Job(j)) => serde_json::to_value(j),
        Some(Body::Status(s)) => serde_json::to_value(s),
        Some(Body::Jobs(l)) => serde_json::to_value(&l.jobs),
        Some(Body::Agents(l)) => serde_json::to_value(&l.agents),
        Some(Body::Log(l)) => serde_json::to_value(l),
        None => Ok(serde_json::Value::Null),
    };
    v.unwrap_or(serde_json::Value::Null).to_string()
}

/// `job status --watch`: the status, redrawn every 2 s (the screen cleared first on a
/// terminal), until the job has finished or failed; a coordinator that does not answer for a
/// while (restarting) is waited for.
fn watch_status(session: &zenoh::Session, id: &str, json: bool) -> Result<i32> {
    use std::io::IsTerminal;
    let tty = std::io::stdout().is_terminal();
    let mut silent_since: Option<std::time::Instant> = None;
    loop {
        match request(session, Kind::StatusJobId(id.to_string()), Duration::from_secs(3)) {
            Ok(r) if r.ok => {
                silent_since = None;
                if tty {
                    print!("\x1b[2J\x1b[H");
                }
                println!("{}", if json { json_of(&r) } else { r.text.clone() });
                match state_of(&r) {
                    Some(JobState::Finished) => return Ok(0),
                    Some(JobState::Failed) => return Ok(1),
                    _ => {}
                }
            }
            Ok(r) => {
                println!("{}", r.text);
                return Ok(1);
            }
            Err(e) => {
                let since = *silent_since.get_or_insert_with(std::time::Instant::now);
                if since.elapsed() > Duration::from_secs(60) {
                    return Err(e.context("the coordinator has not answered for a minute"));
                }
                eprintln!("(waiting for the coordinator: {e:#})");
            }
        }
        std::thread::sleep(Duration::from_secs(2));
    }
}

/// A job id from a spec file's name and the time.
pub fn new_job_id(path: &std::path::Path, name: Option<&str>) -> String {
    let stem = name
        .map(str::to_string)
        .unwrap_or_else(|| path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "job".into()));
    let clean: String =
        stem.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '-' }).collect();
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis()).unwrap_or(0);
    format!("{clean}-{}", t % 100_000_000)
}

pub fn run(cmd: JobCommand) -> Result<i32> {
    let (net, kind, follow) = match cmd {
        JobCommand::Start { spec, id, net } => {
            let text = std::fs::read_to_string(&spec).with_context(|| format!("reading {}", spec.display()))?;
            let name = coordinator::jobspec::name_of(&text);
            let id = id.unwrap_or_else(|| new_job_id(&spec, name.as_deref()));
            let doc = coordinator::jobspec::load(&spec, &id)?;
            (net, Kind::StartJob(doc), false)
        }
        JobCommand::List { net } => (net, Kind::List(true), false),
        JobCommand::Status { id, json, watch, net } => {
            let session = net::open(&net_args(&net, true))?;
            if !watch {
                let r = request(&session, Kind::StatusJobId(id), Duration::from_secs(5))?;
                println!("{}", if json { json_of(&r) } else { r.text });
                return Ok(if r.ok { 0 } else { 1 });
            }
            return watch_status(&session, &id, json);
        }
        JobCommand::Report { id, out, net } => {
            let session = net::open(&net_args(&net, true))?;
            let r = request(&session, Kind::StatusJobId(id.clone()), Duration::from_secs(5))?;
            if !r.ok {
                anyhow::bail!("{}", r.text);
            }
            let run = status_of(&r)
                .and_then(|s| s.record.as_ref())
                .and_then(|j| j.learner.as_ref())
                .map(|l| l.run_dir.as_str())
                .filter(|d| !d.is_empty())
                .map(std::path::PathBuf::from)
                .ok_or_else(|| anyhow::anyhow!("job {id}: no learner has reported its run folder yet"))?;
            let page = crate::report::write(&run, out.as_deref(), &format!("Paddock job {id}"))?;
            println!("report       {}", page.display());
            return Ok(0);
        }
        JobCommand::Stop { id, net } => (net, Kind::StopJobId(id), false),
        JobCommand::Promote { id, version, net } => {
            // The job's learner holds the checkpoints: it answers.
            let session = net::open(&net_args(&net, true))?;
            let req = protocol::JobPromote {
                protocol_version: PROTOCOL_VERSION,
                job_id: id.clone(),
                policy_version: version,
            };
            let drops = DropCounters::default();
            // A new session learns where the queryable is over a few hundred milliseconds:
            // ask again until a learner answers or 10 s have passed.
            let deadline = std::time::Instant::now() + Duration::from_secs(10);
            let r = loop {
                let replies = net::query::<JobReply>(
                    &session,
                    &keys::promote(&id),
                    Some(protocol::encode(&req)),
                    Duration::from_secs(3),
                    &drops,
                )?;
                if let Some(r) = replies.into_iter().next() {
                    break r;
                }
                if std::time::Instant::now() > deadline {
                    bail!("no learner answered for job '{id}' (is it running?)");
                }
                std::thread::sleep(Duration::from_millis(300));
            };
            println!("{}", r.text);
            return Ok(if r.ok { 0 } else { 1 });
        }
        JobCommand::Logs { id, follow, net } => (net, Kind::LogsJobId(id), follow),
        JobCommand::Agents { net } => (net, Kind::Agents(true), false),
    };
    let session = net::open(&net_args(&net, true))?;
    let r = request(&session, kind.clone(), Duration::from_secs(10))?;
    if !follow {
        println!("{}", r.text.trim_end());
        return Ok(if r.ok { 0 } else { 1 });
    }
    // Follow: print new lines as they come until the job ends.
    let mut shown = 0;
    let mut r = r;
    loop {
        if !r.ok {
            bail!("{}", r.text);
        }
        let lines: Vec<&str> = r.text.lines().collect();
        for l in lines.iter().skip(shown) {
            println!("{l}");
        }
        shown = lines.len().max(shown);
        if matches!(state_of(&r), Some(JobState::Finished | JobState::Failed)) {
            return Ok(0);
        }
        std::thread::sleep(Duration::from_secs(1));
        r = request(&session, kind.clone(), Duration::from_secs(10))?;
    }
}
