//! `certs`: the cluster's credentials. `new` writes one CA (ECDSA P-256, allowed to sign only
//! certificates directly under it) and one certificate per role, its common name
//! `paddock-<role>` (what the access rules of `protocol::secure` match), usable for both ends
//! of a mutual-TLS link, and the learners' model-signing key (`models.key`, `models.pub`):
//! learners given the folder sign with it, agents and cars given it trust what it signs.
//! `issue` gives a machine a certificate of its own (`paddock-<role>.<id>`, bound by the
//! access rules to its id), `revoke` adds certificates to the CA's revocation list
//! (`crl.pem`, which a running coordinator hands to every node), `list` shows them all.
//! Keys are written readable by their owner only.

use anyhow::{Context, Result, bail};
use protocol::secure::{CA_FILE, MODEL_KEY_FILE, MODEL_PUB_FILE, ROSTER_FILE, Role, Roster, stem};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose, date_time_ymd,
};
use std::path::Path;

/// Years a credential set is valid.
pub const YEARS: i32 = 10;

/// The current year (UTC), for certificates' validity.
pub fn this_year() -> i32 {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    1970 + (secs / 31_556_952) as i32
}

/// Write a new file (never over one), readable by its owner only when `secret`.
pub fn write_file(path: &Path, text: &str, secret: bool) -> Result<()> {
    use std::io::Write;
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(if secret { 0o600 } else { 0o644 });
    }
    let mut f = o.open(path).with_context(|| format!("{}: cannot create it", path.display()))?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .with_context(|| format!("{}: cannot write it", path.display()))
}

/// A node's certificate parameters: common name `cn`, usable for both ends of a mutual-TLS
/// link (validity left to the caller).
pub fn leaf(cn: &str) -> Result<CertificateParams> {
    let mut p = CertificateParams::new(vec!["localhost".to_string()]).context("certificate parameters")?;
    p.distinguished_name = DistinguishedName::new();
    p.distinguished_name.push(DnType::CommonName, cn);
    p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
    Ok(p)
}

/// Write a CA and every role's certificate and key into `dir`. Existing credentials are kept
/// unless `force` (a new CA makes every certificate already handed out useless).
pub fn write(dir: &Path, force: bool, slots: &[(Role, u32)]) -> Result<Vec<String>> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create the folder", dir.display()))?;
    let mut names = vec![CA_FILE.to_string(), "ca.key".to_string()];
    for r in Role::ALL {
        names.push(format!("{}.pem", r.name()));
        names.push(format!("{}.key", r.name()));
    }
    names.push(MODEL_KEY_FILE.to_string());
    names.push(MODEL_PUB_FILE.to_string());
    let existing: Vec<&String> = names.iter().filter(|n| dir.join(n).exists()).collect();
    if !existing.is_empty() {
        if !force {
            bail!(
                "{}: already holds credentials ({}); pass --force to replace them (every role then needs the new files)",
                dir.display(),
                existing.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ")
            );
        }
        for n in existing {
            std::fs::remove_file(dir.join(n))
                .with_context(|| format!("{}: cannot replace it", dir.join(n).display()))?;
        }
    }
    let year = this_year();
    let validity = |p: &mut CertificateParams| {
        p.not_before = date_time_ymd(year - 1, 1, 1);
        p.not_after = date_time_ymd(year + YEARS, 1, 1);
    };
    let ca_key = KeyPair::generate().context("generating the CA key")?;
    let mut ca = CertificateParams::new(Vec::<String>::new()).context("CA parameters")?;
    ca.distinguished_name = DistinguishedName::new();
    ca.distinguished_name.push(DnType::CommonName, "paddock-cluster-ca");
    ca.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign, KeyUsagePurpose::DigitalSignature];
    validity(&mut ca);
    let ca_cert = ca.self_signed(&ca_key).context("signing the CA")?;
    write_file(&dir.join(CA_FILE), &ca_cert.pem(), false)?;
    write_file(&dir.join("ca.key"), &ca_key.serialize_pem(), true)?;
    let issuer = Issuer::new(ca, ca_key);
    for r in Role::ALL {
        let key = KeyPair::generate().with_context(|| format!("generating the {} key", r.name()))?;
        let mut p = leaf(&r.common_name())?;
        validity(&mut p);
        let cert = p.signed_by(&key, &issuer).with_context(|| format!("signing the {} certificate", r.name()))?;
        write_file(&dir.join(format!("{}.pem", r.name())), &cert.pem(), false)?;
        write_file(&dir.join(format!("{}.key", r.name())), &key.serialize_pem(), true)?;
    }
    let stem = dir.join(MODEL_KEY_FILE).with_extension("");
    policy::signature::Signer::generate().write_pair(&stem).context("the model-signing key")?;
    let mut roster = Roster::default();
    set_slots(&mut roster, slots)?;
    replace_file(&dir.join(ROSTER_FILE), &roster.to_toml())?;
    names.push(ROSTER_FILE.to_string());
    Ok(names)
}

