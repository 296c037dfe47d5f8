//! The cluster's certificate revocation list: an X.509 CRL signed by the cluster's CA
//! (`coordinator certs revoke` writes it to the credentials folder as [`CRL_FILE`]), which
//! the coordinator publishes on [`keys::REVOKED`](crate::keys::REVOKED) and every node with
//! credentials follows.
//!
//! A node takes a list only if it is the CA's (tried on the node's own certificate with the
//! verifier every handshake uses, so a forged list is refused before it could break them) and
//! newer than the one it holds (its CRL number; an old list replayed to un-revoke a
//! certificate is refused). Taken, it goes to the TLS links (the patched `zenoh-link-tls`):
//! handshakes refuse the certificates it names and open links to them are closed. Lists
//! refused are counted with the network's other refusals.

use crate::secure::{Credentials, REFUSED};
use std::path::Path;
use std::sync::Mutex;
use x509_parser::prelude::{CertificateRevocationList, FromDer};
use zenoh::Wait;

/// The revocation list in a credentials folder (PEM).
pub const CRL_FILE: &str = "crl.pem";

/// Why a revocation list was not taken.
#[derive(Debug, thiserror::Error)]
pub enum RevocationError {
    /// Not a DER or PEM X.509 CRL.
    #[error("not an X.509 certificate revocation list: {0}")]
    Malformed(String),
    /// Not signed by the cluster's CA, or unusable with it.
    #[error("not the cluster CA's revocation list: {0}")]
    NotTheCa(String),
    /// Older than the list held.
    #[error("revocation list number {got} is older than the one held ({held})")]
    Stale {
        /// The list's number.
        got: u64,
        /// The number of the list held.
        held: u64,
    },
    /// The credentials could not be read.
    #[error("{0}")]
    Credentials(String),
}

/// What taking a list did.
#[derive(Debug, PartialEq)]
pub enum Taken {
    /// A newer list: now in force.
    Installed {
        /// Its CRL number.
        number: u64,
        /// Certificates it revokes.
        revoked: usize,
        /// Open links it closed.
        closed: usize,
        /// Whether it revokes this node's own certificate.
        self_revoked: bool,
    },
    /// The list already in force.
    Unchanged,
}

/// The list in force in this process: its number and DER bytes.
static HELD: Mutex<Option<(u64, Vec<u8>)>> = Mutex::new(None);

/// The DER bytes of a CRL given as PEM (`X509 CRL`) or DER.
pub fn der_of(bytes: &[u8]) -> Result<Vec<u8>, RevocationError> {
    if bytes.starts_with(b"-----BEGIN") {
        let (_, pem) =
            x509_parser::pem::parse_x509_pem(bytes).map_err(|e| RevocationError::Malformed(format!("PEM: {e}")))?;
        if pem.label != "X509 CRL" {
            return Err(RevocationError::Malformed(format!("a PEM {}, expected an X509 CRL", pem.label)));
        }
        return Ok(pem.contents);
    }
    Ok(bytes.to_vec())
}

/// A CRL's number and the serial numbers (hex) it revokes.
pub fn contents(der: &[u8]) -> Result<(u64, Vec<String>), RevocationError> {
    let (rest, crl) =
        CertificateRevocationList::from_der(der).map_err(|e| RevocationError::Malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(RevocationError::Malformed(format!("{} bytes after the list", rest.len())));
    }
    let number = match crl.crl_number() {
        Some(n) => {
            let d = n.to_u64_digits();
            if d.len() > 1 {
                return Err(RevocationError::Malformed("a CRL number over 64 bits".into()));
            }
            d.first().copied().unwrap_or(0)
        }
        None => return Err(RevocationError::Malformed("no CRL number".into())),
    };
    let serials = crl.iter_revoked_certificates().map(|r| r.raw_serial_as_string()).collect();
    Ok((number, serials))
}

