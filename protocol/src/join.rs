//! Joining the cluster with one command: the join token's text, the CA pin, and the join
//! door, a TLS link (not Zenoh: the machine holds no certificate yet) over which a machine
//! sends one [`JoinRequest`] and gets one [`JoinReply`].
//!
//! As `kubeadm join` does, the token carries a SHA-256 hash of the CA's public key. The
//! machine makes its key itself, connects, and accepts the door only if the certificate it
//! presents chains to a CA whose key has that hash and names the coordinator: only then does
//! it send the token's secret and its signing request. A forged door (a scouted answer, a
//! wrong address) learns nothing. The coordinator keeps only a hash of the secret
//! (`coordinator::tokens`) and signs nothing but the request's public key.
//!
//! With no address in the token, [`find_doors`] asks Zenoh's multicast scouting for the
//! nodes on the local network and tries the door's port on each.

use crate::secure::{CA_FILE, MODEL_PUB_FILE, ROSTER_FILE, Role, Roster, stem};
use crate::{JoinReply, JoinRequest, PROTOCOL_VERSION};
use prost::Message;
use sha2::Digest;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// The join door's port when none is given.
pub const DOOR_PORT: u16 = 7449;
/// The largest request the door reads.
pub const MAX_FRAME: usize = 64 * 1024;
/// The largest answer a machine reads (the revocation list travels in it).
pub const MAX_REPLY: usize = 4 * 1024 * 1024;
/// How long a machine waits for its join, from the TCP connection to the answer.
pub const JOIN_TIMEOUT: Duration = Duration::from_secs(30);
/// How long the door waits for a handshake and a request (the answer is then always made).
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// Joins the door handles at once; more are refused at once ("busy").
pub const MAX_IN_FLIGHT: usize = 16;
/// Joins one address may have in flight at the door.
pub const MAX_PER_PEER: usize = 4;
/// Join requests per second the door takes in all; past this each is refused unread.
pub const MAX_PER_SECOND: u32 = 20;

/// Why a join failed, on the machine's side.
#[derive(Debug, thiserror::Error)]
pub enum JoinError {
    /// The token's text is not a token.
    #[error("the token: {0}")]
    Token(String),
    /// No door answered, or none passed the CA check.
    #[error("{0}")]
    Door(String),
    /// The coordinator refused, with its reason.
    #[error("the coordinator refused the join: {0}")]
    Refused(String),
    /// The command was given something it cannot use.
    #[error("{0}")]
    Usage(String),
    /// A file could not be written (nothing else is left behind).
    #[error("{path}: {what}")]
    File {
        /// The file.
        path: PathBuf,
        /// What failed.
        what: String,
    },
}

/// A join token: the CA's public-key hash, the token's id and secret, and where the door is.
/// Its `Debug` leaves the secret out.
#[derive(Clone, PartialEq, Eq)]
pub struct Token {
    /// SHA-256 of the CA certificate's SubjectPublicKeyInfo.
    pub ca_hash: [u8; 32],
    /// The token's id (8 hex digits): what `token list` and `token revoke` name.
    pub id: String,
    /// Its secret (32 hex digits); the coordinator keeps only its hash.
    pub secret: String,
    /// The door's `HOST:PORT`, when the token carries it.
    pub address: Option<String>,
}

/// The token text's prefix (and version).
const TOKEN_PREFIX: &str = "P1";

fn is_hex(s: &str, len: usize) -> bool {
    s.len() == len && s.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Token").field("id", &self.id).field("address", &self.address).finish_non_exhaustive()
    }
}

impl std::fmt::Display for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{TOKEN_PREFIX}-{}-{}-{}", hex::encode(self.ca_hash), self.id, self.secret)?;
        if let Some(a) = &self.address {
            write!(f, "@{a}")?;
        }
        Ok(())
    }
}

impl std::str::FromStr for Token {
    type Err = JoinError;

    fn from_str(text: &str) -> Result<Token, JoinError> {
        let bad = |what: &str| {
            JoinError::Token(format!(
                "{what}; expected {TOKEN_PREFIX}-<CA hash, 64 hex digits>-<id, 8 hex digits>-<secret, 32 hex \
                 digits>[@HOST:PORT], as `coordinator token create` prints it"
            ))
        };
        let text = text.trim();
        let (body, address) = match text.split_once('@') {
            Some((b, a)) => (b, Some(a)),
            None => (text, None),
        };
        let parts: Vec<&str> = body.split('-').collect();
        let [prefix, hash, id, secret] = parts.as_slice() else { return Err(bad("not four parts")) };
        if *prefix != TOKEN_PREFIX {
            return Err(bad(&format!("it begins '{prefix}'")));
        }
        if !is_hex(hash, 64) {
            return Err(bad("the CA hash is not 64 lowercase hex digits"));
        }
        if !is_hex(id, 8) {
            return Err(bad("the id is not 8 lowercase hex digits"));
        }
        if !is_hex(secret, 32) {
            return Err(bad("the secret is not 32 lowercase hex digits"));
        }
        let address = match address {
            Some(a) => {
                parse_address(a).map_err(|e| bad(&e))?;
                Some(a.to_string())
            }
            None => None,
        };
        let mut ca_hash = [0u8; 32];
        hex::decode_to_slice(hash, &mut ca_hash).map_err(|e| bad(&e.to_string()))?;
        Ok(Token { ca_hash, id: id.to_string(), secret: secret.to_string(), address })
    }
}

