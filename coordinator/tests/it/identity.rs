//! One identity per machine (issue 35): certificates issued per machine, bound by every
//! node's access rules to their own id; a certificate revoked with `certs revoke` is refused
//! by every node within seconds, its open links closed; an expired one never connects. Real
//! coordinator, real Zenoh over mutual TLS on loopback, OpenSSL as the outside check.

use crate::support::{bin, free_port};
use protocol::net::{self, NetArgs, zenoh};
use protocol::secure::Role;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn certs(dir: &Path, args: &[&str]) -> String {
    let o = Command::new(bin("coordinator")).arg("certs").args(args).current_dir(dir).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "certs {args:?}: {text}");
    text
}

/// OpenSSL's verdict on a certificate, with the folder's revocation list when it has one.
fn openssl_verify(d: &Path, cert: &str) -> bool {
    let mut c = Command::new("openssl");
    c.args(["verify", "-CAfile", "ca.pem"]);
    if d.join("crl.pem").exists() {
        c.args(["-crl_check", "-CRLfile", "crl.pem"]);
    }
    let o = c.arg(cert).current_dir(d).output().expect("openssl (./paddock test installs it)");
    o.status.success()
}

/// Keys the receiver got, in order.
type Seen = Arc<Mutex<Vec<String>>>;

/// Put on `key` every 100 ms until the receiver gets one more sample of it (true) or
/// `within` passes (false).
fn reaches(seen: &Seen, from: &zenoh::Session, key: &str, within: Duration) -> bool {
    let count = || seen.lock().unwrap().iter().filter(|k| *k == key).count();
    let (t, had) = (Instant::now(), count());
    while t.elapsed() < within {
        from.put(key, b"x".to_vec()).wait().unwrap();
        std::thread::sleep(Duration::from_millis(100));
        if count() > had {
            return true;
        }
    }
    false
}

/// An agent certificate for `id` valid from `from` to `until`, signed by the folder's CA,
/// its id added to the roster.
fn agent_cert(d: &Path, id: &str, from: time::OffsetDateTime, until: time::OffsetDateTime) {
    let key = rcgen::KeyPair::from_pem(&std::fs::read_to_string(d.join("ca.key")).unwrap()).unwrap();
    let issuer = rcgen::Issuer::from_ca_cert_pem(&std::fs::read_to_string(d.join("ca.pem")).unwrap(), key).unwrap();
    let k = rcgen::KeyPair::generate().unwrap();
    let mut p = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    p.distinguished_name.push(rcgen::DnType::CommonName, Role::Agent.common_name_of(id));
    p.extended_key_usages =
        vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth, rcgen::ExtendedKeyUsagePurpose::ClientAuth];
    (p.not_before, p.not_after) = (from, until);
    let cert = p.signed_by(&k, &issuer).unwrap();
    std::fs::write(d.join(format!("agent-{id}.pem")), cert.pem()).unwrap();
    std::fs::write(d.join(format!("agent-{id}.key")), k.serialize_pem()).unwrap();
    let mut roster = protocol::secure::Roster::load(d).unwrap();
    roster.add(Role::Agent, id);
    std::fs::write(d.join("ids.toml"), roster.to_toml()).unwrap();
}

