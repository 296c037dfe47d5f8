//! The job-control CLI (`coordinator job …`, `coordinator agents`): requests to
//! `coordinator serve` over Zenoh.

use crate::cli::{JobCommand, NetCli};
use anyhow::{Context, Result, bail};
pub use coordinator::control::{json_of, new_job_id, request, state_of, status_of};
use protocol::net::{self, DropCounters, NetArgs, zenoh};
use protocol::{JobReply, JobState, PROTOCOL_VERSION, job_request::Kind, keys};
use std::time::Duration;

/// Network arguments for a client: default to a coordinator on this machine.
pub fn net_args(n: &NetCli, default_connect: bool) -> NetArgs {
    n.args(default_connect)
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

/// `coordinator token …`: asked of the running coordinator, as `job` commands are.
pub fn token(cmd: crate::cli::TokenCommand) -> Result<i32> {
    use crate::cli::TokenCommand;
    let (net, kind) = match cmd {
        TokenCommand::Create { role, ttl, uses, name, cert_valid, address, net } => (
            net,
            Kind::TokenCreate(protocol::TokenCreate {
                role,
                ttl_s: ttl.as_secs(),
                uses,
                name: name.unwrap_or_default(),
                cert_valid_s: cert_valid.as_secs(),
                address: address.unwrap_or_default(),
            }),
        ),
        TokenCommand::List { net } => (net, Kind::TokenList(true)),
        TokenCommand::Revoke { id, net } => (net, Kind::TokenRevoke(id)),
    };
    let session = net::open(&net_args(&net, true))?;
    let r = request(&session, kind, Duration::from_secs(10))?;
    if !r.ok {
        bail!("{}", r.text);
    }
    println!("{}", r.text.trim_end());
    Ok(0)
}