/// A door's `HOST:PORT` (a name, an IPv4 address or a bracketed IPv6 one, and a port).
pub fn parse_address(a: &str) -> Result<(String, u16), String> {
    let (host, port) = a.rsplit_once(':').ok_or_else(|| format!("address '{a}': expected HOST:PORT"))?;
    let port: u16 = port.parse().map_err(|_| format!("address '{a}': the port is not a number"))?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() || port == 0 || !host.chars().all(|c| c.is_ascii_alphanumeric() || ".-:_".contains(c)) {
        return Err(format!("address '{a}': expected HOST:PORT"));
    }
    Ok((host.to_string(), port))
}

/// A new token id and secret (random, from the operating system's generator through rand's).
pub fn new_id_and_secret() -> (String, String) {
    use rand::RngCore;
    let mut b = [0u8; 20];
    rand::rng().fill_bytes(&mut b);
    (hex::encode(&b[..4]), hex::encode(&b[4..]))
}

/// The hash a coordinator keeps of a token's secret.
pub fn secret_hash(secret: &str) -> [u8; 32] {
    sha2::Sha256::digest(secret.as_bytes()).into()
}

/// SHA-256 of a certificate's SubjectPublicKeyInfo (DER), what a token pins.
pub fn spki_hash(cert_der: &[u8]) -> Result<[u8; 32], String> {
    let (_, c) = x509_parser::parse_x509_certificate(cert_der).map_err(|e| format!("not a certificate ({e})"))?;
    Ok(sha2::Sha256::digest(c.tbs_certificate.subject_pki.raw).into())
}

/// The DER of the first certificate in a PEM text.
pub fn pem_der(pem: &str) -> Result<Vec<u8>, String> {
    let (_, p) =
        x509_parser::pem::parse_x509_pem(pem.as_bytes()).map_err(|e| format!("not a PEM certificate ({e})"))?;
    Ok(p.contents)
}

/// The hash of the CA in a credentials folder (`ca.pem`), as a token carries it.
pub fn ca_hash_of(dir: &Path) -> Result<[u8; 32], String> {
    let path = dir.join(CA_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: cannot read it ({e})", path.display()))?;
    pem_der(&text).and_then(|d| spki_hash(&d)).map_err(|e| format!("{}: {e}", path.display()))
}

fn common_name(cert: &x509_parser::certificate::X509Certificate<'_>) -> String {
    cert.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("").to_string()
}

/// The machine's check of the door: the chain it presents must hold a CA whose key has the
/// token's hash, the door's certificate must be signed by it (webpki) and name the
/// coordinator. Names and addresses are not what is trusted: the pin is.
#[derive(Debug)]
struct PinnedDoor {
    pin: [u8; 32],
    provider: Arc<rustls::crypto::CryptoProvider>,
}

impl rustls::client::danger::ServerCertVerifier for PinnedDoor {
    fn verify_server_cert(
        &self,
        end_entity: &rustls_pki_types::CertificateDer<'_>,
        intermediates: &[rustls_pki_types::CertificateDer<'_>],
        _server_name: &rustls_pki_types::ServerName<'_>,
        ocsp: &[u8],
        now: rustls_pki_types::UnixTime,
    ) -> Result<rustls::client::danger::ServerCertVerified, rustls::Error> {
        let other = |s: String| rustls::Error::General(s);
        let ca = intermediates
            .iter()
            .find(|c| spki_hash(c).is_ok_and(|h| h == self.pin))
            .ok_or_else(|| other("the door's chain holds no CA with the token's hash: not this cluster's".into()))?;
        let mut roots = rustls::RootCertStore::empty();
        roots.add(ca.clone().into_owned()).map_err(|e| other(format!("the pinned CA: {e}")))?;
        let inner = rustls::client::WebPkiServerVerifier::builder_with_provider(Arc::new(roots), self.provider.clone())
            .build()
            .map_err(|e| other(format!("{e}")))?;
        // Cluster certificates name roles, not hosts (each carries `localhost` only).
        let name = rustls_pki_types::ServerName::try_from("localhost").expect("a valid name");
        inner.verify_server_cert(end_entity, &[], &name, ocsp, now)?;
        let (_, leaf) = x509_parser::parse_x509_certificate(end_entity).map_err(|e| other(e.to_string()))?;
        let cn = common_name(&leaf);
        match crate::secure::parse_common_name(&cn) {
            Some((Role::Coordinator, _)) => Ok(rustls::client::danger::ServerCertVerified::assertion()),
            _ => Err(other(format!("the door's certificate is '{cn}', not the coordinator's"))),
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &rustls_pki_types::CertificateDer<'_>,
        dss: &rustls::DigitallySignedStruct,
    ) -> Result<rustls::client::danger::HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &rustls_pki_types::CertificateDer<'_>,
        dss: &rustls::DigitallySignedStruct,
    ) -> Result<rustls::client::danger::HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<rustls::SignatureScheme> {
        self.provider.signature_verification_algorithms.supported_schemes()
    }
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

async fn write_frame<W: tokio::io::AsyncWrite + Unpin>(w: &mut W, bytes: &[u8]) -> std::io::Result<()> {
    use tokio::io::AsyncWriteExt;
    w.write_all(&(bytes.len() as u32).to_be_bytes()).await?;
    w.write_all(bytes).await?;
    w.flush().await
}

async fn read_frame<R: tokio::io::AsyncRead + Unpin>(r: &mut R, max: usize) -> std::io::Result<Vec<u8>> {
    use tokio::io::AsyncReadExt;
    let mut len = [0u8; 4];
    r.read_exact(&mut len).await?;
    let n = u32::from_be_bytes(len) as usize;
    if n > max {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("a {n}-byte message (at most {max})"),
        ));
    }
    let mut buf = vec![0u8; n];
    r.read_exact(&mut buf).await?;
    Ok(buf)
}

/// Send `req` to the door at `addr`, checking the door against `pin` before anything is sent.
pub fn ask(addr: &str, pin: [u8; 32], req: &JoinRequest) -> Result<JoinReply, JoinError> {
    let (host, port) = parse_address(addr).map_err(JoinError::Door)?;
    let provider = provider();
    let config = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| JoinError::Door(e.to_string()))?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(PinnedDoor { pin, provider }))
        .with_no_client_auth();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| JoinError::Door(format!("a runtime: {e}")))?;
    let bytes = req.encode_to_vec();
    let fut = async move {
        let tcp = tokio::net::TcpStream::connect((host.as_str(), port))
            .await
            .map_err(|e| format!("cannot reach it ({e})"))?;
        let name = rustls_pki_types::ServerName::try_from("localhost").expect("a valid name");
        let mut tls = tokio_rustls::TlsConnector::from(Arc::new(config))
            .connect(name, tcp)
            .await
            .map_err(|e| format!("refused the door: {e}"))?;
        write_frame(&mut tls, &bytes).await.map_err(|e| format!("sending: {e}"))?;
        read_frame(&mut tls, MAX_REPLY).await.map_err(|e| format!("reading the answer: {e}"))
    };
    let reply = rt
        .block_on(async { tokio::time::timeout(JOIN_TIMEOUT, fut).await })
        .map_err(|_| JoinError::Door(format!("{addr}: no answer within {} s", JOIN_TIMEOUT.as_secs())))?
        .map_err(|e| JoinError::Door(format!("{addr}: {e}")))?;
    crate::decode::<JoinReply>(&reply).map_err(|e| JoinError::Door(format!("{addr}: a bad answer ({e})")))
}

