//! The console's users: DeepRacer on AWS's three roles (admin, race facilitator, racer),
//! passwords hashed with argon2id, invitations, per-user quotas. They are kept in the data
//! folder's `users.json`, read again whenever another process (`coordinator users …`) changed
//! it, and written whole under a lock (a temporary file renamed over it): two writers never
//! lose each other's change, and a crash never leaves half a file.
//!
//! While the file holds no user the console runs on its single token ([`crate::auth`]); once it
//! holds one, it asks for a login.

use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::SystemTime;

/// The file in the data folder.
pub const FILE: &str = "users.json";

/// A role, in the order of what it may do (each may do what the ones below it may).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Trains, evaluates and imports their own models; enters races.
    Racer,
    /// Also sees every racer's models and downloads them; creates and runs races.
    Facilitator,
    /// Also manages users and quotas.
    Admin,
}

impl Role {
    /// Its name, as the API and the CLI write it.
    pub fn name(self) -> &'static str {
        match self {
            Role::Racer => "racer",
            Role::Facilitator => "facilitator",
            Role::Admin => "admin",
        }
    }

    /// Parse `admin`, `facilitator` or `racer`.
    pub fn parse(s: &str) -> Result<Role, UsersError> {
        match s {
            "racer" => Ok(Role::Racer),
            "facilitator" => Ok(Role::Facilitator),
            "admin" => Ok(Role::Admin),
            other => Err(UsersError::Invalid {
                field: "role".into(),
                message: format!("'{other}' is not a role; expected admin, facilitator or racer"),
            }),
        }
    }
}

/// What a user may spend (none: no limit).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quota {
    /// Models they may have.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub models: Option<u32>,
    /// Minutes of training and evaluation they may spend.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub minutes: Option<f64>,
}

/// An invitation not yet taken: the hash of its secret and when it ends.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Invitation {
    /// SHA-256 of the secret, hex (the secret itself is only in the link).
    pub secret_sha256: String,
    /// Unix seconds.
    pub expires: f64,
}

/// One user.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct User {
    /// The name they log in with.
    pub name: String,
    /// Their role.
    pub role: Role,
    /// The argon2id hash (PHC string); none until an invitation is taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub password: Option<String>,
    /// Unix seconds.
    pub created: f64,
    /// An invitation not yet taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub invitation: Option<Invitation>,
    /// Their quota.
    #[serde(default)]
    pub quota: Quota,
}

impl User {
    /// The user as the API shows it: no hash, no invitation's secret.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "name": self.name, "role": self.role.name(), "created": self.created, "quota": self.quota,
            "invited": self.password.is_none(),
            "invitation_expires": self.invitation.as_ref().map(|i| i.expires),
        })
    }
}

