//! Who may connect and what each may do: the cluster's roles, their TLS credentials (signed
//! by the cluster's CA: one certificate per role, its common name `paddock-<role>`, or one per
//! machine, `paddock-<role>.<id>`), the Zenoh access-control rules that bind each role to its
//! own keys and each machine to its own id, and the count of what the network refused.
//!
//! A role-wide certificate may speak for any id of its role (any agent, say): enough for a
//! small cluster on one network. A machine's own certificate may speak only for its id, so a
//! stolen machine cannot pose as the fleet; the ids are listed in the credentials folder's
//! [`ROSTER_FILE`] (written by `coordinator certs issue`), which every node reads when it
//! opens the network: Zenoh's access rules are fixed for a session's life, so a node started
//! before an id was issued refuses that id until it restarts.
//!
//! Every node enforces the same rules on what it receives (ingress): a message from a peer
//! whose certificate says `paddock-agent` may only be one an agent sends (experience,
//! reports, its info, its liveliness token). Zenoh's own mechanisms do the work (mutual TLS in
//! `zenoh-link-tls`, the ACL interceptor); this module writes their configuration and reads
//! their refusals back out of their logs ([`RefusalLayer`]) so that `job status` can show them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

/// A role in the cluster; each holds its own certificate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Role {
    /// The job table, assignments, job control.
    Coordinator,
    /// Trains; publishes models, credit, evaluation requests and its status.
    Learner,
    /// Simulates; publishes experience, evaluation results and reports.
    Agent,
    /// Drives (the on-car agent, or the simulated car of the car-in-the-loop test).
    Car,
    /// A person at the CLI: job control, watching, the e-stop.
    Operator,
}

impl Role {
    /// Every role, in the order `certs new` writes them.
    pub const ALL: [Role; 5] = [Role::Coordinator, Role::Learner, Role::Agent, Role::Car, Role::Operator];

    /// `coordinator`, `learner`, … (the credential files' stem).
    pub fn name(self) -> &'static str {
        match self {
            Role::Coordinator => "coordinator",
            Role::Learner => "learner",
            Role::Agent => "agent",
            Role::Car => "car",
            Role::Operator => "operator",
        }
    }

    /// The certificate's common name, `paddock-<role>`: what the access rules match.
    pub fn common_name(self) -> String {
        format!("paddock-{}", self.name())
    }

    /// The role a certificate's common name names.
    pub fn from_common_name(cn: &str) -> Option<Role> {
        Role::ALL.into_iter().find(|r| r.common_name() == cn)
    }

    /// The role named `name` (`agent`, …).
    pub fn from_name(name: &str) -> Option<Role> {
        Role::ALL.into_iter().find(|r| r.name() == name)
    }

    /// One machine's common name, `paddock-<role>.<id>`.
    pub fn common_name_of(self, id: &str) -> String {
        format!("paddock-{}.{id}", self.name())
    }
}

/// The role and, for one machine's certificate, the id a common name carries
/// (`paddock-agent` → agent; `paddock-agent.lab-3` → agent `lab-3`).
pub fn parse_common_name(cn: &str) -> Option<(Role, Option<String>)> {
    if let Some(r) = Role::from_common_name(cn) {
        return Some((r, None));
    }
    let (head, id) = cn.split_once('.')?;
    let r = Role::from_common_name(head)?;
    crate::keys::is_valid_name(id).then(|| (r, Some(id.to_string())))
}

/// The list of ids holding a certificate of their own, in a credentials folder.
pub const ROSTER_FILE: &str = "ids.toml";

/// The machines' ids by role ([`ROSTER_FILE`]): `agent = ["lab-1", "lab-2"]`, and so on.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Roster {
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    coordinator: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    learner: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    agent: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    car: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    operator: Vec<String>,
    /// Slots for machines that join with a token (`slot-1`, `slot-2`, … of each role): every
    /// node's access rules cover them from its start, so a join needs no restart.
    #[serde(default, skip_serializing_if = "Slots::is_empty")]
    slots: Slots,
}

/// How many machines of each role may join with a token ([`Roster`]'s `[slots]` table).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Slots {
    #[serde(default)]
    agent: u32,
    #[serde(default)]
    learner: u32,
    #[serde(default)]
    car: u32,
}

impl Slots {
    fn is_empty(&self) -> bool {
        *self == Slots::default()
    }
}

/// The roles a machine may join as with a token.
pub const JOIN_ROLES: [Role; 3] = [Role::Agent, Role::Learner, Role::Car];

/// The slots `certs new` makes: agents, learners, cars.
pub const DEFAULT_SLOTS: [(Role, u32); 3] = [(Role::Agent, 64), (Role::Learner, 8), (Role::Car, 8)];

/// The most slots of one role (each is a subject in every node's access rules).
pub const MAX_SLOTS: u32 = 1024;

/// The id of a role's `n`-th slot (from 1).
pub fn slot_id(n: u32) -> String {
    format!("slot-{n}")
}

impl Roster {
    fn list(&self, role: Role) -> &Vec<String> {
        match role {
            Role::Coordinator => &self.coordinator,
            Role::Learner => &self.learner,
            Role::Agent => &self.agent,
            Role::Car => &self.car,
            Role::Operator => &self.operator,
        }
    }

    /// The ids of `role`.
    pub fn ids(&self, role: Role) -> &[String] {
        self.list(role)
    }