/// The doors on the local network: every host that answers Zenoh's multicast scouting on
/// `interface` within `wait`, with the door's `port`.
pub fn find_doors(interface: &str, port: u16, wait: Duration) -> Result<Vec<String>, JoinError> {
    use zenoh::Wait;
    use zenoh::config::WhatAmI;
    let e = |x: Box<dyn std::error::Error + Send + Sync>| JoinError::Door(format!("scouting: {x}"));
    let mut config = zenoh::Config::default();
    config.insert_json5("scouting/multicast/enabled", "true").map_err(e)?;
    config.insert_json5("scouting/multicast/interface", &format!("{interface:?}")).map_err(e)?;
    let scout = zenoh::scout(WhatAmI::Peer | WhatAmI::Router, config).wait().map_err(e)?;
    let until = std::time::Instant::now() + wait;
    let mut hosts: Vec<String> = Vec::new();
    while let Some(left) = until.checked_duration_since(std::time::Instant::now()) {
        let Ok(Some(hello)) = scout.recv_timeout(left) else { break };
        for l in hello.locators() {
            let a = l.address().as_str().to_string();
            let host = a.rsplit_once(':').map_or(a.as_str(), |(h, _)| h).to_string();
            let addr = format!("{host}:{port}");
            if !hosts.contains(&addr) {
                tracing::info!(zid = %hello.zid(), "scouting found a node at {a}: trying its door at {addr}");
                hosts.push(addr);
            }
        }
    }
    scout.stop();
    Ok(hosts)
}

/// What `sim-agent join` and the others are given.
#[derive(Clone, Debug)]
pub struct JoinPlan {
    /// The role joining.
    pub role: Role,
    /// The token.
    pub token: Token,
    /// The credentials folder to write.
    pub dir: PathBuf,
    /// Replace the role's credentials already in the folder.
    pub force: bool,
    /// Where to look for the door when the token has no address.
    pub interface: String,
    /// The door's port when the token has no address.
    pub port: u16,
}

/// What a join wrote.
#[derive(Clone, Debug)]
pub struct Joined {
    /// The id the machine joined as.
    pub id: String,
    /// The door that answered.
    pub door: String,
    /// The files written, in the folder.
    pub files: Vec<String>,
    /// The coordinator's Zenoh endpoints, as this machine reaches them.
    pub connect: Vec<String>,
}

/// `sim-agent join`, `learner join`, `deploy join`: one definition for every role.
#[derive(clap::Args, Clone)]
pub struct JoinCli {
    /// The token `coordinator token create` printed (`-`: read it from standard input, out of
    /// the process list).
    pub token: String,
    /// The credentials folder to write (with --service: /var/lib/paddock-ROLE/certs).
    #[arg(long, value_name = "DIR")]
    pub certs: Option<PathBuf>,
    /// Join again, replacing this role's credentials in the folder.
    #[arg(long)]
    pub force: bool,
    /// Where to scout for the coordinator when the token carries no address.
    #[arg(long, default_value = "auto")]
    pub multicast: String,
    /// The join door's port when the token carries no address.
    #[arg(long, default_value_t = DOOR_PORT)]
    pub port: u16,
    /// Install the role as a systemd service and start it (as root, where systemd runs).
    #[arg(long)]
    pub service: bool,
    /// With --service: more arguments for `serve` (after `--`).
    #[arg(last = true)]
    pub args: Vec<String>,
}