/// Take a list (PEM or DER) if it is the cluster CA's and newer than the one in force.
pub fn take(creds: &Credentials, bytes: &[u8]) -> Result<Taken, RevocationError> {
    let der = der_of(bytes)?;
    let (number, serials) = contents(&der)?;
    let mut held = HELD.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((n, _)) = held.as_ref() {
        if number == *n {
            return Ok(Taken::Unchanged);
        }
        if number < *n {
            return Err(RevocationError::Stale { got: number, held: *n });
        }
    }
    let read = |p: &Path| std::fs::read(p).map_err(|e| RevocationError::Credentials(format!("{}: {e}", p.display())));
    use zenoh_link_tls::revocation::{ListCheckError, check_revocation_list};
    let self_revoked = check_revocation_list(&read(&creds.ca)?, &read(&creds.cert)?, &der).map_err(|e| match e {
        ListCheckError::Certificate(e) => {
            RevocationError::Credentials(format!("{} (signed by {}): {e}", creds.cert.display(), creds.ca.display()))
        }
        ListCheckError::List(e) => RevocationError::NotTheCa(e),
    })?;
    let closed =
        zenoh_link_tls::revocation::set_revocation_lists(vec![der.clone()]).map_err(RevocationError::Malformed)?;
    *held = Some((number, der));
    Ok(Taken::Installed { number, revoked: serials.len(), closed, self_revoked })
}

/// The list in force (DER), if any: what the coordinator publishes.
pub fn held() -> Option<(u64, Vec<u8>)> {
    HELD.lock().unwrap_or_else(|p| p.into_inner()).clone()
}

/// Log what taking a list did; a refused list is counted with the network's refusals.
pub fn log(source: &str, r: &Result<Taken, RevocationError>) {
    match r {
        Ok(Taken::Installed { number, revoked, closed, self_revoked }) => {
            tracing::info!(source, number, revoked, closed, "revocation list in force");
            if *self_revoked {
                tracing::error!("this node's own certificate is revoked: every peer will refuse it");
            }
        }
        Ok(Taken::Unchanged) => {}
        Err(e) => {
            tracing::warn!(source, "revocation list refused: {e}");
            REFUSED.count(format!("revocation list: {}", short(e)));
        }
    }
}

fn short(e: &RevocationError) -> &'static str {
    match e {
        RevocationError::Malformed(_) => "malformed",
        RevocationError::NotTheCa(_) => "not signed by the cluster CA",
        RevocationError::Stale { .. } => "older than the one held",
        RevocationError::Credentials(_) => "credentials unreadable",
    }
}

/// Follow the cluster's revocation list on `session`: the folder's [`CRL_FILE`] at once (an
/// unusable file is an error naming it), then every list the coordinator publishes or
/// answers with.
pub fn follow(session: &zenoh::Session, dir: &Path, creds: &Credentials) -> Result<(), FollowError> {
    let file = dir.join(CRL_FILE);
    if file.exists() {
        let bytes = std::fs::read(&file).map_err(policy::FileError::io_at(&file))?;
        let r = take(creds, &bytes);
        match r {
            Err(e @ RevocationError::Credentials(_)) => return Err(FollowError::Credentials(e)),
            Err(error) => return Err(FollowError::Refused { path: file.display().to_string(), error }),
            Ok(_) => {}
        }
        log("file", &r);
    }
    let c = creds.clone();
    session
        .declare_subscriber(crate::keys::REVOKED)
        .callback(move |s| log("published", &take(&c, &s.payload().to_bytes())))
        .background()
        .wait()
        .map_err(|e| FollowError::Subscribe(e.to_string()))?;
    let c = creds.clone();
    let s = session.clone();
    std::thread::Builder::new()
        .name("revocation-query".into())
        .spawn(move || {
            let Ok(replies) = s.get(crate::keys::REVOKED).timeout(std::time::Duration::from_secs(3)).wait() else {
                return;
            };
            while let Ok(r) = replies.recv() {
                if let Ok(sample) = r.result() {
                    log("asked", &take(&c, &sample.payload().to_bytes()));
                }
            }
        })
        .map_err(FollowError::Thread)?;
    Ok(())
}