fn set_slots(roster: &mut Roster, slots: &[(Role, u32)]) -> Result<()> {
    for (role, n) in slots {
        anyhow::ensure!(
            protocol::secure::JOIN_ROLES.contains(role),
            "slots: {} machines do not join with a token (agent, learner or car)",
            role.name()
        );
        anyhow::ensure!(
            *n <= protocol::secure::MAX_SLOTS,
            "slots: {n} {} slots is more than {}",
            role.name(),
            protocol::secure::MAX_SLOTS
        );
        roster.set_slots(*role, *n);
    }
    Ok(())
}

/// `certs slots DIR --agent N …`: how many machines of each role may join with a token.
/// Growing takes effect on each node when it next starts (give it the new ids.toml);
/// shrinking below a slot that holds a valid certificate is refused.
pub fn slots(dir: &Path, slots: &[(Role, u32)]) -> Result<String> {
    let mut roster = Roster::load(dir)?;
    let (_, revoked) = revoked_in(dir)?;
    let now = time::OffsetDateTime::now_utc();
    for (role, n) in slots {
        for id in roster.slot_ids(*role).into_iter().skip(*n as usize) {
            let pem = dir.join(format!("{}.pem", stem(*role, Some(&id))));
            if pem.exists() {
                let (serial, _, until) = cert_info(&pem)?;
                anyhow::ensure!(
                    until < now || revoked.iter().any(|(s, _)| *s == serial),
                    "{}: {} {id} holds a valid certificate; revoke it (`coordinator certs revoke {} {}`) before \
                     shrinking the {} slots below it",
                    pem.display(),
                    role.name(),
                    dir.display(),
                    stem(*role, Some(&id)),
                    role.name()
                );
            }
        }
    }
    set_slots(&mut roster, slots)?;
    replace_file(&dir.join(ROSTER_FILE), &roster.to_toml())?;
    Ok(format!(
        "{}: {} agent, {} learner and {} car slots; give every node this ids.toml and restart it to cover new slots",
        dir.join(ROSTER_FILE).display(),
        roster.slots(Role::Agent),
        roster.slots(Role::Learner),
        roster.slots(Role::Car)
    ))
}

/// The cluster CA in `dir` (`ca.pem` and `ca.key`), ready to sign.
pub fn issuer(dir: &Path) -> Result<Issuer<'static, KeyPair>> {
    let read = |n: &str| {
        std::fs::read_to_string(dir.join(n)).with_context(|| {
            format!("{}: cannot read it (the CA's files, made by `coordinator certs new DIR`)", dir.join(n).display())
        })
    };
    let key = KeyPair::from_pem(&read("ca.key")?)
        .with_context(|| format!("{}: not a PEM key", dir.join("ca.key").display()))?;
    Issuer::from_ca_cert_pem(&read(CA_FILE)?, key)
        .with_context(|| format!("{}: not the CA certificate", dir.join(CA_FILE).display()))
}

/// A certificate file's serial number (hex, as a revocation list names it), common name and
/// expiry.
pub fn cert_info(path: &Path) -> Result<(Vec<u8>, String, time::OffsetDateTime)> {
    let text = std::fs::read(path).with_context(|| format!("{}: cannot read it", path.display()))?;
    let (_, pem) = x509_parser::pem::parse_x509_pem(&text)
        .map_err(|e| anyhow::anyhow!("{}: not a PEM certificate ({e})", path.display()))?;
    let cert = pem.parse_x509().map_err(|e| anyhow::anyhow!("{}: not a certificate ({e})", path.display()))?;
    let cn = cert.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("").to_string();
    Ok((cert.raw_serial().to_vec(), cn, cert.validity().not_after.to_datetime()))
}

/// Write `text` to `path` in one step (a temporary file renamed over it).
pub fn replace_file(path: &Path, text: &str) -> Result<()> {
    let tmp = path.with_extension("tmp");
    let _ = std::fs::remove_file(&tmp);
    write_file(&tmp, text, false)?;
    std::fs::rename(&tmp, path).with_context(|| format!("{}: cannot replace it", path.display()))
}

/// Certificates revoked: serial number, and when.
pub type RevokedList = Vec<(Vec<u8>, time::OffsetDateTime)>;