    /// Add an id (kept sorted, once).
    pub fn add(&mut self, role: Role, id: &str) {
        let l = match role {
            Role::Coordinator => &mut self.coordinator,
            Role::Learner => &mut self.learner,
            Role::Agent => &mut self.agent,
            Role::Car => &mut self.car,
            Role::Operator => &mut self.operator,
        };
        if !l.iter().any(|x| x == id) {
            l.push(id.to_string());
            l.sort();
        }
    }

    /// How many machines of `role` may join with a token (0 for roles that cannot).
    pub fn slots(&self, role: Role) -> u32 {
        match role {
            Role::Agent => self.slots.agent,
            Role::Learner => self.slots.learner,
            Role::Car => self.slots.car,
            Role::Coordinator | Role::Operator => 0,
        }
    }

    /// Set how many machines of `role` (agent, learner or car) may join with a token.
    pub fn set_slots(&mut self, role: Role, n: u32) {
        match role {
            Role::Agent => self.slots.agent = n,
            Role::Learner => self.slots.learner = n,
            Role::Car => self.slots.car = n,
            Role::Coordinator | Role::Operator => {}
        }
    }

    /// The ids of `role`'s slots, `slot-1` onwards.
    pub fn slot_ids(&self, role: Role) -> Vec<String> {
        (1..=self.slots(role)).map(slot_id).collect()
    }

    /// Every id of `role` the access rules cover: the rostered ones and the slots.
    pub fn covered(&self, role: Role) -> Vec<String> {
        let mut v = self.ids(role).to_vec();
        for s in self.slot_ids(role) {
            if !v.contains(&s) {
                v.push(s);
            }
        }
        v
    }

    /// Whether the access rules cover `role`'s machine `id`.
    pub fn covers(&self, role: Role, id: &str) -> bool {
        self.ids(role).iter().any(|x| x == id)
            || id
                .strip_prefix("slot-")
                .and_then(|n| n.parse::<u32>().ok())
                .is_some_and(|n| n >= 1 && n <= self.slots(role) && slot_id(n) == id)
    }

    /// `DIR/ids.toml`, or an empty roster when the folder has none; every id checked.
    pub fn load(dir: &Path) -> Result<Roster, CredentialError> {
        let path = dir.join(ROSTER_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Roster::default()),
            Err(e) => return Err(CredentialError { path, what: format!("cannot read it ({e})") }),
        };
        let r: Roster =
            toml::from_str(&text).map_err(|e| CredentialError { path: path.clone(), what: e.to_string() })?;
        for role in Role::ALL {
            if let Some(bad) = r.ids(role).iter().find(|id| !crate::keys::is_valid_name(id)) {
                return Err(CredentialError {
                    path,
                    what: format!("{}: id '{bad}' may hold only letters, digits, '-', '_' and '.'", role.name()),
                });
            }
            if r.slots(role) > MAX_SLOTS {
                return Err(CredentialError {
                    path,
                    what: format!("slots.{}: {} is more than {MAX_SLOTS}", role.name(), r.slots(role)),
                });
            }
        }
        Ok(r)
    }

    /// The roster as [`ROSTER_FILE`] holds it.
    pub fn to_toml(&self) -> String {
        format!(
            "# The machines that hold a certificate of their own (`coordinator certs issue`), and the\n\
             # slots machines join with a token (`coordinator token create`). Every node reads this\n\
             # when it starts: `join` writes it, and after `certs issue` copy it to every machine.\n{}",
            toml::to_string(self).unwrap_or_default()
        )
    }
}

/// The cluster CA's certificate file in a credentials folder.
pub const CA_FILE: &str = "ca.pem";

/// The learner's model-signing key in a credentials folder (ed25519, PKCS#8 PEM): only the
/// learners' machines need it.
pub const MODEL_KEY_FILE: &str = "models.key";

/// Its public half (SubjectPublicKeyInfo PEM): agents and cars given the folder trust the
/// models it signs.
pub const MODEL_PUB_FILE: &str = "models.pub";

/// One node's credentials: the CA that signs every certificate, and this node's certificate
/// (its role's, or its machine's own) and key.
#[derive(Clone, Debug)]
pub struct Credentials {
    /// The cluster CA certificate (PEM).
    pub ca: PathBuf,
    /// This node's certificate (PEM).
    pub cert: PathBuf,
    /// This node's private key (PEM).
    pub key: PathBuf,
    /// The id the certificate is bound to (`None`: the role-wide certificate).
    pub id: Option<String>,
}

/// Credentials that are missing or not PEM.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {what}")]
pub struct CredentialError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong with it.
    pub what: String,
}

/// The file stem of a certificate: `agent` (role-wide) or `agent-lab-3` (one machine's).
pub fn stem(role: Role, id: Option<&str>) -> String {
    match id {
        Some(id) => format!("{}-{id}", role.name()),
        None => role.name().to_string(),
    }
}

/// The id of the one machine certificate of `role` in `dir` (`DIR/<role>-<id>.pem`), when
/// there is exactly one: a machine given only its own files takes its id from them.
pub fn only_id(dir: &Path, role: Role) -> Option<String> {
    let prefix = format!("{}-", role.name());
    let ids: Vec<String> = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .filter_map(|n| n.strip_prefix(&prefix)?.strip_suffix(".pem").map(str::to_string))
        .filter(|id| crate::keys::is_valid_name(id) && dir.join(format!("{prefix}{id}.key")).exists())
        .collect();
    match ids.as_slice() {
        [one] => Some(one.clone()),
        _ => None,
    }
}