/// Issue 35: each machine speaks only for itself and a revoked or expired certificate is refused.
#[test]
fn each_machine_speaks_only_for_itself_and_a_revoked_or_expired_certificate_is_refused() {
    protocol::secure::init_logging("warn");
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("certs");
    let ds = d.display().to_string();
    certs(tmp.path(), &["new", &ds]);
    let out = certs(tmp.path(), &["issue", &ds, "agent", "lab-1", "lab-2"]);
    assert!(out.contains("agent-lab-1.pem") && out.contains("ids.toml"), "{out}");
    certs(tmp.path(), &["issue", &ds, "learner", "gpu-1"]);
    // A certificate that expired yesterday and one that expires during the test, signed by the
    // cluster's CA, their ids on the roster.
    let now = time::OffsetDateTime::now_utc();
    agent_cert(&d, "old", now - time::Duration::days(30), now - time::Duration::days(1));
    let short_until = Instant::now() + Duration::from_secs(12);
    agent_cert(&d, "short", now - time::Duration::days(1), now + time::Duration::seconds(12));
    // OpenSSL agrees with what Paddock wrote.
    assert!(openssl_verify(&d, "agent-lab-1.pem") && !openssl_verify(&d, "agent-old.pem"));

    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let log = std::fs::File::create(tmp.path().join("coordinator.log")).unwrap();
    let _coordinator = Killed(
        Command::new(bin("coordinator"))
            .args(["serve", "--listen", &endpoint, "--db"])
            .arg(tmp.path().join("c.redb"))
            .args(["--certs", &ds])
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap(),
    );
    let base = NetArgs { connect: vec![endpoint.clone()], certs: Some(d.clone()), ..Default::default() };
    let open = |a: NetArgs| net::open(&a).unwrap();
    // The receiver listens where every agent dials it: its refusals are this process's.
    let receiver_ep = format!("tls/127.0.0.1:{}", free_port());
    let learner = open(NetArgs { listen: vec![receiver_ep.clone()], ..base.clone() }.as_role(Role::Learner));
    let _token = learner.liveliness().declare_token("paddock/v1/alive/learner/recv").wait().unwrap();
    let seen: Seen = Arc::default();
    let s2 = seen.clone();
    let _sub = learner
        .declare_subscriber("paddock/v1/job/j/experience/**")
        .callback(move |s| s2.lock().unwrap().push(s.key_expr().to_string()))
        .wait()
        .unwrap();
    let agents = NetArgs { connect: vec![receiver_ep.clone(), endpoint.clone()], ..base.clone() };
    let lab1 = open(agents.clone().as_machine(Role::Agent, "lab-1"));
    let lab2 = open(agents.clone().as_machine(Role::Agent, "lab-2"));
    // No --id and several machines' files in the folder: the role-wide certificate.
    let wide = open(agents.clone().as_role(Role::Agent));
    let old = open(agents.clone().as_machine(Role::Agent, "old"));
    let short = open(agents.clone().as_machine(Role::Agent, "short"));
    let key = |id: &str| protocol::keys::experience("j", id);
    let wait = Duration::from_secs(20);
    let refused = |what: &str| protocol::secure::REFUSED.reasons().iter().any(|(r, _)| r.contains(what));
    let until = |what: &str, ok: &dyn Fn() -> bool| {
        let t = Instant::now();
        while !ok() {
            assert!(t.elapsed() < wait, "{what}: {:?}", protocol::secure::REFUSED.reasons());
            std::thread::sleep(Duration::from_millis(100));
        }
    };

    // Each machine sends as itself; the role-wide certificate may still speak for any agent.
    assert!(reaches(&seen, &lab1, &key("lab-1"), wait), "lab-1's own experience");
    assert!(reaches(&seen, &lab2, &key("lab-2"), wait), "lab-2's own experience");
    assert!(reaches(&seen, &wide, &key("anyone"), wait), "the role-wide certificate");
    assert!(reaches(&seen, &short, &key("short"), short_until - Instant::now()), "before its expiry");
    // lab-1 posing as lab-2 is refused by the receiver's access rules, and counted by name:
    // its own experience, sent after, arrives; the forged puts before it (same link, in
    // order) do not.
    let before = seen.lock().unwrap().len();
    for _ in 0..10 {
        lab1.put(key("lab-2"), b"forged".to_vec()).wait().unwrap();
    }
    assert!(reaches(&seen, &lab1, &key("lab-1"), wait));
    let after: Vec<String> = seen.lock().unwrap()[before..].to_vec();
    assert!(!after.iter().any(|k| *k == key("lab-2")), "lab-1 sent as lab-2: {after:?}");
    let reasons = protocol::secure::REFUSED.reasons();
    assert!(
        reasons.iter().any(|(r, _)| r.contains("agent lab-1 may not put on paddock/v1/job/*/experience/lab-2")),
        "{reasons:?}"
    );
    // Liveliness too: lab-1's token under its own id is taken, one under lab-2's refused.
    let _own = lab1.liveliness().declare_token("paddock/v1/alive/agent/lab-1").wait().unwrap();
    let _posing = lab1.liveliness().declare_token("paddock/v1/alive/agent/lab-2").wait().unwrap();
    until("lab-1's token as lab-2 refused", &|| {
        refused("agent lab-1 may not liveliness token on paddock/v1/alive/agent/lab-2")
    });
    assert!(!refused("on paddock/v1/alive/agent/lab-1"), "{:?}", protocol::secure::REFUSED.reasons());
    // The expired certificate is refused at the handshake, and never heard.
    until("the expired certificate refused", &|| refused("invalid peer certificate: certificate expired"));
    assert!(!reaches(&seen, &old, &key("old"), Duration::from_secs(1)), "an expired certificate connected");
    // A learner with its own certificate watches every learner's token (a team's need).
    let gpu = open(base.clone().as_machine(Role::Learner, "gpu-1"));
    until("gpu-1 sees the other learner", &|| {
        let r = gpu.liveliness().get("paddock/v1/alive/learner/*").timeout(Duration::from_secs(1)).wait().unwrap();
        std::iter::from_fn(|| r.recv().ok()).any(|r| r.result().is_ok_and(|s| s.key_expr().as_str().ends_with("/recv")))
    });

    // Revoke lab-1 while it is connected: the running coordinator hands the list to every node,
    // which closes its links to lab-1 and refuses it from then on; lab-2 carries on.
    let out = certs(tmp.path(), &["revoke", &ds, "lab-1"]);
    assert!(out.contains("revoked paddock-agent.lab-1"), "{out}");
    assert!(!openssl_verify(&d, "agent-lab-1.pem") && openssl_verify(&d, "agent-lab-2.pem"));
    let t = Instant::now();
    while protocol::revocation::held().map(|h| h.0) != Some(1) {
        assert!(t.elapsed() < Duration::from_secs(20), "the revocation list never arrived");
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs(1));
    assert!(!reaches(&seen, &lab1, &key("lab-1"), Duration::from_secs(2)), "a revoked machine was heard");
    assert!(reaches(&seen, &lab2, &key("lab-2"), wait), "lab-2 after lab-1's revocation");
    // lab-1 dials again and is refused at the handshake (not only cut off after it), and the
    // coordinator's own process took the list from the folder.
    until("the revoked certificate refused", &|| refused("invalid peer certificate: Revoked"));
    let log = std::fs::read_to_string(tmp.path().join("coordinator.log")).unwrap();
    assert!(log.contains("revocation list in force"), "{log}");
    let listed = certs(tmp.path(), &["list", &ds]);
    let status = |f: &str| listed.lines().find(|l| l.starts_with(f)).map(|l| l.split_whitespace().last().unwrap_or(""));
    assert_eq!(
        (status("agent-lab-1.pem"), status("agent-lab-2.pem"), status("agent-old.pem")),
        (Some("REVOKED"), Some("valid"), Some("EXPIRED")),
        "{listed}"
    );
    // The certificate that expired meanwhile: its links were closed, and it is not heard.
    std::thread::sleep(short_until.saturating_duration_since(Instant::now()) + Duration::from_secs(1));
    assert!(!reaches(&seen, &short, &key("short"), Duration::from_secs(2)), "heard after its certificate expired");
    // A revoked id may be issued anew (a new key); the list keeps the old one revoked.
    std::fs::copy(d.join("agent-lab-1.pem"), d.join("lab-1-before.pem")).unwrap();
    certs(tmp.path(), &["issue", &ds, "agent", "lab-1"]);
    assert!(openssl_verify(&d, "agent-lab-1.pem") && !openssl_verify(&d, "lab-1-before.pem"));
}
