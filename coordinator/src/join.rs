//! Join tokens and the coordinator's side of a join: tokens kept in the job database (only a
//! hash of each secret), and the answer to a machine's [`JoinRequest`]: the token checked and
//! used in one database transaction, a free slot of its role chosen, and a certificate signed
//! for the request's public key alone (`paddock-ROLE.ID`, client and server use, never a CA).
//!
//! The transport (the join door, the token's text, the CA pin) is `protocol::join`'s.

use crate::certs;
use crate::jobs::{Db, now_unix};
use anyhow::{Context, Result};
use protocol::secure::{CA_FILE, JOIN_ROLES, MODEL_PUB_FILE, ROSTER_FILE, Role, Roster, stem};
use protocol::{JoinReply, JoinRequest, PROTOCOL_VERSION, TokenCreate, TokenList, TokenRow};
use redb::{ReadableDatabase, ReadableTable, ReadableTableMetadata, TableDefinition};
use sha2::Digest;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use subtle::ConstantTimeEq;

/// Join tokens by id (JSON records).
const TOKENS: TableDefinition<&str, &[u8]> = TableDefinition::new("join_tokens");

/// The longest a token may live (a token is for joining a machine now, not a standing key).
pub const MAX_TTL_S: u64 = 7 * 24 * 3600;
/// The most machines one token may join.
pub const MAX_USES: u32 = 1024;
/// The longest a certificate from a token may live (the CA's own span).
pub const MAX_CERT_VALID_S: u64 = certs::YEARS as u64 * 365 * 24 * 3600;
/// Tokens kept (used, expired and revoked ones are dropped oldest first past this).
const MAX_TOKENS: usize = 4096;

/// One token as the database keeps it.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
struct Record {
    role: String,
    name: String,
    /// SHA-256 of the secret, hex.
    hash: String,
    uses: u32,
    used: u32,
    created: f64,
    expires: f64,
    cert_valid_s: u64,
    revoked: bool,
    joined: Vec<String>,
    /// SHA-256 (hex) of each joined machine's public key, beside `joined`: a machine that
    /// asks again with the same token and key (its answer was lost) gets the same grant.
    #[serde(default)]
    keys: Vec<String>,
}

impl Record {
    fn spent(&self, now: f64) -> bool {
        self.revoked || self.used >= self.uses || now >= self.expires
    }
}

/// The coordinator's join office: the credentials folder (with the CA's key) and the
/// database the tokens live in.
#[derive(Clone)]
pub struct Office {
    dir: PathBuf,
    db: Arc<Db>,
    /// The coordinator's Zenoh listen endpoints, told to each machine that joins.
    connect: Vec<String>,
}

/// A join refused: the reason the machine is told (and that is counted).
#[derive(Debug)]
struct Refused(String);

fn refused(s: impl Into<String>) -> Refused {
    Refused(s.into())
}