impl Credentials {
    /// `DIR/ca.pem` with `DIR/<role>-<id>.pem` and its key when `id` has a certificate of its
    /// own there, else the role-wide `DIR/<role>.pem` and `DIR/<role>.key` (as `coordinator
    /// certs` writes them), each checked to exist and hold PEM.
    pub fn from_dir(dir: &Path, role: Role, id: Option<&str>) -> Result<Credentials, CredentialError> {
        let own = id.filter(|id| dir.join(format!("{}.pem", stem(role, Some(id)))).exists());
        let s = stem(role, own);
        let c = Credentials {
            ca: dir.join(CA_FILE),
            cert: dir.join(format!("{s}.pem")),
            key: dir.join(format!("{s}.key")),
            id: own.map(str::to_string),
        };
        for (p, label) in [(&c.ca, "CERTIFICATE"), (&c.cert, "CERTIFICATE"), (&c.key, "PRIVATE KEY")] {
            let text = std::fs::read_to_string(p).map_err(|e| CredentialError {
                path: p.clone(),
                what: format!("cannot read it ({e}); make the cluster's credentials with `coordinator certs new DIR`"),
            })?;
            if !text.contains("-----BEGIN ") || !text.contains(label) {
                return Err(CredentialError { path: p.clone(), what: format!("expected a PEM {label}") });
            }
        }
        Ok(c)
    }
}

/// Every message kind the access rules know.
const ALL_MESSAGES: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

const ROS_SENSOR: &str = "**/sensor_fusion_pkg/sensor_msg";
const ROS_SERVO: &str = "**/deepracer_navigation_pkg/auto_drive";

fn rule(id: &str, messages: &[&str], keys: &[&str]) -> serde_json::Value {
    serde_json::json!({
        "id": id,
        "messages": messages,
        "flows": ["ingress"],
        "permission": "allow",
        "key_exprs": keys,
    })
}

/// One rule of a role's list: what it is for, the messages, the keys.
type RuleSpec = (&'static str, Vec<&'static str>, Vec<String>);

/// What `role` may send, as the node holding `id`'s certificate (`*`: the role-wide
/// certificate, which may speak for any id of its role).
fn role_rules(role: Role, id: &str) -> Vec<RuleSpec> {
    let job = |k: &str| format!("paddock/v1/job/*/{k}");
    let s = |v: &[String]| v.to_vec();
    // Every node follows the coordinator's revocation list.
    let revoked = || crate::keys::REVOKED.to_string();
    match role {
        Role::Coordinator => vec![("all", ALL_MESSAGES.to_vec(), vec!["**".into()])],
        Role::Learner => vec![
            (
                "publish",
                vec!["put"],
                s(&[
                    job("policy"),
                    job("best"),
                    job("learner"),
                    job("credit"),
                    job("eval/request/*"),
                    job("team/plan"),
                    job("team/memory"),
                    job(&format!("team/share/{id}")),
                    job(&format!("team/join/{id}")),
                ]),
            ),
            (
                "subscribe",
                vec!["declare_subscriber"],
                s(&["paddock/v1/jobs".into(), job("experience/**"), job("eval/report/*"), job("team/**"), revoked()]),
            ),
            ("ask", vec!["query"], s(&[job("spec"), revoked()])),
            ("answer", vec!["declare_queryable", "reply"], s(&[job("policy"), job("best"), job("promote")])),
            // A team watches every learner's token, and a learner that watches passes the
            // tokens it learnt on to its peers: not bound to the id.
            (
                "alive",
                vec!["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                vec!["paddock/v1/alive/learner/*".into()],
            ),
        ],
        Role::Agent => vec![
            (
                "publish",
                vec!["put"],
                s(&[
                    job(&format!("experience/{id}")),
                    job(&format!("eval/report/{id}")),
                    job(&format!("report/{id}")),
                    job(&format!("camera/{id}")),
                ]),
            ),
            (
                "subscribe",
                vec!["declare_subscriber"],
                s(&["paddock/v1/assign/*".into(), job("policy"), job("credit"), job("eval/request/*"), revoked()]),
            ),
            ("ask", vec!["query"], s(&[job("policy"), job("spec"), revoked()])),
            ("answer", vec!["declare_queryable", "reply"], vec![format!("paddock/v1/agent/{id}/info")]),
            ("alive", vec!["liveliness_token"], vec![format!("paddock/v1/alive/agent/{id}")]),
        ],
        Role::Car => vec![
            ("publish", vec!["put"], s(&[format!("paddock/v1/car/{id}/status"), ROS_SENSOR.into(), ROS_SERVO.into()])),
            (
                "subscribe",
                vec!["declare_subscriber"],
                s(&[
                    job("policy"),
                    job("best"),
                    "paddock/v1/car/*/control".into(),
                    "paddock/v1/car/*/assign".into(),
                    ROS_SENSOR.into(),
                    ROS_SERVO.into(),
                    revoked(),
                ]),
            ),
            ("ask", vec!["query"], s(&[job("policy"), job("best"), revoked()])),
            ("alive", vec!["liveliness_token"], vec![format!("paddock/v1/alive/car/{id}")]),
        ],
        Role::Operator => vec![
            ("control", vec!["query"], s(&["paddock/v1/control".into(), job("promote"), revoked()])),
            ("estop", vec!["put"], vec!["paddock/v1/car/*/control".into(), "paddock/v1/car/*/assign".into()]),
            ("watch", vec!["declare_subscriber"], vec!["paddock/v1/**".into()]),
            ("alive", vec!["declare_liveliness_subscriber", "liveliness_query"], vec!["paddock/v1/alive/**".into()]),
        ],
    }
}

