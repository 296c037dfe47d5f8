//! Signed models: who made a model, checked before a car drives it.
//!
//! A learner signs every model it publishes and every model folder it writes with an ed25519
//! key (`ed25519-dalek`). The signature covers one short text that names the three parts of
//! a model by their sha256:
//!
//! ```text
//! paddock-model-signature-1
//! weights_sha256 <hex of model.safetensors>
//! model_metadata_sha256 <hex of model_metadata.json>
//! manifest_sha256 <hex of manifest.json>
//! ```
//!
//! so changing any byte of the weights, the metadata or the manifest breaks it. In a folder it
//! is `signature.json` (`{"format", "public_key", "signature"}`, hex); on the wire it travels
//! beside the three parts. Keys are files in the standard formats (PKCS#8 PEM for the secret
//! key, SubjectPublicKeyInfo PEM for the public one), so `openssl pkey` reads them too.
//! A verifier trusts the public keys it is given and nothing else.

use ed25519_dalek::pkcs8::spki::der::pem::LineEnding;
use ed25519_dalek::pkcs8::{DecodePrivateKey, DecodePublicKey, EncodePrivateKey, EncodePublicKey};
use ed25519_dalek::{Signer as _, SigningKey, Verifier as _, VerifyingKey};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::error::FileError;
use crate::folder::sha256_hex;

/// The first line of the signed text (and the signature file's format tag).
pub const FORMAT: &str = "paddock-signature-1";

/// Why a key or a signature could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SignatureError {
    /// A key file could not be read or written, or is not a key of the expected kind.
    #[error(transparent)]
    File(#[from] FileError),
    /// A model's signature is missing, malformed, by an untrusted key, or does not match.
    #[error("{0}")]
    Refused(String),
}

/// A signing key (a learner's).
pub struct Signer {
    key: SigningKey,
}

impl std::fmt::Debug for Signer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Signer({})", self.public_hex())
    }
}

/// A model's signature: the signing key's public half and the signature, both hex.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSignature {
    /// [`FORMAT`].
    pub format: String,
    /// The ed25519 public key (32 bytes, hex).
    pub public_key: String,
    /// The ed25519 signature (64 bytes, hex).
    pub signature: String,
}

/// The text a model's signature covers (see the module documentation).
pub fn signed_text(weights: &[u8], metadata_json: &str, manifest_json: &str) -> String {
    format!(
        "paddock-model-signature-1\nweights_sha256 {}\nmodel_metadata_sha256 {}\nmanifest_sha256 {}\n",
        sha256_hex(weights),
        sha256_hex(metadata_json.as_bytes()),
        sha256_hex(manifest_json.as_bytes())
    )
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SignatureError + '_ {
    move |error| FileError::io(path, error).into()
}

impl Signer {
    /// A new random key.
    pub fn generate() -> Signer {
        let seed: [u8; 32] = rand::random();
        Signer { key: SigningKey::from_bytes(&seed) }
    }

    /// A key from 32 seed bytes (tests).
    pub fn from_seed(seed: [u8; 32]) -> Signer {
        Signer { key: SigningKey::from_bytes(&seed) }
    }

    /// Read a PKCS#8 PEM secret key.
    pub fn load(path: &Path) -> Result<Signer, SignatureError> {
        let text = std::fs::read_to_string(path).map_err(io(path))?;
        let key = SigningKey::from_pkcs8_pem(&text).map_err(|e| {
            FileError::invalid(
                path.display().to_string(),
                format!("not an ed25519 secret key in PKCS#8 PEM ({e}); make one with `coordinator keys new NAME`"),
            )
        })?;
        Ok(Signer { key })
    }