/// Why a users operation failed.
#[derive(Debug, thiserror::Error)]
pub enum UsersError {
    /// A field is wrong.
    #[error("{field}: {message}")]
    Invalid {
        /// The field.
        field: String,
        /// What is wrong and what was expected.
        message: String,
    },
    /// No such user.
    #[error("no user named '{0}'")]
    NotFound(String),
    /// The name is taken.
    #[error("a user named '{0}' already exists")]
    Taken(String),
    /// The last admin cannot go.
    #[error("'{0}' is the last admin: make another admin first")]
    LastAdmin(String),
    /// The file could not be read or written.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

fn invalid(field: &str, message: impl Into<String>) -> UsersError {
    UsersError::Invalid { field: field.into(), message: message.into() }
}

/// DeepRacer on AWS's rule for a racer's alias, here a user's name: 2 to 64 letters, digits,
/// `-`, `_` or `.`.
pub fn name_problem(name: &str) -> Option<String> {
    let ok = (2..=64).contains(&name.chars().count())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
    (!ok).then(|| "2 to 64 letters, digits, '-', '_' or '.'".to_string())
}

/// DeepRacer on AWS's password rule (its user pool's): at least 8 characters with an upper-case
/// letter, a lower-case letter, a digit and a symbol; at most 256.
pub fn password_problem(password: &str) -> Option<String> {
    let n = password.chars().count();
    let has = |f: fn(char) -> bool| password.chars().any(f);
    let ok = (8..=256).contains(&n)
        && has(|c| c.is_uppercase())
        && has(|c| c.is_lowercase())
        && has(|c| c.is_ascii_digit())
        && has(|c| !c.is_alphanumeric() && !c.is_whitespace());
    (!ok).then(|| {
        "8 to 256 characters, with an upper-case letter, a lower-case letter, a digit and a symbol".to_string()
    })
}

/// A new password that meets [`password_problem`]'s rule: 20 random letters and digits, and
/// one of each class the rule asks for.
pub fn new_password() -> String {
    use rand::Rng;
    const ALPHABET: &[u8] = b"abcdefghijkmnopqrstuvwxyzABCDEFGHJKLMNPQRSTUVWXYZ23456789";
    let mut rng = rand::rng();
    let body: String = (0..20).map(|_| ALPHABET[rng.random_range(0..ALPHABET.len())] as char).collect();
    format!("{body}-Aa1")
}

/// argon2id (the crate's defaults: 19 MiB, 2 passes, 1 lane; OWASP's minimum), salted.
pub fn hash_password(password: &str) -> String {
    let salt_bytes: [u8; 16] = rand::random();
    let salt = SaltString::encode_b64(&salt_bytes).expect("16 bytes make a salt");
    argon2::Argon2::default().hash_password(password.as_bytes(), &salt).expect("argon2 hashes any password").to_string()
}

/// Whether `password` matches the PHC string `hash` (argon2's comparison is constant-time).
pub fn verify_password(password: &str, hash: &str) -> bool {
    PasswordHash::new(hash).is_ok_and(|h| argon2::Argon2::default().verify_password(password.as_bytes(), &h).is_ok())
}

fn sha256_hex(s: &str) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(s.as_bytes()))
}

fn now() -> f64 {
    SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// The file: the instance's quota and the users.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UsersFile {
    /// What every user together may spend.
    #[serde(default)]
    pub instance_quota: Quota,
    /// The users.
    #[serde(default)]
    pub users: Vec<User>,
}

/// The users of a data folder.
pub struct Users {
    path: PathBuf,
    lock: PathBuf,
    /// The file as last read, and what it was then (see [`Stamp`]).
    cache: Mutex<(UsersFile, Option<Stamp>)>,
}

/// What tells one version of the file from the next: every write is a new file renamed over
/// the old (a new inode), and the modification time alone is too coarse (a few milliseconds).
type Stamp = (u64, SystemTime, u64);

fn stamp(path: &Path) -> Option<Stamp> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).ok()?;
    Some((m.ino(), m.modified().ok()?, m.len()))
}

impl Users {
    /// The users of the data folder `data` (none while it has no `users.json`); a file that does
    /// not parse is an error naming it.
    pub fn open(data: &Path) -> Result<Users, UsersError> {
        let u = Users {
            path: data.join(FILE),
            lock: data.join("users.lock"),
            cache: Mutex::new((UsersFile::default(), None)),
        };
        u.fresh()?;
        Ok(u)
    }

    fn file_error(&self, e: impl std::fmt::Display) -> UsersError {
        UsersError::File { path: self.path.display().to_string(), message: e.to_string() }
    }

    fn read(&self) -> Result<(UsersFile, Option<Stamp>), UsersError> {
        let modified = match std::fs::metadata(&self.path) {
            Ok(_) => stamp(&self.path),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((UsersFile::default(), None)),
            Err(e) => return Err(self.file_error(e)),
        };
        let text = std::fs::read_to_string(&self.path).map_err(|e| self.file_error(e))?;
        let file: UsersFile = serde_json::from_str(&text)
            .map_err(|e| self.file_error(format!("expected {{\"instance_quota\", \"users\": [...]}}: {e}")))?;
        Ok((file, modified))
    }