/// The access-control section (`access_control` in a Zenoh config) every node runs with:
/// deny by default; per role (role-wide certificate) and per machine (each id of `roster`,
/// its own certificate) the messages it may send. Only ingress is filtered (each node judges
/// what it receives), so a node's own sends are never held back.
pub fn access_control_json(roster: &Roster) -> serde_json::Value {
    let mut rules = Vec::new();
    let mut policies = Vec::new();
    let mut subjects = Vec::new();
    let mut add = |subject: String, cn: Option<String>, list: Vec<RuleSpec>| {
        let mut ids = Vec::new();
        for (i, (what, msgs, keys)) in list.into_iter().enumerate() {
            let id = format!("{subject}-{i}-{what}");
            let keys: Vec<&str> = keys.iter().map(String::as_str).collect();
            rules.push(rule(&id, &msgs, &keys));
            ids.push(id);
        }
        // What a node sends is judged by its receiver; Zenoh filters egress too when the
        // default is deny, so every node may send anything to a known subject.
        ids.push("egress".to_string());
        policies.push(serde_json::json!({ "id": subject, "rules": ids, "subjects": [subject] }));
        subjects.push(match cn {
            Some(cn) => serde_json::json!({ "id": subject, "cert_common_names": [cn] }),
            // The car's own ROS bridge (zenoh-bridge-ros2dds on the car) holds no certificate:
            // on the loopback interface over plain TCP it may carry the camera and the servo.
            None => serde_json::json!({ "id": subject, "interfaces": ["lo"], "link_protocols": ["tcp"] }),
        });
    };
    for r in Role::ALL {
        add(r.name().to_string(), Some(r.common_name()), role_rules(r, "*"));
        for id in roster.covered(r) {
            add(format!("{}.{id}", r.name()), Some(r.common_name_of(&id)), role_rules(r, &id));
        }
    }
    add(
        "local-ros".into(),
        None,
        vec![("ros", vec!["put", "declare_subscriber"], vec![ROS_SENSOR.into(), ROS_SERVO.into()])],
    );
    let mut egress = rule("egress", &ALL_MESSAGES, &["**"]);
    egress["flows"] = serde_json::json!(["egress"]);
    rules.push(egress);
    serde_json::json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// What the network refused, by reason: connections that failed mutual TLS and messages the
/// access rules denied (each node's own count).
#[derive(Debug, Default)]
pub struct Refusals {
    total: AtomicU64,
    reasons: Mutex<BTreeMap<String, u64>>,
}

/// Distinct refusal reasons kept; the rest count as "other".
const MAX_REFUSAL_REASONS: usize = 64;

impl Refusals {
    /// Count one refusal.
    pub fn count(&self, reason: String) {
        self.total.fetch_add(1, Ordering::Relaxed);
        let mut r = self.reasons.lock().unwrap_or_else(|p| p.into_inner());
        let key = if r.len() < MAX_REFUSAL_REASONS || r.contains_key(&reason) { reason } else { "other".into() };
        *r.entry(key).or_default() += 1;
    }

    /// Refusals so far.
    pub fn total(&self) -> u64 {
        self.total.load(Ordering::Relaxed)
    }

    /// Refusals per reason, most frequent first.
    pub fn reasons(&self) -> Vec<(String, u64)> {
        let r = self.reasons.lock().unwrap_or_else(|p| p.into_inner());
        let mut v: Vec<(String, u64)> = r.iter().map(|(k, n)| (k.clone(), *n)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }
}

/// Counts per reason (or per peer) as the wire carries them.
pub fn drop_counts(v: Vec<(String, u64)>) -> Vec<crate::DropCount> {
    v.into_iter().map(|(reason, count)| crate::DropCount { reason, count }).collect()
}

/// This process's refusals (filled by [`RefusalLayer`]).
pub static REFUSED: std::sync::LazyLock<Refusals> = std::sync::LazyLock::new(Refusals::default);

/// Refusals of one peer within [`HOSTILE_WINDOW`] that make it hostile.
pub const HOSTILE_REFUSALS: u64 = 20;
/// The window [`HOSTILE_REFUSALS`] are counted in.
pub const HOSTILE_WINDOW: std::time::Duration = std::time::Duration::from_secs(60);
/// Peers tracked at once (the least recently refused is forgotten past this).
const MAX_PEERS: usize = 1024;

/// Peers whose messages this node keeps refusing: each is logged once, with its
/// certificate's name, when it passes [`HOSTILE_REFUSALS`] in a [`HOSTILE_WINDOW`], and named
/// from then on by [`HostilePeers::named`] (what `job status` shows).
#[derive(Debug, Default)]
pub struct HostilePeers {
    peers: Mutex<BTreeMap<String, PeerRecord>>,
}

#[derive(Debug)]
struct PeerRecord {
    /// Refusals in the current window, and when it began.
    window: (u64, std::time::Instant),
    /// Refusals in all.
    total: u64,
    last: std::time::Instant,
    hostile: bool,
}

impl HostilePeers {
    /// Count one refusal of `peer` (its certificate's name and Zenoh id); true when this one
    /// made it hostile (the caller logs it, once).
    pub fn count(&self, peer: &str, now: std::time::Instant) -> bool {
        let mut m = self.peers.lock().unwrap_or_else(|p| p.into_inner());
        if !m.contains_key(peer)
            && m.len() >= MAX_PEERS
            && let Some(oldest) = m.iter().min_by_key(|(_, r)| r.last).map(|(k, _)| k.clone())
        {
            m.remove(&oldest);
        }
        let r =
            m.entry(peer.to_string()).or_insert(PeerRecord { window: (0, now), total: 0, last: now, hostile: false });
        if now.duration_since(r.window.1) > HOSTILE_WINDOW {
            r.window = (0, now);
        }
        r.window.0 += 1;
        r.total += 1;
        r.last = now;
        if !r.hostile && r.window.0 >= HOSTILE_REFUSALS {
            r.hostile = true;
            return true;
        }
        false
    }

    /// The hostile peers and their refusals in all, most refused first.
    pub fn named(&self) -> Vec<(String, u64)> {
        let m = self.peers.lock().unwrap_or_else(|p| p.into_inner());
        let mut v: Vec<(String, u64)> =
            m.iter().filter(|(_, r)| r.hostile).map(|(k, r)| (k.clone(), r.total)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }
}

/// This process's hostile peers (filled by [`RefusalLayer`]).
pub static HOSTILE: std::sync::LazyLock<HostilePeers> = std::sync::LazyLock::new(HostilePeers::default);

/// The peer an access-control line names: "certificate 'CN' (zenoh id ZID)", the common
/// name remembered by Zenoh id for lines from Zenoh's cache.
pub fn peer_of(message: &str) -> Option<String> {
    let (head, _) = message.split_once(" is unauthorized to ")?;
    let head = head.trim_start_matches("Using cached result:").trim();
    let zid = head.split_once(" on ").map_or(head, |(z, _)| z).trim();
    let cn = head
        .split("CertCommonName(")
        .nth(1)
        .and_then(|t| t.split(')').next())
        .map(str::to_string)
        .or_else(|| PEER_NAMES.lock().unwrap_or_else(|p| p.into_inner()).get(zid).cloned());
    let zid: String = zid.chars().take(32).collect();
    Some(match cn {
        Some(cn) => format!("certificate '{cn}' (zenoh id {zid})"),
        None => format!("zenoh id {zid}"),
    })
}

const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";
const TLS_TARGET: &str = "zenoh_link_tls";

/// The refusal a Zenoh log line reports, if it reports one: an access-control denial (its
/// trace line "… on `<subject>` is unauthorized to Put (ingress) on `<key>`") or a connection
/// that failed the TLS handshake (zenoh-link-tls's accept warning).
pub fn refusal_reason(target: &str, message: &str) -> Option<String> {
    if target.starts_with(ACL_TARGET) {
        let (head, rest) = message.split_once(" is unauthorized to ")?;
        let (what, key) = rest.split_once(" on ")?;
        if !what.contains("(ingress)") {
            return None;
        }
        let who = who_is(head).unwrap_or_else(|| "a peer".into());
        let verb = what.trim_end_matches("(ingress)").trim().to_lowercase();
        return Some(format!("access control: {who} may not {verb} on {}", generalise(key)));
    }
    if target.starts_with(TLS_TARGET) && message.contains(". Hint: increase the system open file limit") {
        let err = message.split(". Hint:").next().unwrap_or(message);
        // One reason per kind: rustls adds the clock's reading to some (an expired certificate).
        let err = err.split(": verification time").next().unwrap_or(err);
        let err: String = err.chars().take(120).collect();
        return Some(format!("TLS: a connection refused ({err})"));
    }
    None
}

/// The roles of the peers seen in access-control lines, by Zenoh id: a line from Zenoh's
/// cache names the peer by its id only.
static PEERS: std::sync::LazyLock<Mutex<BTreeMap<String, String>>> = std::sync::LazyLock::new(Default::default);

/// The certificates' common names of the peers seen in access-control lines, by Zenoh id.
static PEER_NAMES: std::sync::LazyLock<Mutex<BTreeMap<String, String>>> = std::sync::LazyLock::new(Default::default);

/// Who the head of an access-control line ("<zid> on <subject>", or "Using cached result:
/// <zid>") names: the role of its certificate, remembered by Zenoh id.
fn who_is(head: &str) -> Option<String> {
    let head = head.trim_start_matches("Using cached result:").trim();
    let (zid, subject) = match head.split_once(" on ") {
        Some((z, s)) => (z.trim(), Some(s)),
        None => (head, None),
    };
    let mut peers = PEERS.lock().unwrap_or_else(|p| p.into_inner());
    match subject.and_then(|s| s.split("CertCommonName(").nth(1)).and_then(|t| t.split(')').next()) {
        Some(cn) => {
            let who = match parse_common_name(cn) {
                Some((r, None)) => r.name().to_string(),
                Some((r, Some(id))) => format!("{} {id}", r.name()),
                None => format!("'{cn}'"),
            };
            if peers.len() < 4096 || peers.contains_key(zid) {
                peers.insert(zid.to_string(), who.clone());
                let mut names = PEER_NAMES.lock().unwrap_or_else(|p| p.into_inner());
                if names.len() < 4096 || names.contains_key(zid) {
                    names.insert(zid.to_string(), cn.to_string());
                }
            }
            Some(who)
        }
        None => peers.get(zid).cloned(),
    }
}

/// A key with the job's id in it replaced by `*`, so that one rule is one reason.
fn generalise(key: &str) -> String {
    match key.strip_prefix("paddock/v1/job/") {
        Some(rest) => match rest.split_once('/') {
            Some((_, tail)) => format!("paddock/v1/job/*/{tail}"),
            None => key.to_string(),
        },
        None => key.to_string(),
    }
}

/// A tracing layer that counts Zenoh's refusals into [`REFUSED`]; give it a filter that
/// passes the ACL target at TRACE and zenoh-link-tls at WARN ([`init_logging`] does).
pub struct RefusalLayer;

struct MessageVisitor(String);

impl tracing::field::Visit for MessageVisitor {
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            use std::fmt::Write;
            let _ = write!(self.0, "{value:?}");
        }
    }
}

thread_local! {
    /// The key whose permissions Zenoh is computing in advance on this thread, if it is.
    static CACHING: std::cell::RefCell<Option<String>> = const { std::cell::RefCell::new(None) };
}

/// Whether an access-control log line is a real decision on a message, not one of the
/// decisions Zenoh computes in advance, for every kind of message, when a peer declares a key
/// ("caching permissions for `K`" and then one line per kind on `K`, on the same thread).
fn is_decision(message: &str) -> bool {
    if let Some(rest) = message.split_once("caching permissions for `").map(|x| x.1) {
        let key = rest.split('`').next().unwrap_or("").to_string();
        CACHING.with(|c| *c.borrow_mut() = Some(key));
        return false;
    }
    let key = message.rsplit_once(" on ").map(|x| x.1).unwrap_or("");
    CACHING.with(|c| {
        let mut c = c.borrow_mut();
        let in_block = !message.starts_with("Using cached result")
            && (message.contains(" is authorized to ") || message.contains(" is unauthorized to "))
            && c.as_deref() == Some(key);
        if !in_block {
            *c = None;
        } else if let Some((head, _)) = message.split_once(" is ") {
            who_is(head);
        }
        !in_block
    })
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for RefusalLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        let target = event.metadata().target();
        let mut v = MessageVisitor(String::new());
        event.record(&mut v);
        if target.starts_with(ACL_TARGET) && (!is_decision(&v.0) || !v.0.contains("unauthorized")) {
            return;
        }
        if let Some(r) = refusal_reason(target, &v.0) {
            if target.starts_with(ACL_TARGET)
                && let Some(peer) = peer_of(&v.0)
                && HOSTILE.count(&peer, std::time::Instant::now())
            {
                tracing::warn!(
                    "{peer} had {HOSTILE_REFUSALS} messages refused within {} s (the latest: {r}); \
                     job status names it from now on",
                    HOSTILE_WINDOW.as_secs()
                );
            }
            REFUSED.count(r);
        }
    }
}

