//
// PADDOCK PATCH (this whole file): certificate revocation lists that change while the
// process runs. Upstream zenoh-link-tls builds its certificate verifiers once, from files,
// with no revocation lists; a cluster that revokes a stolen machine's certificate needs every
// node to refuse it from then on, without a restart, and to drop the links it already holds.
//
// - `set_revocation_lists` replaces the process's lists (DER X.509 CRLs); every handshake
//   after it checks the peer's certificate against them (rustls-webpki does the checking), and
//   every open TLS link whose peer's certificate they revoke is closed.
// - `check_revocation_list` tries a list on a certificate with the same verifier a handshake
//   uses, so that a list with a bad signature is refused before it is installed (installed,
//   it would make every handshake fail).
//
// SPDX-License-Identifier: EPL-2.0 OR Apache-2.0
//
use std::{
    collections::BTreeSet,
    io::Cursor,
    sync::{
        atomic::{AtomicU64, Ordering},
        Arc, Mutex, RwLock, Weak,
    },
};

use rustls::{
    client::{
        danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier},
        WebPkiServerVerifier,
    },
    pki_types::{CertificateDer, CertificateRevocationListDer, ServerName, UnixTime},
    server::{
        danger::{ClientCertVerified, ClientCertVerifier},
        WebPkiClientVerifier,
    },
    CertificateError, DigitallySignedStruct, DistinguishedName, Error, RootCertStore,
    SignatureScheme,
};
use x509_parser::prelude::{CertificateRevocationList, FromDer, X509Certificate};

use crate::LinkUnicastTls;

struct Lists {
    ders: Vec<CertificateRevocationListDer<'static>>,
    /// The serial numbers they revoke.
    serials: BTreeSet<Vec<u8>>,
}

static LISTS: RwLock<Lists> = RwLock::new(Lists {
    ders: Vec::new(),
    serials: BTreeSet::new(),
});
static GENERATION: AtomicU64 = AtomicU64::new(0);

/// Open links: the serial number of the peer's certificate, and the link.
type LiveLinks = Vec<(Vec<u8>, String, Weak<LinkUnicastTls>)>;
static LINKS: Mutex<LiveLinks> = Mutex::new(Vec::new());

/// Replace this process's certificate revocation lists (each a DER X.509 CRL). Handshakes from
/// now on refuse a certificate they revoke; open links to a peer whose certificate they revoke
/// are closed. Returns the number of links closed.
pub fn set_revocation_lists(lists: Vec<Vec<u8>>) -> Result<usize, String> {
    let mut serials = BTreeSet::new();
    for (i, der) in lists.iter().enumerate() {
        let bad = |e: String| format!("revocation list {}: not a DER X.509 CRL ({e})", i + 1);
        // As the handshake's verifier will read it, and for its serial numbers.
        webpki::OwnedCertRevocationList::from_der(der).map_err(|e| bad(format!("{e:?}")))?;
        let (_, crl) = CertificateRevocationList::from_der(der).map_err(|e| bad(e.to_string()))?;
        serials.extend(crl.iter_revoked_certificates().map(|r| r.raw_serial().to_vec()));
    }
    let revoked = |serial: &[u8]| serials.contains(serial);
    let mut to_close = Vec::new();
    {
        // The links' lock first, then the lists': a link registered meanwhile is either
        // scanned here or checked against the new lists in `register`.
        let mut links = LINKS.lock().unwrap_or_else(|p| p.into_inner());
        links.retain(|(_, _, l)| l.strong_count() > 0);
        for (serial, name, link) in links.iter() {
            if revoked(serial) {
                if let Some(l) = link.upgrade() {
                    to_close.push((name.clone(), l));
                }
            }
        }
        let mut l = LISTS.write().unwrap_or_else(|p| p.into_inner());
        l.ders = lists
            .into_iter()
            .map(CertificateRevocationListDer::from)
            .collect();
        l.serials = serials;
        GENERATION.fetch_add(1, Ordering::SeqCst);
    }
    let closed = to_close.len();
    for (name, link) in to_close {
        close_revoked(&name, link);
    }
    Ok(closed)
}

/// End a link whose peer's certificate (named `name`) is revoked, on the runtime.
fn close_revoked(name: &str, link: Arc<LinkUnicastTls>) {
    tracing::warn!("Closing TLS link {link}: the peer's certificate ({name}) is revoked");
    zenoh_runtime::ZRuntime::Acceptor.spawn(async move {
        let _ = link.revoke().await;
    });
}