impl std::fmt::Debug for JoinCli {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JoinCli").field("certs", &self.certs).field("service", &self.service).finish_non_exhaustive()
    }
}

/// Run a role's `join` command: join, print what was written and how to start the role (or
/// install and start it as a service).
pub fn run_cli(role: Role, cli: JoinCli) -> Result<(), JoinError> {
    // `-`: the token from standard input (kept out of the process list).
    let text = if cli.token == "-" {
        let mut line = String::new();
        std::io::stdin().read_line(&mut line).map_err(|e| JoinError::Usage(format!("reading the token: {e}")))?;
        line
    } else {
        cli.token.clone()
    };
    let token: Token = text.parse()?;
    let service = crate::service::service_role(role);
    // The credentials folder, and with --service the binary the unit runs.
    let (dir, service_bin) = match (&cli.certs, cli.service) {
        (Some(_), true) => {
            return Err(JoinError::Usage(format!(
                "--certs with --service: the service reads {}; leave --certs out",
                crate::service::certs_dir(service).display()
            )));
        }
        (Some(d), false) => (d.clone(), None),
        // Before the door is asked: a token spent on a machine that cannot install the
        // service would be lost. The unit is written once with these arguments (the
        // coordinator's address, which only the door gives, is added to it after).
        (None, true) => {
            let usage = |e: crate::service::ServiceError| JoinError::Usage(e.to_string());
            let bin = crate::service::sibling_binary(service).map_err(usage)?;
            crate::service::unit(service, &bin, "8G", &cli.args).map_err(usage)?;
            crate::service::require_systemd().map_err(usage)?;
            crate::service::require_root().map_err(usage)?;
            (crate::service::certs_dir(service), Some(bin))
        }
        (None, false) => {
            return Err(JoinError::Usage("--certs DIR: expected the folder to write the credentials in".into()));
        }
    };
    let plan =
        JoinPlan { role, token, dir: dir.clone(), force: cli.force, interface: cli.multicast.clone(), port: cli.port };
    let joined = join(&plan)?;
    println!("joined as {} {} through the door at {}", role.name(), joined.id, joined.door);
    println!("wrote {} in {}", joined.files.join(", "), dir.display());
    let mut args: Vec<String> = joined.connect.iter().flat_map(|c| ["--connect".to_string(), c.clone()]).collect();
    args.extend(cli.args.iter().cloned());
    if let Some(bin) = service_bin {
        // A machine joining again: its state folder belongs to the service's dynamic user, who
        // must read what root just wrote (systemd re-owns only a folder whose owner differs).
        #[cfg(unix)]
        if let Some(state) = dir.parent()
            && let Ok(meta) = std::fs::metadata(state)
        {
            use std::os::unix::fs::MetadataExt;
            for p in std::iter::once(dir.clone()).chain(joined.files.iter().map(|f| dir.join(f))) {
                std::os::unix::fs::chown(&p, Some(meta.uid()), Some(meta.gid())).map_err(|e| JoinError::File {
                    path: p.clone(),
                    what: format!("cannot give it to the service ({e})"),
                })?;
            }
        }
        let unit = crate::service::unit(service, &bin, "8G", &args).map_err(|e| JoinError::Door(e.to_string()))?;
        let path = crate::service::install(service, &unit).map_err(|e| JoinError::Door(e.to_string()))?;
        println!("installed {} and started it", path.display());
    } else {
        let bin = crate::service::SERVICES.iter().find(|(r, _, _)| *r == service).map_or("", |(_, b, _)| b);
        let serve = crate::service::serve_words(service).join(" ");
        let more = if role == Role::Car { " --job JOB" } else { "" };
        println!("start it: {bin} {serve} --certs {} {}{more}", dir.display(), args.join(" "));
    }
    Ok(())
}

/// Files of `role` a join writes beside the shared ones.
fn own_files(role: Role, id: &str) -> [String; 2] {
    let s = stem(role, Some(id));
    [format!("{s}.pem"), format!("{s}.key")]
}