/// Set up a role's process: its log ([`init_logging`]), and no transparent huge pages: the
/// allocator marks its arenas for them, and the kernel collapsing such a range makes the pages
/// handed back inside it resident again (a learner's memory grew by half over an hour).
pub fn init_process(default_log: &str) {
    init_logging(default_log);
    #[cfg(target_os = "linux")]
    if let Err(e) = nix::sys::prctl::set_thp_disable(true) {
        tracing::warn!("transparent huge pages left on: {e}");
    }
}

/// mimalloc's option for how long (ms) memory freed stays resident before it is handed back.
pub const PURGE_DELAY_VAR: &str = "MIMALLOC_PURGE_DELAY";

/// A long-running role's memory follows what it holds: freed memory is handed back to the
/// system `ms` milliseconds after it is freed (mimalloc's own default is 10 ms, but a purge
/// waits for the thread's next allocation after that, so a learner between updates kept up to
/// 370 MB of an update's freed buffers resident, which made its memory's slope over a soak
/// noise). mimalloc reads its options as the program loads, before `main`, and the workspace
/// writes no `unsafe` to call it: unless the variable is already set (a user's choice is kept),
/// this runs the program again in place (the same process id) with it set. Call it before any
/// thread starts; if the program cannot be run again, it goes on as it is, with a warning. A
/// program started through a loader or a tool that does not follow `exec` is best started
/// with the variable set, which skips this.
#[cfg(target_os = "linux")]
pub fn purge_freed_memory_after(ms: u32) {
    use std::os::unix::process::CommandExt;
    // mimalloc 2 still reads the option's older name too.
    if std::env::var_os(PURGE_DELAY_VAR).is_some() || std::env::var_os("MIMALLOC_RESET_DELAY").is_some() {
        return;
    }
    let mut args = std::env::args_os();
    let err = match std::env::current_exe() {
        Ok(exe) => {
            let mut again = std::process::Command::new(exe);
            if let Some(arg0) = args.next() {
                again.arg0(arg0);
            }
            again.args(args).env(PURGE_DELAY_VAR, ms.to_string()).exec()
        }
        Err(e) => e,
    };
    eprintln!(
        "warning: freed memory is handed back on the allocator's own terms: could not run again with {PURGE_DELAY_VAR}={ms} ({err})"
    );
}