/// How many times the lists were replaced in this process.
pub fn revocation_generation() -> u64 {
    GENERATION.load(Ordering::SeqCst)
}

/// Whether the installed lists revoke a certificate with this serial number.
pub(crate) fn is_revoked(serial: &[u8]) -> bool {
    LISTS
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .serials
        .contains(serial)
}

/// Keep track of an open link to a peer whose certificate has this serial number (closed at
/// once if it is already revoked, e.g. by a list that arrived during the handshake).
pub(crate) fn register(peer: &CertificateDer<'_>, link: &Arc<LinkUnicastTls>) {
    let Ok((_, cert)) = X509Certificate::from_der(peer.as_ref()) else {
        return;
    };
    let serial = cert.raw_serial().to_vec();
    let name = cert
        .subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .unwrap_or("no common name")
        .to_string();
    let mut links = LINKS.lock().unwrap_or_else(|p| p.into_inner());
    if is_revoked(&serial) {
        drop(links);
        close_revoked(&name, link.clone());
        return;
    }
    links.retain(|(_, _, l)| l.strong_count() > 0);
    links.push((serial, name, Arc::downgrade(link)));
}

fn current_lists() -> Vec<CertificateRevocationListDer<'static>> {
    LISTS.read().unwrap_or_else(|p| p.into_inner()).ders.clone()
}

fn roots_from_pem(pem: &[u8]) -> Result<RootCertStore, String> {
    let mut roots = RootCertStore::empty();
    for c in rustls_pemfile::certs(&mut Cursor::new(pem)) {
        let c = c.map_err(|e| format!("CA certificate: {e}"))?;
        roots
            .add(c)
            .map_err(|e| format!("CA certificate: {e}"))?;
    }
    if roots.is_empty() {
        return Err("CA certificate: no PEM certificate found".into());
    }
    Ok(roots)
}

fn client_verifier(
    roots: Arc<RootCertStore>,
    lists: Vec<CertificateRevocationListDer<'static>>,
) -> Result<Arc<dyn ClientCertVerifier>, String> {
    WebPkiClientVerifier::builder(roots)
        .with_crls(lists)
        .only_check_end_entity_revocation()
        .allow_unknown_revocation_status()
        .build()
        .map_err(|e| e.to_string())
}

/// Why [`check_revocation_list`] refused.
#[derive(Debug)]
pub enum ListCheckError {
    /// The CA or the certificate to try the list on is unusable (before any list is used).
    Certificate(String),
    /// The list is not the CA's, or does not apply to the certificates it signs.
    List(String),
}

/// Check `list` (a DER X.509 CRL) against the CA (`ca_pem`) by verifying `cert_pem` (a
/// certificate that CA signed) with it, as a handshake would, except that the list must be
/// authoritative for that certificate (the CA's own list, signed by it): `Ok(true)` when it
/// revokes that certificate, `Ok(false)` when it does not.
pub fn check_revocation_list(
    ca_pem: &[u8],
    cert_pem: &[u8],
    list: &[u8],
) -> Result<bool, ListCheckError> {
    let roots = Arc::new(roots_from_pem(ca_pem).map_err(ListCheckError::Certificate)?);
    let cert = rustls_pemfile::certs(&mut Cursor::new(cert_pem))
        .next()
        .ok_or_else(|| ListCheckError::Certificate("no PEM certificate found".into()))?
        .map_err(|e| ListCheckError::Certificate(e.to_string()))?;
    let plain = client_verifier(roots.clone(), Vec::new()).map_err(ListCheckError::Certificate)?;
    plain
        .verify_client_cert(&cert, &[], UnixTime::now())
        .map_err(|e| ListCheckError::Certificate(e.to_string()))?;
    // Unknown status refused: a list that is not the CA's own (another issuer, another
    // distribution point) would otherwise pass unchecked, its signature never looked at.
    let strict = WebPkiClientVerifier::builder(roots)
        .with_crls([CertificateRevocationListDer::from(list.to_vec())])
        .only_check_end_entity_revocation()
        .build()
        .map_err(|e| ListCheckError::List(e.to_string()))?;
    match strict.verify_client_cert(&cert, &[], UnixTime::now()) {
        Ok(_) => Ok(false),
        Err(Error::InvalidCertificate(CertificateError::Revoked)) => Ok(true),
        Err(e) => Err(ListCheckError::List(e.to_string())),
    }
}