/// Join the cluster: make a key here, find and check the door, send the request, check
/// what comes back and write the credentials folder (the key readable by its owner only).
/// Nothing is written unless the join succeeds.
pub fn join(plan: &JoinPlan) -> Result<Joined, JoinError> {
    let file_err = |path: &Path, what: String| JoinError::File { path: path.to_path_buf(), what };
    // Refuse before anything is sent: the CA's own folder, a folder holding another
    // cluster's CA, or this role's credentials already.
    if plan.dir.join("ca.key").exists() {
        return Err(file_err(
            &plan.dir,
            "holds the CA's key: it is the coordinator's folder, whose machines' certificates a join would replace; \
             give join a folder of this machine's own"
                .into(),
        ));
    }
    if let Ok(h) = ca_hash_of(&plan.dir)
        && h != plan.token.ca_hash
    {
        return Err(file_err(&plan.dir.join(CA_FILE), "holds another cluster's CA; give join an empty folder".into()));
    }
    let prefix = format!("{}-", plan.role.name());
    let existing: Vec<String> = std::fs::read_dir(&plan.dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .filter(|n| n.starts_with(&prefix) && (n.ends_with(".pem") || n.ends_with(".key")))
        .collect();
    if !existing.is_empty() && !plan.force {
        return Err(file_err(
            &plan.dir,
            format!(
                "already holds this machine's {} credentials ({}); pass --force to join again and replace them",
                plan.role.name(),
                existing.join(", ")
            ),
        ));
    }
    let key = rcgen::KeyPair::generate().map_err(|e| JoinError::Door(format!("making a key: {e}")))?;
    let mut params = rcgen::CertificateParams::new(Vec::<String>::new()).map_err(|e| JoinError::Door(e.to_string()))?;
    params.distinguished_name = rcgen::DistinguishedName::new();
    params.distinguished_name.push(rcgen::DnType::CommonName, plan.role.common_name());
    let csr = params.serialize_request(&key).map_err(|e| JoinError::Door(format!("the signing request: {e}")))?;
    let req = JoinRequest {
        protocol_version: PROTOCOL_VERSION,
        token_id: plan.token.id.clone(),
        secret: plan.token.secret.clone(),
        role: plan.role.name().to_string(),
        csr_der: csr.der().to_vec(),
    };
    let doors = match &plan.token.address {
        Some(a) => vec![a.clone()],
        None => {
            let found = find_doors(&plan.interface, plan.port, Duration::from_secs(3))?;
            if found.is_empty() {
                return Err(JoinError::Door(format!(
                    "the token has no address and scouting on {} found no node; give the coordinator's \
                     address (`token create --address HOST:PORT`) or scout another interface (--multicast)",
                    plan.interface
                )));
            }
            found
        }
    };
    let mut tried = Vec::new();
    let (door, reply) = 'found: {
        for d in &doors {
            // Once more if the answer was lost: the coordinator sends the same grant again for
            // the same token and key.
            for attempt in 0..2 {
                match ask(d, plan.token.ca_hash, &req) {
                    Ok(r) => break 'found (d.clone(), r),
                    Err(e) => {
                        tracing::info!("{e}");
                        let pin = is_pin_failure(&e);
                        tried.push((pin, e.to_string()));
                        if pin || attempt == 1 {
                            break;
                        }
                        std::thread::sleep(Duration::from_secs(1));
                    }
                }
            }
        }
        let all_pins = tried.iter().all(|(pin, _)| *pin);
        let list = tried.into_iter().map(|(_, e)| e).collect::<Vec<_>>().join("; ");
        return Err(JoinError::Door(if all_pins {
            format!("no door passed the token's CA check (not this token's cluster): {list}")
        } else {
            format!("could not join through any door: {list}")
        }));
    };
    if !reply.ok {
        return Err(JoinError::Refused(reply.refusal));
    }
    let id = check_reply(plan, &reply, &key)?;
    std::fs::create_dir_all(&plan.dir).map_err(|e| file_err(&plan.dir, format!("cannot create it ({e})")))?;
    let [pem, keyfile] = own_files(plan.role, &id);
    let mut files = vec![
        (keyfile, key.serialize_pem(), true),
        (pem, reply.certificate_pem.clone(), false),
        (CA_FILE.to_string(), reply.ca_pem.clone(), false),
        (MODEL_PUB_FILE.to_string(), reply.models_pub.clone(), false),
        (ROSTER_FILE.to_string(), reply.roster_toml.clone(), false),
    ];
    if !reply.crl_pem.is_empty() {
        files.push((crate::revocation::CRL_FILE.to_string(), reply.crl_pem.clone(), false));
    }
    if plan.role == Role::Learner && !reply.models_key.is_empty() {
        files.push((crate::secure::MODEL_KEY_FILE.to_string(), reply.models_key.clone(), true));
    }
    // Every file written beside its place first; only then the old credentials go and the
    // new ones take their places.
    let staged: Vec<PathBuf> = files
        .iter()
        .map(|(name, text, secret)| stage(&plan.dir.join(name), text, *secret))
        .collect::<Result<_, _>>()
        .inspect_err(|_| {
            for (name, _, _) in &files {
                let _ = std::fs::remove_file(staged_name(&plan.dir.join(name)));
            }
        })?;
    for old in existing.iter().filter(|o| !files.iter().any(|(n, _, _)| n == *o)) {
        std::fs::remove_file(plan.dir.join(old))
            .map_err(|e| file_err(&plan.dir.join(old), format!("cannot replace it ({e})")))?;
    }
    for ((name, _, _), tmp) in files.iter().zip(&staged) {
        std::fs::rename(tmp, plan.dir.join(name))
            .map_err(|e| file_err(&plan.dir.join(name), format!("cannot write it ({e})")))?;
    }
    if let Ok(d) = std::fs::File::open(&plan.dir) {
        let _ = d.sync_all();
    }
    let door_host = parse_address(&door).map(|(h, _)| h).unwrap_or_default();
    let connect = reply.connect.iter().map(|ep| endpoint_for(ep, &door_host)).collect();
    Ok(Joined { id, door, files: files.into_iter().map(|(n, _, _)| n).collect(), connect })
}

/// A listen endpoint as a machine reaches it: an unspecified host (`0.0.0.0`, `[::]`) is
/// the door's.
fn endpoint_for(ep: &str, door_host: &str) -> String {
    let host = if door_host.contains(':') { format!("[{door_host}]") } else { door_host.to_string() };
    for any in ["0.0.0.0", "[::]"] {
        if let Some((proto, rest)) = ep.split_once('/')
            && let Some(port) = rest.strip_prefix(any).and_then(|r| r.strip_prefix(':'))
        {
            return format!("{proto}/{host}:{port}");
        }
    }
    ep.to_string()
}