/// Elsewhere the allocator keeps its own terms.
#[cfg(not(target_os = "linux"))]
pub fn purge_freed_memory_after(_ms: u32) {}

/// Set up every role's log: `RUST_LOG` (or `default`) for what is printed, zenoh-link-tls's
/// per-connection warnings folded into one line every 10 s (a peer that keeps knocking must not
/// fill the log), and [`RefusalLayer`] counting refusals.
pub fn init_logging(default: &str) {
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    use tracing_subscriber::{EnvFilter, Layer, filter::LevelFilter, filter::Targets};
    let spec = std::env::var("RUST_LOG").ok().filter(|s| !s.trim().is_empty()).unwrap_or_else(|| default.to_string());
    let printed = EnvFilter::try_new(format!("{spec},{TLS_TARGET}=error"))
        .unwrap_or_else(|_| EnvFilter::new(format!("{default},{TLS_TARGET}=error")));
    let counted = Targets::new().with_target(ACL_TARGET, LevelFilter::TRACE).with_target(TLS_TARGET, LevelFilter::WARN);
    let _ = tracing_subscriber::registry()
        .with(tracing_subscriber::fmt::layer().with_writer(std::io::stderr).with_filter(printed))
        .with(RefusalLayer.with_filter(counted))
        .try_init();
    std::thread::Builder::new()
        .name("refusal-log".into())
        .spawn(|| {
            let mut last = 0;
            loop {
                std::thread::sleep(std::time::Duration::from_secs(10));
                let now = REFUSED.total();
                if now > last {
                    let top: Vec<String> =
                        REFUSED.reasons().into_iter().take(4).map(|(r, n)| format!("{n}× {r}")).collect();
                    tracing::warn!("the network refused {} more (total {now}): {}", now - last, top.join("; "));
                    last = now;
                }
            }
        })
        .ok();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rules_are_a_valid_zenoh_access_control_section() {
        use zenoh::Wait;
        let mut c = zenoh::Config::default();
        let mut roster = Roster::default();
        roster.add(Role::Agent, "lab-1");
        roster.add(Role::Learner, "l.2");
        roster.add(Role::Car, "c1");
        roster.add(Role::Operator, "me");
        let acl = access_control_json(&roster);
        assert_eq!(acl["subjects"].as_array().unwrap().len(), Role::ALL.len() + 4 + 1);
        c.insert_json5("access_control", &acl.to_string()).expect("zenoh accepts the rules");
        c.insert_json5("listen/endpoints", "[]").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false").unwrap();
        // Zenoh checks the rules (ids, subjects, policies) when a session opens.
        zenoh::open(c).wait().expect("a session opens with the rules");
    }

    #[test]
    fn refusals_are_read_from_zenohs_log_lines() {
        let table = [
            (
                "zenoh::net::routing::interceptor::access_control",
                "a1b2 on lo+CertCommonName(paddock-agent)+Tls+a1b2 is unauthorized to Put (ingress) on paddock/v1/job/j7/policy",
                Some("access control: agent may not put on paddock/v1/job/*/policy"),
            ),
            (
                "zenoh::net::routing::interceptor::access_control",
                "Using cached result: a1b2 is unauthorized to Query (ingress) on paddock/v1/control",
                Some("access control: agent may not query on paddock/v1/control"),
            ),
            (
                "zenoh::net::routing::interceptor::access_control",
                "Using cached result: ffff is unauthorized to Query (ingress) on paddock/v1/control",
                Some("access control: a peer may not query on paddock/v1/control"),
            ),
            (
                "zenoh::net::routing::interceptor::access_control",
                "a1b2 on CertCommonName(paddock-car) is authorized to Put (ingress) on paddock/v1/car/c/status",
                None,
            ),
            (
                "zenoh::net::routing::interceptor::access_control",
                "a1b2 on x is unauthorized to Put (egress) on paddock/v1/jobs",
                None,
            ),
            (
                "zenoh_link_tls::unicast",
                "received fatal alert: CertificateRequired. Hint: increase the system open file limit.",
                Some("TLS: a connection refused (received fatal alert: CertificateRequired)"),
            ),
            (
                "zenoh_link_tls::unicast",
                "invalid peer certificate: certificate expired: verification time 1795905269 (UNIX), but certificate \
                 is not valid after 1795818869 (86400 seconds ago). Hint: increase the system open file limit.",
                Some("TLS: a connection refused (invalid peer certificate: certificate expired)"),
            ),
            ("zenoh_link_tls::unicast", "Skipping name verification of TLS server", None),
            ("zenoh::net::runtime", "anything", None),
        ];
        for (target, line, want) in table {
            assert_eq!(refusal_reason(target, line).as_deref(), want, "{line}");
        }
    }

    #[test]
    fn permissions_computed_in_advance_are_not_refusals() {
        let k = "paddock/v1/job/j/experience";
        let lines = [
            (format!("ACL (ingress): caching permissions for `{k}` ..."), false),
            (format!("z on CertCommonName(paddock-agent) is unauthorized to Query (ingress) on {k}"), false),
            (format!("z on CertCommonName(paddock-agent) is authorized to Put (ingress) on {k}"), false),
            (format!("z on CertCommonName(paddock-agent) is unauthorized to Reply (ingress) on {k}"), false),
            (format!("Using cached result: z is authorized to Put (ingress) on {k}"), true),
            (format!("z on CertCommonName(paddock-agent) is unauthorized to Query (ingress) on {k}"), true),
            (
                "z on CertCommonName(paddock-agent) is unauthorized to Put (ingress) on paddock/v1/jobs".to_string(),
                true,
            ),
        ];
        for (line, want) in lines {
            assert_eq!(is_decision(&line), want, "{line}");
        }
    }

    /// Issue 35: a peer refused again and again is named once.
    #[test]
    fn a_peer_refused_again_and_again_is_named_once() {
        let line =
            "f00d on lo+CertCommonName(paddock-agent)+Tls+f00d is unauthorized to Put (ingress) on paddock/v1/jobs";
        let peer = peer_of(line).unwrap();
        assert_eq!(peer, "certificate 'paddock-agent' (zenoh id f00d)");
        // A line from Zenoh's cache names the peer by its id alone: its certificate is remembered.
        who_is("f00d on lo+CertCommonName(paddock-agent)+Tls+f00d");
        assert_eq!(peer_of("Using cached result: f00d is unauthorized to Query (ingress) on x").unwrap(), peer);
        assert_eq!(peer_of("beef is unauthorized to Query (ingress) on x").unwrap(), "zenoh id beef");
        assert_eq!(peer_of("f00d is authorized to Put (ingress) on x"), None);
        let h = HostilePeers::default();
        let t0 = std::time::Instant::now();
        // Fewer than N in each window: never hostile.
        for window in 0..3u32 {
            let at = t0 + (HOSTILE_WINDOW + std::time::Duration::from_secs(1)) * window;
            for _ in 1..HOSTILE_REFUSALS {
                assert!(!h.count("slow", at));
            }
        }
        assert!(h.named().is_empty());
        // A burst: named once, at the N-th refusal, and counted on.
        let made: Vec<bool> = (0..HOSTILE_REFUSALS + 5).map(|_| h.count(&peer, t0)).collect();
        assert_eq!(made.iter().filter(|m| **m).count(), 1);
        assert!(made[HOSTILE_REFUSALS as usize - 1]);
        assert_eq!(h.named(), vec![(peer, HOSTILE_REFUSALS + 5)]);
    }

    #[test]
    fn credentials_name_the_missing_file() {
        let dir = std::env::temp_dir().join(format!("paddock-creds-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = Credentials::from_dir(&dir, Role::Agent, None).unwrap_err();
        assert!(e.to_string().contains("ca.pem"), "{e}");
        std::fs::write(dir.join("ca.pem"), "-----BEGIN CERTIFICATE-----\n").unwrap();
        std::fs::write(dir.join("agent.pem"), "not pem").unwrap();
        let e = Credentials::from_dir(&dir, Role::Agent, Some("lab-1")).unwrap_err();
        assert!(e.to_string().contains("agent.pem") && e.to_string().contains("PEM CERTIFICATE"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Issue 35: a machine is named by its certificate and takes its own files.
    #[test]
    fn a_machine_is_named_by_its_certificate_and_takes_its_own_files() {
        let table = [
            ("paddock-agent", Some((Role::Agent, None))),
            ("paddock-agent.lab-1", Some((Role::Agent, Some("lab-1")))),
            ("paddock-learner.l.2", Some((Role::Learner, Some("l.2")))),
            ("paddock-agent.", None),
            ("paddock-agent.a/b", None),
            ("paddock-wizard.x", None),
            ("paddock-agentx", None),
        ];
        for (cn, want) in table {
            assert_eq!(parse_common_name(cn), want.map(|(r, id)| (r, id.map(str::to_string))), "{cn}");
        }
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for f in ["ca.pem", "agent.pem", "agent-lab-1.pem"] {
            std::fs::write(d.join(f), "-----BEGIN CERTIFICATE-----\n").unwrap();
        }
        for f in ["agent.key", "agent-lab-1.key"] {
            std::fs::write(d.join(f), "-----BEGIN PRIVATE KEY-----\n").unwrap();
        }
        assert_eq!(only_id(d, Role::Agent).as_deref(), Some("lab-1"));
        assert_eq!(only_id(d, Role::Learner), None);
        let own = Credentials::from_dir(d, Role::Agent, Some("lab-1")).unwrap();
        assert_eq!(
            (own.cert.file_name().unwrap().to_str(), own.id.as_deref()),
            (Some("agent-lab-1.pem"), Some("lab-1"))
        );
        // An id without its own certificate presents the role-wide one.
        let wide = Credentials::from_dir(d, Role::Agent, Some("lab-9")).unwrap();
        assert_eq!((wide.cert.file_name().unwrap().to_str(), wide.id), (Some("agent.pem"), None));
        // The roster: missing is empty; written and read back; a bad id names the file.
        assert_eq!(Roster::load(d).unwrap(), Roster::default());
        let mut r = Roster::default();
        r.add(Role::Agent, "lab-2");
        r.add(Role::Agent, "lab-1");
        r.add(Role::Agent, "lab-2");
        std::fs::write(d.join(ROSTER_FILE), r.to_toml()).unwrap();
        assert_eq!(Roster::load(d).unwrap().ids(Role::Agent), ["lab-1", "lab-2"]);
        std::fs::write(d.join(ROSTER_FILE), "agent = [\"a/b\"]\n").unwrap();
        let e = Roster::load(d).unwrap_err().to_string();
        assert!(e.contains("ids.toml") && e.contains("a/b"), "{e}");
        std::fs::write(d.join(ROSTER_FILE), "agents = []\n").unwrap();
        assert!(Roster::load(d).unwrap_err().to_string().contains("ids.toml"));
    }

    #[test]
    fn roles_round_trip_through_their_common_names() {
        for r in Role::ALL {
            assert_eq!(Role::from_common_name(&r.common_name()), Some(r));
        }
        assert_eq!(Role::from_common_name("paddock-root"), None);
    }
}