/// The verifier of clients' certificates on a listener: webpki's, rebuilt with the current
/// revocation lists whenever they change.
#[derive(Debug)]
pub(crate) struct RevocableClientVerifier {
    roots: Arc<RootCertStore>,
    subjects: Vec<DistinguishedName>,
    current: Mutex<(u64, Arc<dyn ClientCertVerifier>)>,
}

impl RevocableClientVerifier {
    pub(crate) fn new(roots: RootCertStore) -> Result<Arc<Self>, String> {
        let roots = Arc::new(roots);
        let g = revocation_generation();
        let v = client_verifier(roots.clone(), current_lists())?;
        Ok(Arc::new(Self {
            roots,
            subjects: v.root_hint_subjects().to_vec(),
            current: Mutex::new((g, v)),
        }))
    }

    fn get(&self) -> Arc<dyn ClientCertVerifier> {
        let g = revocation_generation();
        let mut c = self.current.lock().unwrap_or_else(|p| p.into_inner());
        if c.0 != g {
            match client_verifier(self.roots.clone(), current_lists()) {
                Ok(v) => *c = (g, v),
                Err(e) => tracing::error!("TLS: cannot use the new revocation lists: {e}"),
            }
        }
        c.1.clone()
    }
}

impl ClientCertVerifier for RevocableClientVerifier {
    fn root_hint_subjects(&self) -> &[DistinguishedName] {
        &self.subjects
    }

    fn verify_client_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        now: UnixTime,
    ) -> Result<ClientCertVerified, Error> {
        self.get().verify_client_cert(end_entity, intermediates, now)
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, Error> {
        self.get().verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, Error> {
        self.get().verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.get().supported_verify_schemes()
    }
}

/// The verifier of servers' certificates on a connector: webpki's with the current revocation
/// lists, the server's name checked or not (`verify_name_on_connect`).
#[derive(Debug)]
pub(crate) struct RevocableServerVerifier {
    roots: Arc<RootCertStore>,
    verify_name: bool,
    current: Mutex<(u64, Arc<WebPkiServerVerifier>)>,
}

fn server_verifier(
    roots: Arc<RootCertStore>,
    lists: Vec<CertificateRevocationListDer<'static>>,
) -> Result<Arc<WebPkiServerVerifier>, String> {
    WebPkiServerVerifier::builder(roots)
        .with_crls(lists)
        .only_check_end_entity_revocation()
        .allow_unknown_revocation_status()
        .build()
        .map_err(|e| e.to_string())
}

impl RevocableServerVerifier {
    pub(crate) fn new(roots: RootCertStore, verify_name: bool) -> Result<Arc<Self>, String> {
        let roots = Arc::new(roots);
        let g = revocation_generation();
        let v = server_verifier(roots.clone(), current_lists())?;
        Ok(Arc::new(Self {
            roots,
            verify_name,
            current: Mutex::new((g, v)),
        }))
    }

    fn get(&self) -> Arc<WebPkiServerVerifier> {
        let g = revocation_generation();
        let mut c = self.current.lock().unwrap_or_else(|p| p.into_inner());
        if c.0 != g {
            match server_verifier(self.roots.clone(), current_lists()) {
                Ok(v) => *c = (g, v),
                Err(e) => tracing::error!("TLS: cannot use the new revocation lists: {e}"),
            }
        }
        c.1.clone()
    }
}

impl ServerCertVerifier for RevocableServerVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        server_name: &ServerName<'_>,
        ocsp_response: &[u8],
        now: UnixTime,
    ) -> Result<ServerCertVerified, Error> {
        // webpki checks the chain (and revocation) before the name: a name error means the
        // rest held.
        match self.get().verify_server_cert(
            end_entity,
            intermediates,
            server_name,
            ocsp_response,
            now,
        ) {
            Err(Error::InvalidCertificate(
                CertificateError::NotValidForName | CertificateError::NotValidForNameContext { .. },
            )) if !self.verify_name => Ok(ServerCertVerified::assertion()),
            other => other,
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, Error> {
        self.get().verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, Error> {
        self.get().verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.get().supported_verify_schemes()
    }
}