    /// Write the pair as `<stem>.key` (secret, owner-only) and `<stem>.pub`; returns both paths.
    /// Refuses to overwrite an existing secret key.
    pub fn write_pair(&self, stem: &Path) -> Result<(PathBuf, PathBuf), SignatureError> {
        let secret = stem.with_extension("key");
        let public = stem.with_extension("pub");
        if secret.exists() {
            return Err(SignatureError::from(FileError::invalid(
                secret.display().to_string(),
                "exists already; remove it first to make a new key",
            )));
        }
        if let Some(dir) = secret.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(io(dir))?;
        }
        let pem = self.key.to_pkcs8_pem(LineEnding::LF).expect("an ed25519 key encodes");
        write_private(&secret, pem.as_bytes())?;
        std::fs::write(&public, self.public_pem()).map_err(io(&public))?;
        Ok((secret, public))
    }

    /// The secret key at `path` (with its `.pub` beside it), made when it is not there.
    pub fn load_or_create(path: &Path) -> Result<Signer, SignatureError> {
        if path.exists() {
            return Signer::load(path);
        }
        let s = Signer::generate();
        s.write_pair(&path.with_extension(""))?;
        Ok(s)
    }

    /// The public key, SubjectPublicKeyInfo PEM.
    pub fn public_pem(&self) -> String {
        self.key.verifying_key().to_public_key_pem(LineEnding::LF).expect("an ed25519 key encodes")
    }

    /// The public key, hex.
    pub fn public_hex(&self) -> String {
        hex::encode(self.key.verifying_key().as_bytes())
    }

    /// Sign a model's three parts.
    pub fn sign(&self, weights: &[u8], metadata_json: &str, manifest_json: &str) -> ModelSignature {
        let sig = self.key.sign(signed_text(weights, metadata_json, manifest_json).as_bytes());
        ModelSignature { format: FORMAT.into(), public_key: self.public_hex(), signature: hex::encode(sig.to_bytes()) }
    }
}

#[cfg(unix)]
fn write_private(path: &Path, bytes: &[u8]) -> Result<(), SignatureError> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new().write(true).create_new(true).mode(0o600).open(path).map_err(io(path))?;
    f.write_all(bytes).map_err(io(path))
}

#[cfg(not(unix))]
fn write_private(path: &Path, bytes: &[u8]) -> Result<(), SignatureError> {
    std::fs::write(path, bytes).map_err(io(path))
}

/// The public keys a verifier trusts.
#[derive(Clone, Debug, Default)]
pub struct TrustedKeys {
    keys: Vec<(String, VerifyingKey)>,
}

impl TrustedKeys {
    /// Read SubjectPublicKeyInfo PEM files (each may hold one key).
    pub fn load(paths: &[PathBuf]) -> Result<TrustedKeys, SignatureError> {
        let mut t = TrustedKeys::default();
        for p in paths {
            let text = std::fs::read_to_string(p).map_err(io(p))?;
            let key = VerifyingKey::from_public_key_pem(&text).map_err(|e| {
                FileError::invalid(
                    p.display().to_string(),
                    format!("not an ed25519 public key in PEM ({e}); give the learner's `.pub` file"),
                )
            })?;
            t.keys.push((p.display().to_string(), key));
        }
        Ok(t)
    }

    /// Trust a SubjectPublicKeyInfo PEM text (`name`: where it came from, for errors).
    pub fn add_pem(&mut self, name: &str, text: &str) -> Result<(), SignatureError> {
        let key = VerifyingKey::from_public_key_pem(text)
            .map_err(|e| FileError::invalid(name.to_string(), format!("not an ed25519 public key in PEM ({e})")))?;
        self.keys.push((name.into(), key));
        Ok(())
    }

    /// Trust one signer's public key (tests, and a learner checking its own folders).
    pub fn add(&mut self, name: &str, signer: &Signer) {
        self.keys.push((name.into(), signer.key.verifying_key()));
    }

    /// Trust a public key given as hex (32 bytes: a signature's `public_key`).
    pub fn add_hex(&mut self, name: &str, public_hex: &str) -> Result<(), SignatureError> {
        let key = hex::decode(public_hex)
            .ok()
            .and_then(|b| <[u8; 32]>::try_from(b).ok())
            .and_then(|b| VerifyingKey::from_bytes(&b).ok())
            .ok_or_else(|| SignatureError::Refused("the signature's public key is not an ed25519 key in hex".into()))?;
        self.keys.push((name.into(), key));
        Ok(())
    }