/// What the coordinator sent must be a certificate for this key, from the pinned CA, naming
/// this role and an id; the CA the token's; the roster and key files what they claim.
fn check_reply(plan: &JoinPlan, reply: &JoinReply, key: &rcgen::KeyPair) -> Result<String, JoinError> {
    let bad = |what: String| JoinError::Door(format!("the coordinator's answer: {what}"));
    let ca_der = pem_der(&reply.ca_pem).map_err(|e| bad(format!("the CA {e}")))?;
    if spki_hash(&ca_der).map_err(bad)? != plan.token.ca_hash {
        return Err(bad("its CA is not the token's".into()));
    }
    let der = pem_der(&reply.certificate_pem).map_err(|e| bad(format!("the certificate {e}")))?;
    let (_, cert) = x509_parser::parse_x509_certificate(&der).map_err(|e| bad(e.to_string()))?;
    let (_, ca) = x509_parser::parse_x509_certificate(&ca_der).map_err(|e| bad(e.to_string()))?;
    cert.verify_signature(Some(ca.public_key())).map_err(|e| bad(format!("the certificate is not the CA's ({e})")))?;
    if cert.tbs_certificate.subject_pki.subject_public_key.data.as_ref() != key.public_key_raw() {
        return Err(bad("the certificate is not for the key made here".into()));
    }
    let cn = common_name(&cert);
    let id = match crate::secure::parse_common_name(&cn) {
        Some((r, Some(id))) if r == plan.role && id == reply.id => id,
        _ => return Err(bad(format!("the certificate names '{cn}', not {} {}", plan.role.name(), reply.id))),
    };
    let roster: Roster = toml::from_str(&reply.roster_toml).map_err(|e| bad(format!("ids.toml: {e}")))?;
    if !roster.covers(plan.role, &id) {
        return Err(bad(format!("ids.toml does not cover {} {id}", plan.role.name())));
    }
    policy::signature::TrustedKeys::default()
        .add_pem(MODEL_PUB_FILE, &reply.models_pub)
        .map_err(|e| bad(e.to_string()))?;
    Ok(id)
}

/// Where a file is staged before it takes its place (`NAME.joining`).
fn staged_name(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".joining");
    PathBuf::from(s)
}

/// Whether a door was refused for failing the token's CA pin (or not naming the coordinator).
fn is_pin_failure(e: &JoinError) -> bool {
    let t = e.to_string();
    t.contains("no CA with the token's hash") || t.contains("not the coordinator's")
}

/// Write `text` beside `path` (`.joining`), synced, readable by its owner only when `secret`;
/// returns the staged file.
fn stage(path: &Path, text: &str, secret: bool) -> Result<PathBuf, JoinError> {
    use std::io::Write;
    let err = |what: String| JoinError::File { path: path.to_path_buf(), what };
    let tmp = staged_name(path);
    let _ = std::fs::remove_file(&tmp);
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(if secret { 0o600 } else { 0o644 });
    }
    let mut f = o.open(&tmp).map_err(|e| err(format!("cannot create it ({e})")))?;
    f.write_all(text.as_bytes()).and_then(|()| f.sync_all()).map_err(|e| err(format!("cannot write it ({e})")))?;
    Ok(tmp)
}

/// Joins granted and refused by this process's door, by reason.
#[derive(Debug, Default)]
pub struct JoinCounts {
    /// Joins granted.
    pub granted: AtomicU64,
    /// Joins refused, by reason.
    pub refused: crate::secure::Refusals,
}

/// This process's join figures.
pub static JOINS: std::sync::LazyLock<JoinCounts> = std::sync::LazyLock::new(JoinCounts::default);

/// A join request's answer, made by the coordinator; `peer` is where it came from.
pub type Handler = dyn Fn(JoinRequest, SocketAddr) -> JoinReply + Send + Sync;

/// A refusal as the door sends it.
pub fn refusal(reason: impl Into<String>) -> JoinReply {
    JoinReply { protocol_version: PROTOCOL_VERSION, ok: false, refusal: reason.into(), ..Default::default() }
}

/// When a refusal was last logged (unix seconds): a flood is counted, and logged once a
/// second.
static LAST_LOGGED: AtomicU64 = AtomicU64::new(0);

/// Count a refused join (here and in the node's refusals `job status` shows) and log it.
fn count_refusal(reason: &str, peer: SocketAddr) {
    let short: String = reason.split(':').next().unwrap_or(reason).chars().take(60).collect();
    JOINS.refused.count(short.clone());
    crate::secure::REFUSED.count(format!("join refused: {short}"));
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    if LAST_LOGGED.swap(now, Ordering::Relaxed) != now {
        let reason: String = reason.chars().take(300).collect();
        tracing::warn!(%peer, "join refused: {}", reason.escape_debug());
    }
}

/// The door's admission: at most [`MAX_PER_SECOND`] requests a second in all.
struct Rate {
    window: std::time::Instant,
    n: u32,
}

