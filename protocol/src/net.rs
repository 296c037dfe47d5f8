//! Zenoh sessions and typed messaging: how every role opens the network, publishes and
//! receives messages, and counts what it drops.

use crate::secure::{Credentials, Role};
use crate::{DecodeError, Versioned, decode};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
pub use zenoh;
use zenoh::Wait;

/// Where a role connects and listens (`--connect`, `--listen`, `-c`).
#[derive(Clone, Debug, Default)]
pub struct NetArgs {
    /// Endpoints to dial, e.g. `tcp/10.0.0.2:7447`.
    pub connect: Vec<String>,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`.
    pub listen: Vec<String>,
    /// A zenoh configuration file (JSON5); flags are applied on top.
    pub config: Option<PathBuf>,
    /// Network interface for multicast scouting (off when `None`).
    pub multicast: Option<String>,
    /// The cluster's credentials folder (`coordinator certs new DIR`): mutual TLS with this
    /// role's certificate, and the access rules of [`crate::secure`].
    pub certs: Option<PathBuf>,
    /// Listen beyond loopback without credentials (refused otherwise).
    pub insecure: bool,
    /// Whose certificate to present (with `certs`); an operator's when unset.
    pub role: Option<Role>,
    /// This machine's id: with `certs`, its own certificate (`DIR/<role>-<id>.pem`) is
    /// presented when the folder holds one, the role-wide one otherwise.
    pub id: Option<String>,
}

impl NetArgs {
    /// The same endpoints, presenting `role`'s certificate.
    pub fn as_role(mut self, role: Role) -> NetArgs {
        self.role = Some(role);
        self
    }

    /// The id of this machine's own certificate of `role` in the credentials folder, when it
    /// holds exactly one (what a node with no `--id` takes).
    pub fn own_id(&self, role: Role) -> Option<String> {
        self.certs.as_deref().and_then(|d| crate::secure::only_id(d, role))
    }

    /// The same endpoints, presenting the certificate of `role`'s machine `id` (the
    /// role-wide one where the folder holds none of its own).
    pub fn as_machine(mut self, role: Role, id: &str) -> NetArgs {
        self.role = Some(role);
        self.id = Some(id.to_string());
        self
    }
}

/// The network flags every role and client takes (`--connect`, `--listen`, `-c`,
/// `--multicast`), one definition for every binary.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct NetCli {
    /// Zenoh endpoint to connect to (repeatable), e.g. tcp/10.0.0.1:7447; clients default to
    /// tcp/127.0.0.1:7447.
    #[arg(long)]
    pub connect: Vec<String>,
    /// Zenoh endpoint to listen on (repeatable).
    #[arg(long)]
    pub listen: Vec<String>,
    /// Zenoh configuration file (JSON5); flags apply on top.
    #[arg(short = 'c', long = "zenoh-config")]
    pub zenoh_config: Option<PathBuf>,
    /// Multicast scouting on this interface (e.g. lo); off by default.
    #[arg(long)]
    pub multicast: Option<String>,
    /// The cluster's credentials folder (made by `coordinator certs new DIR`): connect and
    /// listen with mutual TLS as this role, under the cluster's access rules. Endpoints are
    /// then `tls/HOST:PORT`.
    #[arg(long, value_name = "DIR")]
    pub certs: Option<PathBuf>,
    /// Allow listening beyond loopback without credentials: anyone who reaches the port
    /// joins the cluster. Refused without this flag.
    #[arg(long)]
    pub insecure: bool,
}

impl NetCli {
    /// The endpoints; a client (`default_connect`) with none dials port 7447 on loopback
    /// (`tls/` with credentials, `tcp/` without).
    pub fn args(&self, default_connect: bool) -> NetArgs {
        let mut connect = self.connect.clone();
        if connect.is_empty() && default_connect && self.zenoh_config.is_none() && self.multicast.is_none() {
            let proto = if self.certs.is_some() { "tls" } else { "tcp" };
            connect.push(format!("{proto}/127.0.0.1:7447"));
        }
        NetArgs {
            connect,
            listen: self.listen.clone(),
            config: self.zenoh_config.clone(),
            multicast: self.multicast.clone(),
            certs: self.certs.clone(),
            insecure: self.insecure,
            role: None,
            id: None,
        }
    }
}

impl From<NetCli> for NetArgs {
    fn from(n: NetCli) -> NetArgs {
        n.args(false)
    }
}

/// Why the network could not be opened.
#[derive(Debug, thiserror::Error)]
#[error("zenoh: {0}")]
pub struct NetError(pub String);

fn json_list(items: &[String]) -> String {
    format!("[{}]", items.iter().map(|e| format!("{e:?}")).collect::<Vec<_>>().join(","))
}

/// Whether an endpoint's host is a loopback address (`127.0.0.0/8`, `::1`, `localhost`).
pub fn is_loopback(endpoint: &str) -> bool {
    let addr = endpoint.split_once('/').map(|(_, a)| a).unwrap_or(endpoint);
    let addr = addr.split(['#', '?']).next().unwrap_or(addr);
    let host = match addr.rsplit_once(':') {
        Some((h, _)) => h,
        None => addr,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// The listen endpoints a config holds for its mode (the value may be a list, or one list per
/// mode).
fn listen_endpoints(config: &zenoh::Config) -> Vec<String> {
    let mode = config
        .get_json("mode")
        .ok()
        .and_then(|m| serde_json::from_str::<String>(&m).ok())
        .unwrap_or_else(|| "peer".into());
    let Some(v) =
        config.get_json("listen/endpoints").ok().and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
    else {
        return Vec::new();
    };
    let list = match &v {
        serde_json::Value::Object(m) => m.get(&mode).cloned().unwrap_or_default(),
        other => other.clone(),
    };
    list.as_array().into_iter().flatten().filter_map(|e| e.as_str().map(str::to_string)).collect()
}

/// Open a peer-mode session (or whatever mode the config file says) with the given endpoints.
/// `connect/exit_on_failure` is always false: roles wait for each other.
///
/// With `certs`, every link is mutual TLS with this role's certificate and the access rules
/// of [`crate::secure`] apply; with neither `certs` nor `insecure`, listening is confined to
/// loopback (by default `tcp/127.0.0.1:0`) and a non-loopback listen endpoint is refused.
pub fn open(args: &NetArgs) -> Result<zenoh::Session, NetError> {
    let e = |x: Box<dyn std::error::Error + Send + Sync>| NetError(x.to_string());
    let mut config = match &args.config {
        Some(p) => zenoh::Config::from_file(p).map_err(|x| NetError(format!("{}: {x}", p.display())))?,
        None => {
            let mut c = zenoh::Config::default();
            c.insert_json5("mode", r#""peer""#).map_err(e)?;
            c
        }
    };
    match &args.multicast {
        Some(iface) => {
            config.insert_json5("scouting/multicast/enabled", "true").map_err(e)?;
            config.insert_json5("scouting/multicast/interface", &format!("{iface:?}")).map_err(e)?;
        }
        None if args.config.is_none() => config.insert_json5("scouting/multicast/enabled", "false").map_err(e)?,
        None => {}
    }
    if !args.connect.is_empty() {
        config.insert_json5("connect/endpoints", &json_list(&args.connect)).map_err(e)?;
    }
    // A role never exits because the other side is not up yet or went away: it keeps
    // retrying in the background (clients default to giving up).
    config.insert_json5("connect/exit_on_failure", "false").map_err(e)?;
    if !args.listen.is_empty() {
        config.insert_json5("listen/endpoints", &json_list(&args.listen)).map_err(e)?;
    } else if args.config.is_none() {
        // Zenoh's own default is every interface; ours is what the credentials allow.
        let default = if args.certs.is_some() {
            "tls/[::]:0"
        } else if args.insecure {
            "tcp/[::]:0"
        } else {
            "tcp/127.0.0.1:0"
        };
        config.insert_json5("listen/endpoints", &json_list(&[default.to_string()])).map_err(e)?;
    }
    let mut credentials = None;
    if let Some(dir) = &args.certs {
        let role = args.role.unwrap_or(Role::Operator);
        // A machine given only its own certificate (no id on the command line) presents it.
        let id = args.id.clone().or_else(|| crate::secure::only_id(dir, role));
        let c = Credentials::from_dir(dir, role, id.as_deref()).map_err(|x| NetError(x.to_string()))?;
        let roster = crate::secure::Roster::load(dir).map_err(|x| NetError(x.to_string()))?;
        match (&c.id, &id) {
            (Some(id), _) if !roster.covers(role, id) => tracing::warn!(
                role = role.name(),
                id,
                "presenting this machine's own certificate, but {} does not list it: nodes that read that \
                 file refuse this machine; copy the ids.toml `coordinator certs issue` wrote",
                dir.join(crate::secure::ROSTER_FILE).display()
            ),
            (Some(id), _) => tracing::info!(role = role.name(), id, "presenting this machine's own certificate"),
            (None, Some(id)) => tracing::info!(
                role = role.name(),
                id,
                "no certificate of this machine's own in the folder: presenting the role-wide one"
            ),
            (None, None) => {}
        }
        credentials = Some((dir.clone(), c.clone()));
        let path = |p: &std::path::Path| format!("{:?}", p.display().to_string());
        let tls = [
            ("root_ca_certificate", path(&c.ca)),
            ("listen_certificate", path(&c.cert)),
            ("listen_private_key", path(&c.key)),
            ("connect_certificate", path(&c.cert)),
            ("connect_private_key", path(&c.key)),
            // Certificates name roles, not hosts: the CA's signature and the role are checked.
            ("verify_name_on_connect", "false".into()),
            ("enable_mtls", "true".into()),
            // A link ends when the peer's certificate expires (a new handshake refuses it).
            ("close_link_on_expiration", "true".into()),
        ];
        for (k, v) in tls {
            config.insert_json5(&format!("transport/link/tls/{k}"), &v).map_err(e)?;
        }
        config.insert_json5("access_control", &crate::secure::access_control_json(&roster).to_string()).map_err(e)?;
    }
    if !args.insecure {
        let mtls =
            args.certs.is_some() || config.get_json("transport/link/tls/enable_mtls").is_ok_and(|v| v.trim() == "true");
        for ep in listen_endpoints(&config) {
            let secured = mtls && ep.starts_with("tls/");
            if !is_loopback(&ep) && !secured {
                return Err(NetError(format!(
                    "refusing to listen on {ep} without credentials: anyone who reaches it would join the \
                     cluster. Pass --certs DIR (made by `coordinator certs new DIR`) with a tls/ endpoint, \
                     listen on 127.0.0.1, or pass --insecure"
                )));
            }
        }
    }
    let session = zenoh::open(config).wait().map_err(e)?;
    if let Some((dir, c)) = credentials {
        crate::revocation::follow(&session, &dir, &c).map_err(|e| NetError(e.to_string()))?;
    }
    Ok(session)
}

/// [`open`], retried every second while the endpoints to connect to are not up yet (a
/// client-mode session refuses to open without its router); other errors return at once.
pub fn open_retrying(args: &NetArgs) -> Result<zenoh::Session, NetError> {
    let mut warned = false;
    loop {
        match open(args) {
            Err(e) if e.0.contains("Unable to connect") => {
                if !warned {
                    tracing::warn!("waiting for {:?} to come up: {e}", args.connect);
                    warned = true;
                }
                std::thread::sleep(std::time::Duration::from_secs(1));
            }
            other => return other,
        }
    }
}

/// Counts of messages dropped on receipt, by reason, and a log that a flood cannot fill.
#[derive(Debug, Default)]
pub struct DropCounters {
    /// Did not decode.
    pub malformed: AtomicU64,
    /// Over the size limit.
    pub oversized: AtomicU64,
    /// Another protocol version.
    pub version: AtomicU64,
    /// Decoded, but did not fit the job (ids, sizes, action indices, ranges, worlds).
    pub invalid: AtomicU64,
    /// Counts per reason (the error's text without its numbers and quoted names, so that one
    /// check is one reason), at most [`MAX_REASONS`] of them.
    reasons: Mutex<BTreeMap<String, u64>>,
    gate: Mutex<LogGate>,
}

/// Distinct drop reasons kept; the rest are counted under "other".
pub const MAX_REASONS: usize = 64;
/// Drops logged per [`LOG_WINDOW`]; the rest are summed up in one line when it ends.
pub const LOG_BURST: u32 = 10;
/// The window of the drop log's rate limit.
pub const LOG_WINDOW: Duration = Duration::from_secs(10);

#[derive(Debug, Default)]
struct LogGate {
    since: Option<Instant>,
    logged: u32,
    silenced: u64,
}

/// The reason of a drop: its error's text with numbers and quoted strings taken out.
pub fn reason(e: &DecodeError) -> String {
    let text = match e {
        DecodeError::TooLarge(_) => return "over the size limit".into(),
        DecodeError::Version(_) => return "another protocol version".into(),
        DecodeError::Malformed(_) => return "malformed".into(),
        DecodeError::Invalid(m) => m,
    };
    let mut out = String::with_capacity(text.len().min(120));
    let mut quoted = false;
    for c in text.chars().take(200) {
        match c {
            '"' => {
                quoted = !quoted;
                if quoted {
                    out.push('…');
                }
            }
            _ if quoted => {}
            '0'..='9' | '.' | '-' | '+' | 'e' if out.ends_with('#') => {}
            '0'..='9' => out.push('#'),
            _ => out.push(c),
        }
    }
    out
}

impl DropCounters {
    /// Total dropped.
    pub fn total(&self) -> u64 {
        self.malformed.load(Ordering::Relaxed)
            + self.oversized.load(Ordering::Relaxed)
            + self.version.load(Ordering::Relaxed)
            + self.invalid.load(Ordering::Relaxed)
    }

    /// Count one drop (and log it, within the rate limit).
    pub fn count(&self, e: &DecodeError) {
        self.refuse("a message", e);
    }

    /// Count one drop of `what` and log it, at most [`LOG_BURST`] lines per [`LOG_WINDOW`].
    pub fn refuse(&self, what: &str, e: &DecodeError) {
        let c = match e {
            DecodeError::TooLarge(_) => &self.oversized,
            DecodeError::Version(_) => &self.version,
            DecodeError::Malformed(_) => &self.malformed,
            DecodeError::Invalid(_) => &self.invalid,
        };
        c.fetch_add(1, Ordering::Relaxed);
        {
            let mut r = self.reasons.lock().unwrap_or_else(|p| p.into_inner());
            let key = reason(e);
            let key = if r.len() < MAX_REASONS || r.contains_key(&key) { key } else { "other".into() };
            *r.entry(key).or_default() += 1;
        }
        let mut g = self.gate.lock().unwrap_or_else(|p| p.into_inner());
        let now = Instant::now();
        if g.since.is_none_or(|t| now.duration_since(t) >= LOG_WINDOW) {
            if g.silenced > 0 {
                tracing::warn!("{} more dropped messages were not logged (the log is rate-limited)", g.silenced);
            }
            *g = LogGate { since: Some(now), logged: 0, silenced: 0 };
        }
        if g.logged < LOG_BURST {
            g.logged += 1;
            let text = e.to_string();
            let text: String = text.chars().take(300).collect();
            tracing::warn!("dropped {what}: {text}");
        } else {
            g.silenced += 1;
        }
    }

    /// The drops so far per reason, most frequent first.
    pub fn reasons(&self) -> Vec<(String, u64)> {
        let r = self.reasons.lock().unwrap_or_else(|p| p.into_inner());
        let mut v: Vec<(String, u64)> = r.iter().map(|(k, n)| (k.clone(), *n)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }
}

/// Decode a sample's payload as `M`; a bad one is counted, logged and `None`.
pub fn decode_sample<M: Versioned>(sample: &zenoh::sample::Sample, drops: &DropCounters) -> Option<M> {
    let bytes = sample.payload().to_bytes();
    match decode::<M>(&bytes) {
        Ok(m) => Some(m),
        Err(e) => {
            drops.refuse(&format!("a message on {} ({} bytes)", sample.key_expr(), bytes.len()), &e);
            None
        }
    }
}

/// Put an encoded message on `key`, blocking under congestion (nothing lost).
pub fn put<M: prost::Message>(session: &zenoh::Session, key: &str, m: &M) -> Result<(), NetError> {
    session
        .put(key, crate::encode(m))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| NetError(e.to_string()))
}

/// Query `key` with an optional request message; return the decoded replies (bad ones dropped).
pub fn query<M: Versioned>(
    session: &zenoh::Session,
    key: &str,
    request: Option<Vec<u8>>,
    timeout: std::time::Duration,
    drops: &DropCounters,
) -> Result<Vec<M>, NetError> {
    Ok(query_keyed(session, key, request, timeout, drops)?.into_iter().map(|(_, m)| m).collect())
}

/// [`query`], each reply with the key it came on (a query on a wildcard: who answered).
pub fn query_keyed<M: Versioned>(
    session: &zenoh::Session,
    key: &str,
    request: Option<Vec<u8>>,
    timeout: std::time::Duration,
    drops: &DropCounters,
) -> Result<Vec<(String, M)>, NetError> {
    let mut get = session.get(key).timeout(timeout);
    if let Some(r) = request {
        get = get.payload(r);
    }
    let replies = get.wait().map_err(|e| NetError(e.to_string()))?;
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result()
            && let Some(m) = decode_sample::<M>(sample, drops)
        {
            out.push((sample.key_expr().as_str().to_string(), m));
        }
    }
    Ok(out)
}

/// A subscriber whose samples wait in a queue until taken.
pub type Sub = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// Subscribe to `key`.
pub fn subscribe(session: &zenoh::Session, key: &str) -> Result<Sub, NetError> {
    session.declare_subscriber(key.to_string()).wait().map_err(|e| NetError(e.to_string()))
}

/// The next message already received on `sub` that decodes as `M`, with its key; the ones
/// that do not decode are counted and skipped.
pub fn try_next<M: Versioned>(sub: &Sub, drops: &DropCounters) -> Option<(String, M)> {
    while let Ok(Some(s)) = sub.try_recv() {
        if let Some(m) = decode_sample::<M>(&s, drops) {
            return Some((s.key_expr().as_str().to_string(), m));
        }
    }
    None
}

/// The ids (last key chunk) of the liveliness tokens alive under `key` (e.g. every learner).
pub fn alive(session: &zenoh::Session, key: &str, timeout: std::time::Duration) -> Result<Vec<String>, NetError> {
    let replies =
        session.liveliness().get(key.to_string()).timeout(timeout).wait().map_err(|e| NetError(e.to_string()))?;
    let mut ids = Vec::new();
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result() {
            ids.push(crate::keys::last(sample.key_expr().as_str()).to_string());
        }
    }
    ids.sort();
    ids.dedup();
    Ok(ids)
}