    /// The file now: the cache, read again when the file changed.
    fn file(&self) -> Result<UsersFile, UsersError> {
        let modified = stamp(&self.path);
        let mut cache = self.cache.lock().expect("users");
        if modified != cache.1 || modified.is_none() {
            *cache = self.read()?;
        }
        Ok(cache.0.clone())
    }

    /// The users now.
    fn fresh(&self) -> Result<Vec<User>, UsersError> {
        self.file().map(|f| f.users)
    }

    /// What every user together may spend.
    pub fn instance_quota(&self) -> Quota {
        self.file().map(|f| f.instance_quota).unwrap_or_default()
    }

    /// Set what every user together may spend.
    pub fn set_instance_quota(&self, quota: Quota) -> Result<Quota, UsersError> {
        if quota.minutes.is_some_and(|m| !(m.is_finite() && m >= 0.0)) {
            return Err(invalid("minutes", "a number of minutes, 0 or more"));
        }
        self.change_file(|f| {
            f.instance_quota = quota.clone();
            Ok(quota)
        })
    }

    /// Every user, by name.
    pub fn list(&self) -> Vec<User> {
        match self.fresh() {
            Ok(mut v) => {
                v.sort_by(|a, b| a.name.cmp(&b.name));
                v
            }
            Err(e) => {
                tracing::error!("{e}");
                Vec::new()
            }
        }
    }

    /// Whether the console asks for a login: the folder has a user. A file that cannot be read
    /// counts as having one (the console does not fall back to its token).
    pub fn any(&self) -> bool {
        self.fresh().map(|v| !v.is_empty()).unwrap_or(true)
    }

    /// One user.
    pub fn get(&self, name: &str) -> Option<User> {
        self.fresh().ok()?.into_iter().find(|u| u.name == name)
    }

    /// Change the users under the lock, from the file as it is now, and write it whole.
    fn change<T>(&self, f: impl FnOnce(&mut Vec<User>) -> Result<T, UsersError>) -> Result<T, UsersError> {
        self.change_file(|file| f(&mut file.users))
    }

