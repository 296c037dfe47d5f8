//! The job-control protocol's client side: one request to `coordinator serve` and its
//! reply, and what a reply says. The CLI (`coordinator job …`, `up`) and the console use
//! these, so a job started from one is the same job to the other.

use anyhow::{Context, Result, bail};
use protocol::job_reply::Body;
use protocol::net::{self, DropCounters, zenoh};
use protocol::{JobReply, JobRequest, JobState, JobStatus, PROTOCOL_VERSION, job_request::Kind, keys};
use std::time::Duration;

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
        Some(Body::Tokens(l)) => serde_json::to_value(l),
        Some(Body::Token(t)) => Ok(serde_json::Value::String(t.clone())),
        None => Ok(serde_json::Value::Null),
    };
    v.unwrap_or(serde_json::Value::Null).to_string()
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