    /// How many keys are trusted.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// No key is trusted.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// Check a signature over a model's three parts: made by a trusted key, over these bytes.
    /// Returns the trusted key's name (its file).
    pub fn verify(
        &self,
        sig: &ModelSignature,
        weights: &[u8],
        metadata_json: &str,
        manifest_json: &str,
    ) -> Result<&str, SignatureError> {
        let refuse = |m: String| Err(SignatureError::Refused(m));
        if sig.format != FORMAT {
            return refuse(format!("signature format is '{}', expected '{FORMAT}'", sig.format));
        }
        let Some((name, key)) = self.keys.iter().find(|(_, k)| hex::encode(k.as_bytes()) == sig.public_key) else {
            return refuse(format!("signed by key \"{}\", which is not trusted (--trust)", short(&sig.public_key)));
        };
        let bytes: [u8; 64] = match hex::decode(&sig.signature).ok().and_then(|b| b.try_into().ok()) {
            Some(b) => b,
            None => return refuse("the signature is not 64 bytes of hex".into()),
        };
        let s = ed25519_dalek::Signature::from_bytes(&bytes);
        match key.verify(signed_text(weights, metadata_json, manifest_json).as_bytes(), &s) {
            Ok(()) => Ok(name),
            Err(_) => refuse(format!(
                "the signature by {name} does not match the model's weights, model_metadata.json and manifest: \
                 the model was changed after signing"
            )),
        }
    }
}

fn short(hex: &str) -> String {
    hex.chars().take(16).collect::<String>() + "…"
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_signature_covers_every_part_and_only_trusted_keys_count() {
        let a = Signer::from_seed([1; 32]);
        let b = Signer::from_seed([2; 32]);
        let mut trust = TrustedKeys::default();
        trust.add("a.pub", &a);
        let sig = a.sign(b"weights", "{\"m\":1}", "{\"v\":1}");
        assert_eq!(trust.verify(&sig, b"weights", "{\"m\":1}", "{\"v\":1}").unwrap(), "a.pub");
        for (w, m, f) in [
            (&b"weightz"[..], "{\"m\":1}", "{\"v\":1}"),
            (b"weights", "{\"m\":2}", "{\"v\":1}"),
            (b"weights", "{\"m\":1}", "{\"v\":2}"),
        ] {
            let e = trust.verify(&sig, w, m, f).unwrap_err().to_string();
            assert!(e.contains("changed after signing"), "{e}");
        }
        let other = b.sign(b"weights", "{\"m\":1}", "{\"v\":1}");
        let e = trust.verify(&other, b"weights", "{\"m\":1}", "{\"v\":1}").unwrap_err().to_string();
        assert!(e.contains("not trusted"), "{e}");
        // A trusted key's id on another key's signature.
        let forged = ModelSignature { public_key: a.public_hex(), ..other };
        assert!(trust.verify(&forged, b"weights", "{\"m\":1}", "{\"v\":1}").is_err());
    }

    #[test]
    fn key_files_round_trip_and_are_not_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let s = Signer::from_seed([7; 32]);
        let (secret, public) = s.write_pair(&dir.path().join("learner")).unwrap();
        assert!(s.write_pair(&dir.path().join("learner")).is_err());
        let back = Signer::load(&secret).unwrap();
        assert_eq!(back.public_hex(), s.public_hex());
        let trust = TrustedKeys::load(std::slice::from_ref(&public)).unwrap();
        let sig = back.sign(b"w", "m", "f");
        trust.verify(&sig, b"w", "m", "f").unwrap();
        let e = TrustedKeys::load(std::slice::from_ref(&secret)).unwrap_err().to_string();
        assert!(e.contains("learner.key") && e.contains("public key"), "{e}");
        let e = Signer::load(&public).unwrap_err().to_string();
        assert!(e.contains("learner.pub") && e.contains("secret key"), "{e}");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&secret).unwrap().permissions().mode() & 0o777, 0o600);
        }
    }
}