/// The revocation list in `dir`: its number and what it revokes.
pub fn revoked_in(dir: &Path) -> Result<(u64, RevokedList)> {
    let path = dir.join(protocol::revocation::CRL_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, Vec::new())),
        Err(e) => return Err(anyhow::anyhow!("{}: cannot read it ({e})", path.display())),
    };
    let der = protocol::revocation::der_of(&bytes).with_context(|| path.display().to_string())?;
    let (number, _) = protocol::revocation::contents(&der).with_context(|| path.display().to_string())?;
    let (_, crl) =
        <x509_parser::revocation_list::CertificateRevocationList as x509_parser::prelude::FromDer<_>>::from_der(&der)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let list =
        crl.iter_revoked_certificates().map(|r| (r.raw_serial().to_vec(), r.revocation_date.to_datetime())).collect();
    Ok((number, list))
}

/// `certs issue DIR console NAME...`: the console's web certificate for each name it is
/// reached by (a host name or an IP address: the certificate's subject alternative name),
/// `console-NAME.pem` with the CA's certificate after its own (the chain a browser needs) and
/// `console-NAME.key`, valid `days`. Not a cluster role: the roster is left as it is.
pub fn issue_console(dir: &Path, names: &[String], days: u32) -> Result<Vec<String>> {
    anyhow::ensure!(days > 0, "--days: expected at least 1");
    anyhow::ensure!(!names.is_empty(), "expected the names the console is reached by (a host name or an IP address)");
    let issuer = issuer(dir)?;
    let ca = std::fs::read_to_string(dir.join(CA_FILE)).with_context(|| dir.join(CA_FILE).display().to_string())?;
    let now = time::OffsetDateTime::now_utc();
    let mut written = Vec::new();
    for name in names {
        anyhow::ensure!(
            protocol::keys::is_valid_name(name) && !name.starts_with('.'),
            "'{name}': expected a host name or an IP address (letters, digits, '-', '_' and '.')"
        );
        let (pem, key) = (dir.join(format!("console-{name}.pem")), dir.join(format!("console-{name}.key")));
        anyhow::ensure!(!pem.exists(), "{}: already there; remove it (and its .key) to issue it again", pem.display());
        let k = KeyPair::generate().context("generating a key")?;
        let mut p = CertificateParams::new(vec![name.clone()]).with_context(|| format!("'{name}': not a host name"))?;
        p.distinguished_name = DistinguishedName::new();
        p.distinguished_name.push(DnType::CommonName, format!("paddock-console {name}"));
        p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
        p.not_before = now - time::Duration::hours(1);
        p.not_after = now + time::Duration::days(days.into());
        let cert = p.signed_by(&k, &issuer).with_context(|| format!("signing {name}'s certificate"))?;
        write_file(&pem, &format!("{}{ca}", cert.pem()), false)?;
        write_file(&key, &k.serialize_pem(), true)?;
        written.push(format!("console-{name}.pem"));
        written.push(format!("console-{name}.key"));
    }
    Ok(written)
}

/// `certs issue DIR ROLE ID...`: a certificate of its own for each machine (common name
/// `paddock-<role>.<id>`, files `<role>-<id>.pem`/`.key`), valid `days`, and the ids added to
/// the folder's roster (`ids.toml`). An id whose certificate is revoked may be issued anew.
pub fn issue(dir: &Path, role: &str, ids: &[String], days: u32) -> Result<Vec<String>> {
    let role = Role::from_name(role)
        .with_context(|| format!("role '{role}': expected one of {}", Role::ALL.map(|r| r.name()).join(", ")))?;
    anyhow::ensure!(days > 0, "--days: expected at least 1");
    let issuer = issuer(dir)?;
    let mut roster = Roster::load(dir)?;
    let (_, revoked) = revoked_in(dir)?;
    let now = time::OffsetDateTime::now_utc();
    let mut written = Vec::new();
    for id in ids {
        anyhow::ensure!(
            protocol::keys::is_valid_name(id),
            "id '{id}': expected letters, digits, '-', '_' and '.' (at most 128)"
        );
        let s = stem(role, Some(id));
        let (pem, key) = (dir.join(format!("{s}.pem")), dir.join(format!("{s}.key")));
        if pem.exists() {
            let (serial, _, _) = cert_info(&pem)?;
            anyhow::ensure!(
                revoked.iter().any(|(r, _)| *r == serial),
                "{}: {id} already has a certificate; revoke it first (`coordinator certs revoke {} {s}`)",
                pem.display(),
                dir.display()
            );
            std::fs::remove_file(&pem).with_context(|| format!("{}: cannot replace it", pem.display()))?;
            let _ = std::fs::remove_file(&key);
        }
        let k = KeyPair::generate().context("generating a key")?;
        let mut p = leaf(&role.common_name_of(id))?;
        p.not_before = now - time::Duration::hours(1);
        p.not_after = now + time::Duration::days(days.into());
        let cert = p.signed_by(&k, &issuer).with_context(|| format!("signing {id}'s certificate"))?;
        write_file(&pem, &cert.pem(), false)?;
        write_file(&key, &k.serialize_pem(), true)?;
        roster.add(role, id);
        written.push(format!("{s}.pem"));
        written.push(format!("{s}.key"));
    }
    replace_file(&dir.join(ROSTER_FILE), &roster.to_toml())?;
    Ok(written)
}