/// Serve the join door on `listener` (a thread of its own), with the coordinator's
/// certificate chain (its own, then the CA's) and key, answering each request with
/// `handler`. Slow, oversized, malformed and excess requests are refused and counted.
pub fn serve(
    listener: std::net::TcpListener,
    chain: Vec<rustls_pki_types::CertificateDer<'static>>,
    key: rustls_pki_types::PrivateKeyDer<'static>,
    handler: Arc<Handler>,
) -> Result<std::thread::JoinHandle<()>, JoinError> {
    let config = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| JoinError::Door(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(chain, key)
        .map_err(|e| JoinError::Door(format!("the door's certificate: {e}")))?;
    let acceptor = tokio_rustls::TlsAcceptor::from(Arc::new(config));
    listener.set_nonblocking(true).map_err(|e| JoinError::Door(e.to_string()))?;
    std::thread::Builder::new()
        .name("join-door".into())
        .spawn(move || {
            let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                Ok(rt) => rt,
                Err(e) => return tracing::error!("the join door cannot start: {e}"),
            };
            rt.block_on(async move {
                let listener = match tokio::net::TcpListener::from_std(listener) {
                    Ok(l) => l,
                    Err(e) => return tracing::error!("the join door cannot listen: {e}"),
                };
                let slots = Arc::new(tokio::sync::Semaphore::new(MAX_IN_FLIGHT));
                let peers: Arc<std::sync::Mutex<std::collections::HashMap<std::net::IpAddr, usize>>> = Arc::default();
                let mut rate = Rate { window: std::time::Instant::now(), n: 0 };
                loop {
                    let (tcp, peer) = match listener.accept().await {
                        Ok(x) => x,
                        Err(e) => {
                            // Out of descriptors, say: wait rather than spin.
                            tracing::warn!("the join door cannot accept: {e}");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                            continue;
                        }
                    };
                    let Ok(permit) = slots.clone().try_acquire_owned() else {
                        count_refusal("busy: too many joins at once", peer);
                        continue;
                    };
                    {
                        let mut p = peers.lock().unwrap_or_else(|e| e.into_inner());
                        let n = p.entry(peer.ip()).or_default();
                        if *n >= MAX_PER_PEER {
                            count_refusal("busy: too many joins from this address at once", peer);
                            continue;
                        }
                        *n += 1;
                    }
                    if rate.window.elapsed() >= Duration::from_secs(1) {
                        rate = Rate { window: std::time::Instant::now(), n: 0 };
                    }
                    rate.n += 1;
                    let over = rate.n > MAX_PER_SECOND;
                    let (acceptor, handler, peers) = (acceptor.clone(), handler.clone(), peers.clone());
                    tokio::spawn(async move {
                        let _permit = permit;
                        // The handshake and the request have a deadline; once a request is
                        // read, its answer is made and sent whatever the time (a grant is
                        // never made and then dropped).
                        let read = async {
                            let mut tls = acceptor.accept(tcp).await.map_err(|e| format!("handshake: {e}"))?;
                            let bytes = read_frame(&mut tls, MAX_FRAME).await.map_err(|e| format!("malformed: {e}"))?;
                            Ok::<_, String>((tls, bytes))
                        };
                        let result = match tokio::time::timeout(REQUEST_TIMEOUT, read).await {
                            Err(_) => Err("too slow: no request in time".to_string()),
                            Ok(Err(e)) => Err(e),
                            Ok(Ok((mut tls, bytes))) => {
                                let reply = if over {
                                    refusal("busy: too many join requests this second; try again")
                                } else {
                                    match crate::decode::<JoinRequest>(&bytes) {
                                        Ok(req) => {
                                            let h = handler.clone();
                                            tokio::task::spawn_blocking(move || h(req, peer))
                                                .await
                                                .unwrap_or_else(|_| refusal("the coordinator failed on it"))
                                        }
                                        Err(e) => refusal(format!("malformed: {e}")),
                                    }
                                };
                                if reply.ok {
                                    JOINS.granted.fetch_add(1, Ordering::Relaxed);
                                } else {
                                    count_refusal(&reply.refusal, peer);
                                }
                                let sent =
                                    tokio::time::timeout(JOIN_TIMEOUT, write_frame(&mut tls, &reply.encode_to_vec()))
                                        .await;
                                match sent {
                                    Ok(Ok(())) => Ok(()),
                                    // A grant whose answer was lost is sent again when the
                                    // machine asks again with the same token and key.
                                    Ok(Err(e)) => Err(format!("answering: {e}")),
                                    Err(_) => Err("answering: too slow".to_string()),
                                }
                            }
                        };
                        if let Err(e) = result {
                            count_refusal(&e, peer);
                        }
                        let mut p = peers.lock().unwrap_or_else(|e| e.into_inner());
                        if let Some(n) = p.get_mut(&peer.ip()) {
                            *n -= 1;
                            if *n == 0 {
                                p.remove(&peer.ip());
                            }
                        }
                    });
                }
            })
        })
        .map_err(|e| JoinError::Door(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 54: a token's text round-trips, and a tampered or foreign one is refused.
    #[test]
    fn a_token_round_trips_and_a_malformed_one_says_what_is_expected() {
        let t = Token {
            ca_hash: [0xab; 32],
            id: "0a1b2c3d".into(),
            secret: "00112233445566778899aabbccddeeff".into(),
            address: Some("10.0.0.1:7449".into()),
        };
        let text = t.to_string();
        assert_eq!(text.parse::<Token>().unwrap(), t);
        let bare = Token { address: None, ..t.clone() };
        assert_eq!(bare.to_string().parse::<Token>().unwrap(), bare);
        let v6 = Token { address: Some("[::1]:7449".into()), ..t.clone() };
        assert_eq!(v6.to_string().parse::<Token>().unwrap(), v6);
        let table = [
            (text.replacen("P1", "P2", 1), "begins 'P2'"),
            (text.replace("-0a1b2c3d-", "-0a1b2c3-"), "id"),
            (text.replace("ff@", "fg@"), "secret"),
            (text.replace(&"ab".repeat(32), &"AB".repeat(32)), "CA hash"),
            (text.replace("@10.0.0.1:7449", "@10.0.0.1"), "HOST:PORT"),
            ("K10abc::server:secret".to_string(), "four parts"),
        ];
        for (bad, want) in table {
            let e = bad.parse::<Token>().unwrap_err().to_string();
            assert!(e.contains(want) && e.contains("token create"), "{bad}: {e}");
        }
        let (id, secret) = new_id_and_secret();
        assert!(is_hex(&id, 8) && is_hex(&secret, 32));
        assert_ne!(new_id_and_secret().1, secret);
    }

    /// A CA, and a certificate named `cn` it signs: (CA DER, chain, key).
    fn chain(
        cn: &str,
    ) -> (Vec<u8>, Vec<rustls_pki_types::CertificateDer<'static>>, rustls_pki_types::PrivateKeyDer<'static>) {
        let ca_key = rcgen::KeyPair::generate().unwrap();
        let mut ca = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
        ca.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Constrained(0));
        ca.key_usages = vec![rcgen::KeyUsagePurpose::KeyCertSign, rcgen::KeyUsagePurpose::DigitalSignature];
        let ca_cert = ca.self_signed(&ca_key).unwrap();
        let issuer = rcgen::Issuer::new(ca, ca_key);
        let key = rcgen::KeyPair::generate().unwrap();
        let mut p = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap();
        p.distinguished_name = rcgen::DistinguishedName::new();
        p.distinguished_name.push(rcgen::DnType::CommonName, cn);
        let cert = p.signed_by(&key, &issuer).unwrap();
        let ca_der = ca_cert.der().to_vec();
        let chain = vec![cert.der().clone(), ca_cert.der().clone()];
        let key = rustls_pki_types::PrivateKeyDer::Pkcs8(key.serialize_der().into());
        (ca_der, chain, key)
    }

    fn door(cn: &str, calls: Arc<AtomicU64>) -> ([u8; 32], String) {
        let (ca, chain, key) = chain(cn);
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        let handler = Arc::new(move |req: JoinRequest, _peer| {
            calls.fetch_add(1, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(300));
            JoinReply { protocol_version: PROTOCOL_VERSION, ok: true, id: req.token_id, ..Default::default() }
        });
        serve(l, chain, key, handler).unwrap();
        (spki_hash(&ca).unwrap(), addr)
    }

    fn request(id: &str) -> JoinRequest {
        JoinRequest { protocol_version: PROTOCOL_VERSION, token_id: id.into(), ..Default::default() }
    }

    /// Issue 54: a door that is not the token's CA's coordinator hears nothing; a flood of
    /// joins is refused past the door's limits, each counted, and the door keeps answering.
    #[test]
    fn a_forged_door_hears_nothing_and_a_flood_of_joins_is_refused_and_counted() {
        let calls = Arc::new(AtomicU64::new(0));
        let (pin, addr) = door("paddock-coordinator", calls.clone());
        // Another cluster's coordinator, and this cluster's agent posing as the door.
        let (_, other) = door("paddock-coordinator", calls.clone());
        let e = ask(&other, pin, &request("x")).unwrap_err().to_string();
        assert!(e.contains("no CA with the token's hash"), "{e}");
        let (agent_pin, agent_door) = {
            let (ca, chain, key) = chain("paddock-agent.slot-1");
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            let a = l.local_addr().unwrap().to_string();
            let c = calls.clone();
            serve(
                l,
                chain,
                key,
                Arc::new(move |_r: JoinRequest, _p| {
                    c.fetch_add(1, Ordering::SeqCst);
                    refusal("-")
                }),
            )
            .unwrap();
            (spki_hash(&ca).unwrap(), a)
        };
        let e = ask(&agent_door, agent_pin, &request("x")).unwrap_err().to_string();
        assert!(e.contains("not the coordinator's"), "{e}");
        assert_eq!(calls.load(Ordering::SeqCst), 0, "a door that failed the check heard the request");
        // The real door answers.
        assert_eq!(ask(&addr, pin, &request("one")).unwrap().id, "one");
        assert_eq!(calls.swap(0, Ordering::SeqCst), 1);
        // A flood: 60 at once.
        std::thread::sleep(Duration::from_millis(1100));
        let refused_before = JOINS.refused.total();
        let answers: Vec<_> = (0..60)
            .map(|i| {
                let a = addr.clone();
                std::thread::spawn(move || ask(&a, pin, &request(&format!("{i}"))))
            })
            .collect::<Vec<_>>()
            .into_iter()
            .map(|h| h.join().unwrap())
            .collect();
        let granted = answers.iter().filter(|a| a.as_ref().is_ok_and(|r| r.ok)).count();
        let busy = answers.iter().filter(|a| a.as_ref().is_ok_and(|r| r.refusal.starts_with("busy"))).count();
        let handled = calls.load(Ordering::SeqCst) as usize;
        assert!(handled <= MAX_PER_SECOND as usize * 2 && granted == handled, "{handled} handled, {granted} granted");
        assert!(granted + busy < 60 || busy > 0, "nothing was refused: {granted} granted");
        assert!(JOINS.refused.total() - refused_before >= (60 - granted) as u64, "refusals not counted");
        // And it still answers.
        std::thread::sleep(Duration::from_millis(1100));
        assert_eq!(ask(&addr, pin, &request("after")).unwrap().id, "after");
    }
}