impl Office {
    /// The office for the credentials folder `dir` (which must hold `ca.key`).
    pub fn new(dir: &Path, db: Arc<Db>, connect: Vec<String>) -> Result<Office> {
        anyhow::ensure!(
            dir.join("ca.key").exists(),
            "{}: no CA key there; the coordinator that takes joins needs the folder `certs new` made",
            dir.join("ca.key").display()
        );
        let w = db.database().begin_write()?;
        w.open_table(TOKENS)?;
        w.commit()?;
        Ok(Office { dir: dir.to_path_buf(), db, connect })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Where `role`'s machine `id`'s certificate is kept (what `certs revoke` and `certs list`
    /// read, and what marks its slot taken).
    fn cert_path(&self, role: Role, id: &str) -> PathBuf {
        self.dir.join(format!("{}.pem", stem(role, Some(id))))
    }

    /// Make a token (`token create`) and return its text; the door's `address` goes in it.
    pub fn create(&self, req: &TokenCreate, address: Option<String>) -> Result<String> {
        let role = Role::from_name(&req.role)
            .filter(|r| JOIN_ROLES.contains(r))
            .with_context(|| format!("--role '{}': expected agent, learner or car", req.role))?;
        anyhow::ensure!(req.ttl_s > 0 && req.ttl_s <= MAX_TTL_S, "--ttl: expected 1 s to 7 days");
        anyhow::ensure!(req.uses >= 1 && req.uses <= MAX_USES, "--uses: expected 1 to {MAX_USES}");
        anyhow::ensure!(
            req.cert_valid_s >= 60 && req.cert_valid_s <= MAX_CERT_VALID_S,
            "--cert-valid: expected a minute to {} years",
            certs::YEARS
        );
        let roster = Roster::load(&self.dir)?;
        if !req.name.is_empty() {
            anyhow::ensure!(
                roster.covers(role, &req.name),
                "--name '{}': not one of the {} slots or rostered ids in {} (slots are slot-1 to slot-{}); leave \
                 it out to take the next free slot",
                req.name,
                role.name(),
                self.dir.join(ROSTER_FILE).display(),
                roster.slots(role)
            );
            anyhow::ensure!(req.uses == 1, "--name: a token for one id joins one machine (--uses 1)");
        }
        anyhow::ensure!(
            roster.slots(role) > 0 || !req.name.is_empty(),
            "{}: no {} slots; make some with `coordinator certs slots {} --{} N` and restart the nodes",
            self.dir.join(ROSTER_FILE).display(),
            role.name(),
            self.dir.display(),
            role.name()
        );
        if let Some(a) = &address {
            protocol::join::parse_address(a).map_err(anyhow::Error::msg)?;
        }
        let ca_hash = protocol::join::ca_hash_of(&self.dir).map_err(anyhow::Error::msg)?;
        let now = now_unix();
        let w = self.db.database().begin_write()?;
        let (id, secret) = {
            let mut t = w.open_table(TOKENS)?;
            // A new id (32 bits: drawn again should it be taken).
            let (id, secret) = loop {
                let (id, secret) = protocol::join::new_id_and_secret();
                if t.get(id.as_str())?.is_none() {
                    break (id, secret);
                }
            };
            let rec = Record {
                role: role.name().to_string(),
                name: req.name.clone(),
                hash: hex::encode(protocol::join::secret_hash(&secret)),
                uses: req.uses,
                used: 0,
                created: now,
                expires: now + req.ttl_s as f64,
                cert_valid_s: req.cert_valid_s,
                revoked: false,
                joined: Vec::new(),
                keys: Vec::new(),
            };
            // Keep the table bounded: past its size, drop the oldest spent tokens.
            if t.len()? as usize >= MAX_TOKENS {
                let mut all: Vec<(String, Record)> = Vec::new();
                for e in t.iter()? {
                    let (k, v) = e?;
                    if let Ok(r) = serde_json::from_slice::<Record>(v.value()) {
                        all.push((k.value().to_string(), r));
                    }
                }
                all.retain(|(_, r)| r.spent(now));
                all.sort_by(|a, b| a.1.created.total_cmp(&b.1.created));
                for (k, _) in all.iter().take(all.len().saturating_sub(MAX_TOKENS / 2)) {
                    t.remove(k.as_str())?;
                }
            }
            t.insert(id.as_str(), serde_json::to_vec(&rec)?.as_slice())?;
            (id, secret)
        };
        w.commit()?;
        tracing::info!(token = %id, role = role.name(), uses = req.uses, ttl_s = req.ttl_s, "join token made");
        Ok(protocol::join::Token { ca_hash, id, secret, address }.to_string())
    }

    /// Every token kept (`token list`), newest first, with this process's join figures.
    pub fn list(&self) -> Result<TokenList> {
        let r = self.db.database().begin_read()?;
        let t = r.open_table(TOKENS)?;
        let mut tokens = Vec::new();
        for e in t.iter()? {
            let (k, v) = e?;
            let Ok(rec) = serde_json::from_slice::<Record>(v.value()) else { continue };
            tokens.push(TokenRow {
                id: k.value().to_string(),
                role: rec.role,
                name: rec.name,
                uses: rec.uses,
                used: rec.used,
                created: rec.created,
                expires: rec.expires,
                revoked: rec.revoked,
                joined: rec.joined,
            });
        }
        tokens.sort_by(|a, b| b.created.total_cmp(&a.created));
        let j = &*protocol::join::JOINS;
        Ok(TokenList {
            tokens,
            joined: j.granted.load(std::sync::atomic::Ordering::Relaxed),
            refused: protocol::secure::drop_counts(j.refused.reasons()),
        })
    }

    /// Make a token unusable (`token revoke ID`); false when it was already.
    pub fn revoke(&self, id: &str) -> Result<bool> {
        let w = self.db.database().begin_write()?;
        let changed = {
            let mut t = w.open_table(TOKENS)?;
            let mut rec: Record = match t.get(id)? {
                Some(v) => serde_json::from_slice(v.value())?,
                None => anyhow::bail!("no join token '{id}' (see `coordinator token list`)"),
            };
            let changed = !rec.revoked;
            rec.revoked = true;
            t.insert(id, serde_json::to_vec(&rec)?.as_slice())?;
            changed
        };
        w.commit()?;
        Ok(changed)
    }

    /// Answer a join request from `peer`: the credentials, or the reason it is refused.
    pub fn answer(&self, req: JoinRequest, peer: std::net::SocketAddr) -> JoinReply {
        match self.grant(&req) {
            Ok(reply) => {
                tracing::info!(%peer, token = %req.token_id, role = %req.role, id = %reply.id, "a machine joined");
                reply
            }
            Err(Refused(why)) => protocol::join::refusal(why),
        }
    }

    fn grant(&self, req: &JoinRequest) -> Result<JoinReply, Refused> {
        let internal = |e: &dyn std::fmt::Display| {
            tracing::error!("join: {e}");
            refused("the coordinator could not issue a certificate (see its log)")
        };
        let role = Role::from_name(&req.role)
            .filter(|r| JOIN_ROLES.contains(r))
            .ok_or_else(|| refused(format!("role: '{}' cannot join (agent, learner or car)", shown(&req.role))))?;
        // The signing request first (no database work for garbage): only its key is used.
        let csr = rcgen::CertificateSigningRequestParams::from_der(&req.csr_der.clone().into()).map_err(|e| {
            refused(match e {
                rcgen::Error::UnsupportedExtension => {
                    "request: it asks for an extension Paddock does not sign (ask for nothing but the key)".to_string()
                }
                e => format!("request: not a signed PKCS#10 request ({e})"),
            })
        })?;
        let key_hash = hex::encode(sha2::Sha256::digest(rcgen::PublicKeyData::der_bytes(&csr.public_key)));
        if matches!(csr.params.is_ca, rcgen::IsCa::Ca(_)) {
            return Err(refused("request: it asks to be a CA"));
        }
        let w = self.db.database().begin_write().map_err(|e| internal(&e))?;
        let reply = {
            let mut t = w.open_table(TOKENS).map_err(|e| internal(&e))?;
            let mut rec: Record = match t.get(req.token_id.as_str()).map_err(|e| internal(&e))? {
                Some(v) => serde_json::from_slice(v.value()).map_err(|e| internal(&e))?,
                None => return Err(refused("unknown token")),
            };
            let want = hex::decode(&rec.hash).map_err(|e| internal(&e))?;
            let got = protocol::join::secret_hash(&req.secret);
            if !bool::from(got.as_slice().ct_eq(want.as_slice())) {
                return Err(refused("tampered token: its secret is wrong"));
            }
            // The same machine again (same key): its answer was lost; the same grant.
            if let Some(i) = rec.keys.iter().position(|k| *k == key_hash)
                && rec.role == role.name()
                && let Some(id) = rec.joined.get(i)
            {
                return self.again(role, id).map_err(|e| internal(&format!("{e:#}")));
            }
            let now = now_unix();
            if rec.revoked {
                return Err(refused("revoked token"));
            }
            if now >= rec.expires {
                return Err(refused("expired token"));
            }
            if rec.used >= rec.uses {
                return Err(refused(format!("used token: its {} use(s) are spent", rec.uses)));
            }
            if rec.role != role.name() {
                return Err(refused(format!(
                    "other role: the token is for the {} role, not the {}",
                    rec.role,
                    role.name()
                )));
            }
            let id = self.free_id(role, &rec.name)?;
            for cn in csr.params.distinguished_name.iter().filter(|(t, _)| **t == rcgen::DnType::CommonName) {
                let asked = match cn.1 {
                    rcgen::DnValue::Utf8String(s) => s.clone(),
                    rcgen::DnValue::PrintableString(s) => s.as_str().to_string(),
                    other => format!("{other:?}"),
                };
                if asked != role.common_name() && asked != role.common_name_of(&id) {
                    return Err(refused(format!("request: it asks for the name '{}'", shown(&asked))));
                }
            }
            // Everything the machine gets is read before anything is signed.
            let mut reply = self.gather(role, &id).map_err(|e| internal(&format!("{e:#}")))?;
            let cert =
                self.sign(role, &id, &csr.public_key, rec.cert_valid_s).map_err(|e| internal(&format!("{e:#}")))?;
            rec.used += 1;
            rec.joined.push(id.clone());
            rec.keys.push(key_hash);
            let bytes = serde_json::to_vec(&rec).map_err(|e| internal(&e))?;
            t.insert(req.token_id.as_str(), bytes.as_slice()).map_err(|e| internal(&e))?;
            reply.certificate_pem = cert;
            reply
        };
        // The certificate file is written last, and taken back unless the token's use is
        // committed: a slot is never held by a certificate no machine got.
        let pem = self.cert_path(role, &reply.id);
        let _ = std::fs::remove_file(&pem);
        if let Err(e) = certs::write_file(&pem, &reply.certificate_pem, false) {
            return Err(internal(&format!("{e:#}")));
        }
        if let Err(e) = w.commit() {
            let _ = std::fs::remove_file(&pem);
            return Err(internal(&e));
        }
        Ok(reply)
    }

    /// The id a join of `role` takes: the token's `name`, or the first slot free (never
    /// issued, or its certificate revoked or expired).
    fn free_id(&self, role: Role, name: &str) -> Result<String, Refused> {
        let internal = |e: anyhow::Error| {
            tracing::error!("join: {e:#}");
            refused("the coordinator could not read its credentials folder (see its log)")
        };
        let roster = Roster::load(&self.dir).map_err(|e| internal(e.into()))?;
        let (_, revoked) = certs::revoked_in(&self.dir).map_err(internal)?;
        let now = time::OffsetDateTime::now_utc();
        let free = |id: &str| -> Result<bool, Refused> {
            let pem = self.cert_path(role, id);
            if !pem.exists() {
                return Ok(true);
            }
            let (serial, _, until) = certs::cert_info(&pem).map_err(internal)?;
            Ok(until < now || revoked.iter().any(|(s, _)| *s == serial))
        };
        if !name.is_empty() {
            if !roster.covers(role, name) {
                return Err(refused(format!("name: '{name}' is no longer in the roster")));
            }
            return if free(name)? {
                Ok(name.to_string())
            } else {
                Err(refused(format!("taken: {name} holds a valid certificate")))
            };
        }
        for id in roster.slot_ids(role) {
            if free(&id)? {
                return Ok(id);
            }
        }
        Err(refused(format!(
            "full: all {n} {r} slots hold valid certificates; grow the roster (`coordinator certs slots DIR --{r} {m}` \
             on the coordinator's machine), give every node the new ids.toml and restart them",
            n = roster.slots(role),
            r = role.name(),
            m = (roster.slots(role) * 2).clamp(8, protocol::secure::MAX_SLOTS)
        )))
    }

    /// Sign `key` as `role`'s machine `id`: the certificate's PEM (not yet written).
    fn sign(&self, role: Role, id: &str, key: &impl rcgen::PublicKeyData, valid_s: u64) -> Result<String> {
        let issuer = certs::issuer(&self.dir)?;
        let now = time::OffsetDateTime::now_utc();
        let mut p = certs::leaf(&role.common_name_of(id))?;
        p.is_ca = rcgen::IsCa::ExplicitNoCa;
        p.not_before = now - time::Duration::minutes(5);
        p.not_after = now
            .checked_add(time::Duration::seconds(valid_s.min(MAX_CERT_VALID_S) as i64))
            .context("the certificate's expiry is out of range")?;
        Ok(p.signed_by(key, &issuer).context("signing the certificate")?.pem())
    }

    /// What a machine that joined as `role`'s `id` gets beside its certificate.
    fn gather(&self, role: Role, id: &str) -> Result<JoinReply> {
        let read =
            |n: &str| std::fs::read_to_string(self.dir.join(n)).with_context(|| self.dir.join(n).display().to_string());
        let crl = match std::fs::read_to_string(self.dir.join(protocol::revocation::CRL_FILE)) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => anyhow::bail!("{}: {e}", self.dir.join(protocol::revocation::CRL_FILE).display()),
        };
        let models_key = if role == Role::Learner {
            read(protocol::secure::MODEL_KEY_FILE).context("a learner signs models with the cluster's key")?
        } else {
            String::new()
        };
        Ok(JoinReply {
            protocol_version: PROTOCOL_VERSION,
            ok: true,
            refusal: String::new(),
            id: id.to_string(),
            certificate_pem: String::new(),
            ca_pem: read(CA_FILE)?,
            crl_pem: crl,
            models_pub: read(MODEL_PUB_FILE)?,
            roster_toml: read(ROSTER_FILE)?,
            models_key,
            connect: self.connect.clone(),
        })
    }

    /// The grant made before to `role`'s `id`, again (its certificate as written).
    fn again(&self, role: Role, id: &str) -> Result<JoinReply> {
        let pem = self.cert_path(role, id);
        let mut reply = self.gather(role, id)?;
        reply.certificate_pem = std::fs::read_to_string(&pem).with_context(|| pem.display().to_string())?;
        tracing::info!(role = role.name(), id, "a machine asked again with the same token and key: the same grant");
        Ok(reply)
    }
}

/// A value from a request as a refusal shows it: 64 characters at most, escaped.
fn shown(s: &str) -> String {
    s.chars().take(64).collect::<String>().escape_debug().to_string()
}

/// `token list`'s table.
pub fn list_text(l: &TokenList, now: f64) -> String {
    let mut out = format!("{:<10} {:<8} {:<10} {:>9} {:<20} state\n", "token", "role", "name", "used", "expires");
    for t in &l.tokens {
        let state = if t.revoked {
            "revoked"
        } else if t.used >= t.uses {
            "used"
        } else if now >= t.expires {
            "expired"
        } else {
            "active"
        };
        let expires = time::OffsetDateTime::from_unix_timestamp(t.expires as i64)
            .map(|d| format!("{:04}-{:02}-{:02} {:02}:{:02}", d.year(), d.month() as u8, d.day(), d.hour(), d.minute()))
            .unwrap_or_default();
        let name = if t.name.is_empty() { "-" } else { &t.name };
        out.push_str(&format!(
            "{:<10} {:<8} {:<10} {:>9} {:<20} {state}{}\n",
            t.id,
            t.role,
            name,
            format!("{}/{}", t.used, t.uses),
            expires,
            if t.joined.is_empty() { String::new() } else { format!(" (joined: {})", t.joined.join(", ")) }
        ));
    }
    out.push_str(&format!("joins since the coordinator started: {} granted", l.joined));
    let refused: u64 = l.refused.iter().map(|d| d.count).sum();
    if refused > 0 {
        out.push_str(&format!(
            ", {refused} refused ({})",
            l.refused.iter().map(|d| format!("{} {}", d.count, d.reason)).collect::<Vec<_>>().join(", ")
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn office(slots: u32) -> (tempfile::TempDir, Office) {
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("ca");
        certs::write(&dir, false, &[(Role::Agent, slots), (Role::Learner, 1), (Role::Car, 0)]).unwrap();
        let db = Arc::new(Db::open(&t.path().join("db.redb")).unwrap());
        let o = Office::new(&dir, db, vec!["tls/[::]:7447".into()]).unwrap();
        (t, o)
    }

    fn token(o: &Office, role: &str, ttl_s: u64, name: &str) -> protocol::join::Token {
        let req = TokenCreate {
            role: role.into(),
            ttl_s,
            uses: 1,
            name: name.into(),
            cert_valid_s: 3600,
            address: String::new(),
        };
        o.create(&req, Some("127.0.0.1:7449".into())).unwrap().parse().unwrap()
    }

    /// A signing request for a new key: common name `cn`, a CA when `ca`.
    fn csr(cn: &str, ca: bool) -> Vec<u8> {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut p = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
        p.distinguished_name = rcgen::DistinguishedName::new();
        p.distinguished_name.push(rcgen::DnType::CommonName, cn);
        if ca {
            p.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
        }
        p.serialize_request(&key).unwrap().der().to_vec()
    }

    fn ask(o: &Office, t: &protocol::join::Token, role: &str, csr_der: Vec<u8>) -> JoinReply {
        let req = JoinRequest {
            protocol_version: PROTOCOL_VERSION,
            token_id: t.id.clone(),
            secret: t.secret.clone(),
            role: role.into(),
            csr_der,
        };
        o.answer(req, "127.0.0.1:1".parse().unwrap())
    }

    fn issued(o: &Office) -> usize {
        std::fs::read_dir(o.dir())
            .unwrap()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().contains("slot-"))
            .count()
    }

    /// Issue 54: every bad join is refused with its reason and nothing is issued; a good one
    /// gets `paddock-ROLE.slot-N`, and a revoked slot is joined again with a new serial.
    #[test]
    fn a_bad_join_is_refused_with_its_reason_and_nothing_is_issued() {
        let (_t, o) = office(2);
        let agent = "paddock-agent";
        type Case = (&'static str, Box<dyn Fn(&Office) -> JoinReply>);
        let table: Vec<Case> = vec![
            (
                "unknown token",
                Box::new(|o| {
                    let mut t = token(o, "agent", 60, "");
                    t.id = "00000000".into();
                    ask(o, &t, "agent", csr(agent, false))
                }),
            ),
            (
                "tampered token",
                Box::new(|o| {
                    let mut t = token(o, "agent", 60, "");
                    t.secret = t.secret.chars().rev().collect();
                    ask(o, &t, "agent", csr(agent, false))
                }),
            ),
            ("other role", Box::new(|o| ask(o, &token(o, "learner", 60, ""), "agent", csr(agent, false)))),
            (
                "revoked token",
                Box::new(|o| {
                    let t = token(o, "agent", 60, "");
                    assert!(o.revoke(&t.id).unwrap());
                    ask(o, &t, "agent", csr(agent, false))
                }),
            ),
            (
                "expired token",
                Box::new(|o| {
                    let t = token(o, "agent", 1, "");
                    std::thread::sleep(std::time::Duration::from_millis(1100));
                    ask(o, &t, "agent", csr(agent, false))
                }),
            ),
            ("asks to be a CA", Box::new(|o| ask(o, &token(o, "agent", 60, ""), "agent", csr(agent, true)))),
            (
                "asks for the name 'paddock-coordinator'",
                Box::new(|o| ask(o, &token(o, "agent", 60, ""), "agent", csr("paddock-coordinator", false))),
            ),
            (
                "asks for the name 'paddock-agent.slot-2'",
                Box::new(|o| ask(o, &token(o, "agent", 60, ""), "agent", csr("paddock-agent.slot-2", false))),
            ),
            (
                "not a signed PKCS#10 request",
                Box::new(|o| {
                    let mut der = csr(agent, false);
                    let n = der.len();
                    der[n - 3] ^= 0x55;
                    ask(o, &token(o, "agent", 60, ""), "agent", der)
                }),
            ),
            (
                "role: 'operator' cannot join",
                Box::new(|o| ask(o, &token(o, "agent", 60, ""), "operator", csr(agent, false))),
            ),
        ];
        for (want, case) in table {
            let r = case(&o);
            assert!(!r.ok && r.refusal.contains(want), "{want}: {}", r.refusal);
            assert_eq!(issued(&o), 0, "{want}: a certificate was issued");
        }
        // A learner's join when the coordinator has no signing key: refused, no slot held.
        let models_key = o.dir().join(protocol::secure::MODEL_KEY_FILE);
        std::fs::rename(&models_key, o.dir().join("away")).unwrap();
        let l = ask(&o, &token(&o, "learner", 60, ""), "learner", csr("paddock-learner", false));
        assert!(!l.ok && !o.dir().join("learner-slot-1.pem").exists(), "{}", l.refusal);
        std::fs::rename(o.dir().join("away"), &models_key).unwrap();
        // A good join: the first free slot, for the request's key.
        let t = token(&o, "agent", 60, "");
        let der = csr(agent, false);
        let r = ask(&o, &t, "agent", der.clone());
        assert!(r.ok, "{}", r.refusal);
        assert_eq!((r.id.as_str(), r.connect.as_slice()), ("slot-1", &["tls/[::]:7447".to_string()][..]));
        assert!(r.models_key.is_empty(), "an agent gets no signing key");
        // Its answer lost, the same machine asks again: the same grant; another key is refused.
        let same = ask(&o, &t, "agent", der);
        assert_eq!((same.ok, same.id.as_str(), &same.certificate_pem), (true, "slot-1", &r.certificate_pem));
        let again = ask(&o, &t, "agent", csr(agent, false));
        assert!(again.refusal.contains("used token"), "{}", again.refusal);
        // A named slot, then the roster is full and the refusal says how to grow it.
        let r2 = ask(&o, &token(&o, "agent", 60, "slot-2"), "agent", csr(agent, false));
        assert_eq!(r2.id, "slot-2");
        let full = ask(&o, &token(&o, "agent", 60, ""), "agent", csr(agent, false));
        assert!(full.refusal.contains("full") && full.refusal.contains("certs slots"), "{}", full.refusal);
        // Revoked: the slot is free again and gets a new serial.
        let before = certs::cert_info(&o.dir().join("agent-slot-1.pem")).unwrap().0;
        certs::revoke(o.dir(), &["agent-slot-1".into()]).unwrap();
        let r3 = ask(&o, &token(&o, "agent", 60, ""), "agent", csr(agent, false));
        assert_eq!(r3.id, "slot-1", "{}", r3.refusal);
        assert_ne!(certs::cert_info(&o.dir().join("agent-slot-1.pem")).unwrap().0, before);
        // A learner gets the cluster's model-signing key.
        let l = ask(&o, &token(&o, "learner", 60, ""), "learner", csr("paddock-learner", false));
        assert!(l.ok && l.models_key.contains("PRIVATE KEY"), "{}", l.refusal);
        // Tokens for ids off the roster, or no slots, are not made.
        let bad = |role: &str, name: &str| {
            let req = TokenCreate {
                role: role.into(),
                ttl_s: 60,
                uses: 1,
                name: name.into(),
                cert_valid_s: 3600,
                address: String::new(),
            };
            o.create(&req, None).unwrap_err().to_string()
        };
        assert!(bad("agent", "lab-9").contains("'lab-9': not one of the agent slots"));
        assert!(bad("car", "").contains("no car slots"));
        assert!(bad("operator", "").contains("expected agent, learner or car"));
        let forever = TokenCreate {
            role: "agent".into(),
            ttl_s: 60,
            uses: 1,
            name: String::new(),
            cert_valid_s: u64::MAX,
            address: String::new(),
        };
        assert!(o.create(&forever, None).unwrap_err().to_string().contains("--cert-valid"));
        let list = o.list().unwrap();
        assert_eq!(list.tokens.iter().filter(|t| t.used == 1).count(), 4);
    }
}