    /// Change the file under the lock, from the file as it is now, and write it whole.
    fn change_file<T>(&self, f: impl FnOnce(&mut UsersFile) -> Result<T, UsersError>) -> Result<T, UsersError> {
        let lock = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&self.lock)
            .map_err(|e| self.file_error(e))?;
        lock.lock().map_err(|e| self.file_error(e))?;
        let (mut file, _) = self.read()?;
        let out = f(&mut file)?;
        let tmp = self.path.with_extension("json.tmp");
        let text = serde_json::to_string_pretty(&file).expect("users serialise");
        write_private(&tmp, text.as_bytes()).map_err(|e| self.file_error(e))?;
        std::fs::rename(&tmp, &self.path).map_err(|e| self.file_error(e))?;
        *self.cache.lock().expect("users") = (file, stamp(&self.path));
        Ok(out)
    }

    /// Add a user with a password.
    pub fn add(&self, name: &str, role: Role, password: &str) -> Result<User, UsersError> {
        check_name(name)?;
        if let Some(p) = password_problem(password) {
            return Err(invalid("password", p));
        }
        let hash = hash_password(password);
        self.change(|users| {
            if users.iter().any(|u| u.name == name) {
                return Err(UsersError::Taken(name.into()));
            }
            let u = User {
                name: name.into(),
                role,
                password: Some(hash),
                created: now(),
                invitation: None,
                quota: Quota::default(),
            };
            users.push(u.clone());
            Ok(u)
        })
    }

    /// Invite a user: they have no password until they take the invitation, whose secret this
    /// returns (it is kept only as a hash) and which ends after `ttl_s` seconds. Inviting a user
    /// again replaces their invitation.
    pub fn invite(&self, name: &str, role: Role, ttl_s: f64) -> Result<String, UsersError> {
        check_name(name)?;
        let secret = crate::auth::new_token();
        let invitation = Invitation { secret_sha256: sha256_hex(&secret), expires: now() + ttl_s };
        self.change(|users| {
            match users.iter_mut().find(|u| u.name == name) {
                Some(u) if u.password.is_some() => return Err(UsersError::Taken(name.into())),
                Some(u) => {
                    u.role = role;
                    u.invitation = Some(invitation);
                }
                None => users.push(User {
                    name: name.into(),
                    role,
                    password: None,
                    created: now(),
                    invitation: Some(invitation),
                    quota: Quota::default(),
                }),
            }
            Ok(secret)
        })
    }

    /// Take an invitation: set the password of the user it names; their name.
    pub fn accept(&self, secret: &str, password: &str) -> Result<String, UsersError> {
        if let Some(p) = password_problem(password) {
            return Err(invalid("password", p));
        }
        let hash = hash_password(password);
        let digest = sha256_hex(secret);
        let t = now();
        self.change(|users| {
            let u = users
                .iter_mut()
                .find(|u| u.invitation.as_ref().is_some_and(|i| crate::auth::same(&i.secret_sha256, &digest)))
                .ok_or_else(|| invalid("invitation", "no such invitation: it was taken, replaced or never made"))?;
            if u.invitation.as_ref().is_some_and(|i| i.expires < t) {
                return Err(invalid("invitation", "the invitation has expired: ask for a new one"));
            }
            u.invitation = None;
            u.password = Some(hash);
            Ok(u.name.clone())
        })
    }

    /// Change a user's role (the last admin keeps theirs).
    pub fn set_role(&self, name: &str, role: Role) -> Result<User, UsersError> {
        self.change(|users| {
            let admins = users.iter().filter(|u| u.role == Role::Admin).count();
            let u = users.iter_mut().find(|u| u.name == name).ok_or_else(|| UsersError::NotFound(name.into()))?;
            if u.role == Role::Admin && role != Role::Admin && admins == 1 {
                return Err(UsersError::LastAdmin(name.into()));
            }
            u.role = role;
            Ok(u.clone())
        })
    }

    /// Set a user's quota.
    pub fn set_quota(&self, name: &str, quota: Quota) -> Result<User, UsersError> {
        if quota.minutes.is_some_and(|m| !(m.is_finite() && m >= 0.0)) {
            return Err(invalid("minutes", "a number of minutes, 0 or more"));
        }
        self.change(|users| {
            let u = users.iter_mut().find(|u| u.name == name).ok_or_else(|| UsersError::NotFound(name.into()))?;
            u.quota = quota;
            Ok(u.clone())
        })
    }

    /// Remove a user (not the last admin).
    pub fn remove(&self, name: &str) -> Result<(), UsersError> {
        self.change(|users| {
            let i = users.iter().position(|u| u.name == name).ok_or_else(|| UsersError::NotFound(name.into()))?;
            if users[i].role == Role::Admin && users.iter().filter(|u| u.role == Role::Admin).count() == 1 {
                return Err(UsersError::LastAdmin(name.into()));
            }
            users.remove(i);
            Ok(())
        })
    }

    /// The user if `password` is theirs. An unknown name costs the same hashing as a known one,
    /// so that the time taken does not tell which names exist.
    pub fn verify(&self, name: &str, password: &str) -> Option<User> {
        static DUMMY: std::sync::OnceLock<String> = std::sync::OnceLock::new();
        let user = self.get(name);
        let hash = match user.as_ref().and_then(|u| u.password.clone()) {
            Some(h) => h,
            None => DUMMY.get_or_init(|| hash_password("not a password: Aa1-")).clone(),
        };
        let ok = verify_password(password, &hash);
        user.filter(|u| ok && u.password.is_some())
    }
}

fn check_name(name: &str) -> Result<(), UsersError> {
    match name_problem(name) {
        Some(p) => Err(invalid("name", p)),
        None => Ok(()),
    }
}