/// Why a node could not follow the revocation list.
#[derive(Debug, thiserror::Error)]
pub enum FollowError {
    /// The credentials folder's [`CRL_FILE`] could not be read.
    #[error(transparent)]
    File(#[from] policy::FileError),
    /// The credentials folder's [`CRL_FILE`] is not a list the node takes.
    #[error("{path}: {error}")]
    Refused {
        /// The file.
        path: String,
        /// Why it was refused.
        error: RevocationError,
    },
    /// The node's own credentials could not be read to check the list.
    #[error(transparent)]
    Credentials(RevocationError),
    /// The subscription to the published lists failed (zenoh's reason).
    #[error("{0}")]
    Subscribe(String),
    /// The thread that asks for the current list could not start.
    #[error("{0}")]
    Thread(std::io::Error),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::secure::Role;
    use rcgen::{
        CertificateParams, CertificateRevocationListParams, DistinguishedName, DnType, IsCa, Issuer, KeyIdMethod,
        KeyPair, RevokedCertParams, SerialNumber,
    };

    /// A CA with the cluster CA's name, and its certificate (PEM).
    fn ca() -> (Issuer<'static, KeyPair>, String) {
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.distinguished_name = DistinguishedName::new();
        p.distinguished_name.push(DnType::CommonName, "paddock-cluster-ca");
        p.is_ca = IsCa::Ca(rcgen::BasicConstraints::Constrained(0));
        let pem = p.self_signed(&key).unwrap().pem();
        (Issuer::new(p, key), pem)
    }

    fn crl(issuer: &Issuer<'_, KeyPair>, number: u64, serials: &[Vec<u8>]) -> rcgen::CertificateRevocationList {
        let now = time::OffsetDateTime::now_utc();
        CertificateRevocationListParams {
            this_update: now,
            next_update: now + time::Duration::days(30),
            crl_number: SerialNumber::from(number.to_be_bytes().to_vec()),
            issuing_distribution_point: None,
            revoked_certs: serials
                .iter()
                .map(|s| RevokedCertParams {
                    serial_number: SerialNumber::from(s.clone()),
                    revocation_time: now,
                    reason_code: None,
                    invalidity_date: None,
                })
                .collect(),
            key_identifier_method: KeyIdMethod::Sha256,
        }
        .signed_by(issuer)
        .unwrap()
    }

    /// Issue 35: only the CA's newer lists are taken.
    #[test]
    fn only_the_cas_newer_lists_are_taken() {
        let dir = tempfile::tempdir().unwrap();
        // Two CAs with the same name: only the signature tells them apart.
        let ((cluster, ca_pem), (impostor, _)) = (ca(), ca());
        let key = KeyPair::generate().unwrap();
        let mut np = CertificateParams::new(vec!["localhost".to_string()]).unwrap();
        np.distinguished_name = DistinguishedName::new();
        np.distinguished_name.push(DnType::CommonName, Role::Agent.common_name_of("lab-1"));
        let node = np.signed_by(&key, &cluster).unwrap();
        std::fs::write(dir.path().join("ca.pem"), ca_pem).unwrap();
        std::fs::write(dir.path().join("agent-lab-1.pem"), node.pem()).unwrap();
        std::fs::write(dir.path().join("agent-lab-1.key"), key.serialize_pem()).unwrap();
        let creds = Credentials::from_dir(dir.path(), Role::Agent, Some("lab-1")).unwrap();
        let (_, parsed) = x509_parser::parse_x509_certificate(node.der()).unwrap();
        let own = parsed.raw_serial().to_vec();

        assert!(matches!(take(&creds, b"garbage"), Err(RevocationError::Malformed(_))));
        // A list with the cluster CA's name and a higher number, signed by another key.
        let forged = crl(&impostor, 9, std::slice::from_ref(&own));
        assert!(matches!(take(&creds, forged.der()), Err(RevocationError::NotTheCa(_))), "forged list taken");
        // A list under another issuer's name does not apply to the cluster's certificates: its
        // signature is never looked at by a handshake, so it is refused outright (taken, a
        // number like u64::MAX would lock out every genuine list after it).
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.distinguished_name.push(DnType::CommonName, "someone-else");
        p.is_ca = IsCa::Ca(rcgen::BasicConstraints::Constrained(0));
        let elsewhere = crl(&Issuer::new(p, key), u64::MAX, std::slice::from_ref(&own));
        assert!(matches!(take(&creds, elsewhere.der()), Err(RevocationError::NotTheCa(_))), "foreign list taken");
        assert_eq!(held(), None);
        let other = vec![0x11; 20];
        let two = crl(&cluster, 2, std::slice::from_ref(&other));
        assert_eq!(
            take(&creds, two.der()).unwrap(),
            Taken::Installed { number: 2, revoked: 1, closed: 0, self_revoked: false }
        );
        assert_eq!(take(&creds, two.der()).unwrap(), Taken::Unchanged);
        // An older list (one that had not revoked anything yet) replayed to undo a revocation.
        let one = crl(&cluster, 1, &[]);
        assert!(matches!(take(&creds, one.der()), Err(RevocationError::Stale { got: 1, held: 2 })));
        // PEM as `certs revoke` writes it; this node's own certificate on it.
        let three = crl(&cluster, 3, &[other, own]);
        assert_eq!(
            take(&creds, three.pem().unwrap().as_bytes()).unwrap(),
            Taken::Installed { number: 3, revoked: 2, closed: 0, self_revoked: true }
        );
        assert_eq!(held().map(|h| h.0), Some(3));
        assert!(der_of(b"-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n").is_err());
    }
}
