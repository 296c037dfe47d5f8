//! `certs new DIR`: the cluster's credentials. One CA (ECDSA P-256, allowed to sign only
//! certificates directly under it) and one certificate per role, its common name
//! `paddock-<role>` (what the access rules of `protocol::secure` match), usable for both ends
//! of a mutual-TLS link; and the learners' model-signing key (`models.key`, `models.pub`):
//! learners given the folder sign with it, agents and cars given it trust what it signs.
//! Keys are written readable by their owner only.

use anyhow::{Context, Result, bail};
use protocol::secure::{CA_FILE, MODEL_KEY_FILE, MODEL_PUB_FILE, Role};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose, date_time_ymd,
};
use std::path::Path;

/// Years a credential set is valid.
const YEARS: i32 = 10;

fn this_year() -> i32 {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    1970 + (secs / 31_556_952) as i32
}

fn write_file(path: &Path, text: &str, secret: bool) -> Result<()> {
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

/// Write a CA and every role's certificate and key into `dir`. Existing credentials are kept
/// unless `force` (a new CA makes every certificate already handed out useless).
pub fn write(dir: &Path, force: bool) -> Result<Vec<String>> {
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
        let mut p = CertificateParams::new(vec!["localhost".to_string()]).context("certificate parameters")?;
        p.distinguished_name = DistinguishedName::new();
        p.distinguished_name.push(DnType::CommonName, r.common_name());
        p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
        validity(&mut p);
        let cert = p.signed_by(&key, &issuer).with_context(|| format!("signing the {} certificate", r.name()))?;
        write_file(&dir.join(format!("{}.pem", r.name())), &cert.pem(), false)?;
        write_file(&dir.join(format!("{}.key", r.name())), &key.serialize_pem(), true)?;
    }
    let stem = dir.join(MODEL_KEY_FILE).with_extension("");
    policy::signature::Signer::generate().write_pair(&stem).context("the model-signing key")?;
    Ok(names)
}