/// The certificate file a name given to `certs revoke` means: a file stem (`agent-lab-1`,
/// `agent`) or a machine's id when one role has it.
fn resolve(dir: &Path, name: &str) -> Result<std::path::PathBuf> {
    anyhow::ensure!(protocol::keys::is_valid_name(name), "'{name}': expected a certificate's name, like agent-lab-1");
    let direct = dir.join(format!("{name}.pem"));
    if direct.exists() && name != "ca" {
        return Ok(direct);
    }
    let found: Vec<_> =
        Role::ALL.iter().map(|r| dir.join(format!("{}.pem", stem(*r, Some(name))))).filter(|p| p.exists()).collect();
    match found.as_slice() {
        [one] => Ok(one.clone()),
        [] => bail!("{}: no certificate named '{name}' (expected a file like agent-lab-1.pem there)", dir.display()),
        many => bail!(
            "'{name}' is the id of several machines ({}); give the file's name",
            many.iter().filter_map(|p| p.file_stem()?.to_str()).collect::<Vec<_>>().join(", ")
        ),
    }
}

/// `certs revoke DIR NAME...`: add the certificates to the CA's revocation list
/// (`crl.pem`, its number one higher); a running coordinator hands it to every node within
/// seconds. Returns each name with whether it was newly revoked.
pub fn revoke(dir: &Path, names: &[String]) -> Result<Vec<(String, bool)>> {
    let issuer = issuer(dir)?;
    let (number, mut list) = revoked_in(dir)?;
    let now = time::OffsetDateTime::now_utc();
    let mut out = Vec::new();
    for name in names {
        let path = resolve(dir, name)?;
        let (serial, cn, _) = cert_info(&path)?;
        let new = !list.iter().any(|(s, _)| *s == serial);
        if new {
            list.push((serial, now));
        }
        out.push((format!("{cn} ({})", path.display()), new));
    }
    let params = rcgen::CertificateRevocationListParams {
        this_update: now,
        next_update: now + time::Duration::days(365 * YEARS as i64),
        crl_number: rcgen::SerialNumber::from((number + 1).to_be_bytes().to_vec()),
        issuing_distribution_point: None,
        revoked_certs: list
            .into_iter()
            .map(|(serial, when)| rcgen::RevokedCertParams {
                serial_number: rcgen::SerialNumber::from(serial),
                revocation_time: when,
                reason_code: Some(rcgen::RevocationReason::KeyCompromise),
                invalidity_date: None,
            })
            .collect(),
        key_identifier_method: rcgen::KeyIdMethod::Sha256,
    };
    let crl = params.signed_by(&issuer).context("signing the revocation list")?;
    replace_file(&dir.join(protocol::revocation::CRL_FILE), &crl.pem().context("the revocation list's PEM")?)?;
    Ok(out)
}

/// `certs list DIR`: every certificate in the folder with its common name, expiry and
/// whether it is revoked or expired.
pub fn list(dir: &Path) -> Result<Vec<String>> {
    let (number, revoked) = revoked_in(dir)?;
    let now = time::OffsetDateTime::now_utc();
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot read the folder", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "pem") && p.file_stem().is_some_and(|s| s != "ca" && s != "crl"))
        .collect();
    files.sort();
    let mut rows = vec![format!("{:<28} {:<36} {:<12} status", "file", "common name", "expires")];
    for f in files {
        let (serial, cn, until) = cert_info(&f)?;
        let status = if revoked.iter().any(|(s, _)| *s == serial) {
            "REVOKED"
        } else if until < now {
            "EXPIRED"
        } else {
            "valid"
        };
        let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("?");
        rows.push(format!("{name:<28} {cn:<36} {:<12} {status}", until.date().to_string()));
    }
    rows.push(format!("revocation list number {number}, {} certificate(s) revoked", revoked.len()));
    Ok(rows)
}