/// Write a file only its owner reads (it holds password hashes).
fn write_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new().create(true).truncate(true).write(true).mode(0o600).open(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    const PW: &str = "Correct-horse-9";

    /// Issue 52: a user is added, found by their password only, changed and removed; the last
    /// admin stays; a second handle on the folder (another process) sees every change.
    #[test]
    fn users_are_kept_in_the_data_folder_and_seen_by_every_process() {
        let dir = tempfile::tempdir().unwrap();
        let a = Users::open(dir.path()).unwrap();
        assert!(!a.any());
        a.add("ada", Role::Admin, PW).unwrap();
        let b = Users::open(dir.path()).unwrap();
        assert!(b.any());
        assert_eq!(b.verify("ada", PW).map(|u| u.role), Some(Role::Admin));
        assert!(b.verify("ada", "Correct-horse-8").is_none());
        assert!(b.verify("nobody", PW).is_none());
        assert!(matches!(b.add("ada", Role::Racer, PW), Err(UsersError::Taken(_))));
        b.add("rita", Role::Racer, PW).unwrap();
        assert_eq!(a.get("rita").map(|u| u.role), Some(Role::Racer), "the first handle reads the change");
        assert!(matches!(a.set_role("ada", Role::Racer), Err(UsersError::LastAdmin(_))));
        assert!(matches!(a.remove("ada"), Err(UsersError::LastAdmin(_))));
        a.set_role("rita", Role::Facilitator).unwrap();
        a.set_quota("rita", Quota { models: Some(2), minutes: Some(30.0) }).unwrap();
        let rita = b.get("rita").unwrap();
        assert_eq!((rita.role, rita.quota.models), (Role::Facilitator, Some(2)));
        a.set_instance_quota(Quota { models: Some(10), minutes: None }).unwrap();
        assert_eq!(b.instance_quota().models, Some(10));
        b.remove("rita").unwrap();
        assert!(a.get("rita").is_none());
        let text = std::fs::read_to_string(dir.path().join(FILE)).unwrap();
        assert!(text.contains("$argon2id$") && !text.contains(PW), "{text}");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(dir.path().join(FILE)).unwrap().permissions().mode();
        assert_eq!(mode & 0o077, 0, "only its owner reads it");
    }

    /// Issue 52: an invitation is taken once, before it ends, with a password that meets the
    /// rule; its secret is not in the file.
    #[test]
    fn an_invitation_is_taken_once_before_it_ends() {
        let dir = tempfile::tempdir().unwrap();
        let u = Users::open(dir.path()).unwrap();
        let secret = u.invite("rex", Role::Racer, 3600.0).unwrap();
        assert!(!std::fs::read_to_string(dir.path().join(FILE)).unwrap().contains(&secret));
        assert!(u.verify("rex", PW).is_none(), "no password before the invitation is taken");
        assert!(matches!(u.accept(&secret, "short"), Err(UsersError::Invalid { .. })));
        assert_eq!(u.accept(&secret, PW).unwrap(), "rex");
        assert!(u.verify("rex", PW).is_some());
        assert!(u.accept(&secret, PW).is_err(), "taken once");
        let late = u.invite("ray", Role::Racer, -1.0).unwrap();
        let e = u.accept(&late, PW).unwrap_err().to_string();
        assert!(e.contains("expired"), "{e}");
    }

    #[test]
    fn names_and_passwords_follow_deepracers_rules() {
        for (name, ok) in [("ada", true), ("a", false), ("rita.m_2-x", true), ("<img>", false), ("x y", false)] {
            assert_eq!(name_problem(name).is_none(), ok, "{name}");
        }
        for (pw, ok) in
            [(PW, true), ("short1A!", true), ("alllower1!", false), ("NoDigits!!", false), ("NoSymbol12", false)]
        {
            assert_eq!(password_problem(pw).is_none(), ok, "{pw}");
        }
        assert!(password_problem(&new_password()).is_none());
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(FILE), "{ not json").unwrap();
        let e = Users::open(dir.path()).err().unwrap().to_string();
        assert!(e.contains("users.json") && e.contains("expected"), "{e}");
    }
}
