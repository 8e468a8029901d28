//! API keys: listed by their SHA-256, parsed from the key file and `WILLOW_API_KEYS`, reloaded
//! when the file changes and on SIGHUP.

use super::{API_KEYS_ENV, B64, KEY_PREFIX};
use crate::jobs::Caller;
use base64::Engine as _;
use sha2::{Digest, Sha256};
use std::collections::{BTreeSet, HashMap};
use std::path::PathBuf;
use std::sync::{Arc, RwLock};

/// A listed key: who it authenticates.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct KeyEntry {
    caller: Caller,
}

pub(super) type KeyMap = HashMap<[u8; 32], KeyEntry>;

/// SHA-256 of a presented key.
pub(super) fn key_digest(key: &str) -> [u8; 32] {
    Sha256::digest(key.as_bytes()).into()
}

pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex32(s: &str) -> Option<[u8; 32]> {
    if s.len() != 64 || !s.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

/// Parse key lines (`<tenant> <name> sha256:<hex>`, `#` comments, blank lines). `source`
/// names the file or variable in errors, which quote line numbers and never a hash.
pub(super) fn parse_keys(text: &str, source: &str, into: &mut KeyMap) -> Result<(), String> {
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        let at = || format!("{source} line {}", n + 1);
        let [tenant, name, hash] = fields[..] else {
            return Err(format!(
                "{}: expected `<tenant> <name> sha256:<64 hex digits>`, got {} fields",
                at(),
                fields.len()
            ));
        };
        if name.chars().count() > 64 {
            return Err(format!("{}: key name longer than 64 characters", at()));
        }
        let caller = Caller::new(tenant, name).map_err(|e| format!("{}: {e}", at()))?;
        let digest = hash
            .strip_prefix("sha256:")
            .and_then(|h| unhex32(&h.to_ascii_lowercase()))
            .ok_or_else(|| format!("{}: the hash must be `sha256:` and 64 hex digits", at()))?;
        if into.insert(digest, KeyEntry { caller }).is_some() {
            return Err(format!("{}: the same key is listed twice", at()));
        }
    }
    Ok(())
}

/// A new API key and its key-file line: `(key, "<tenant> <name> sha256:<hex>")`.
pub fn new_key(tenant: &str, name: &str) -> Result<(String, String), String> {
    Caller::new(tenant, name)?;
    if name.is_empty() || name.chars().count() > 64 || name.contains(char::is_whitespace) {
        return Err("the key name must be 1-64 characters without spaces".into());
    }
    if name.contains('#') {
        return Err("the key name cannot contain `#` (it starts a comment)".into());
    }
    let mut bytes = [0u8; 32];
    random_bytes(&mut bytes)?;
    let key = format!("{KEY_PREFIX}{}", B64.encode(bytes));
    let line = format!("{tenant} {name} sha256:{}", hex(&key_digest(&key)));
    Ok((key, line))
}

pub(super) fn random_bytes(out: &mut [u8]) -> Result<(), String> {
    use ring::rand::SecureRandom as _;
    ring::rand::SystemRandom::new()
        .fill(out)
        .map_err(|_| "the system random number generator failed".to_string())
}

/// The listed keys and where they come from.
pub(super) struct KeyStore {
    pub(super) file: Option<PathBuf>,
    pub(super) env: Option<String>,
    pub(super) keys: RwLock<Arc<KeyMap>>,
    /// SHA-256 of the file content last looked at (loaded or refused), so a bad file is
    /// reported once, not at every poll.
    pub(super) seen: RwLock<Option<[u8; 32]>>,
}

impl KeyStore {
    pub(super) fn load(file: Option<PathBuf>, env: Option<String>) -> Result<Self, String> {
        let store = KeyStore {
            file,
            env,
            keys: RwLock::new(Arc::new(KeyMap::new())),
            seen: RwLock::new(None),
        };
        let (map, digest) = store.read()?;
        *write(&store.keys) = Arc::new(map);
        *write(&store.seen) = digest;
        Ok(store)
    }

    /// Read and parse the sources; also the file content's digest.
    fn read(&self) -> Result<(KeyMap, Option<[u8; 32]>), String> {
        let mut map = KeyMap::new();
        if let Some(env) = &self.env {
            parse_keys(env, API_KEYS_ENV, &mut map)?;
        }
        let mut digest = None;
        if let Some(path) = &self.file {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
            digest = Some(Sha256::digest(text.as_bytes()).into());
            parse_keys(&text, &path.display().to_string(), &mut map)?;
        }
        Ok((map, digest))
    }

    pub(super) fn lookup(&self, key: &str) -> Option<Caller> {
        let keys = read(&self.keys).clone();
        keys.get(&key_digest(key)).map(|e| e.caller.clone())
    }

    /// Re-read the file if its content changed (or always, when `force`). A file that cannot
    /// be read or parsed keeps the current keys and logs why.
    pub(super) fn reload(&self, force: bool) {
        let Some(path) = &self.file else { return };
        let current = std::fs::read(path)
            .ok()
            .map(|b| <[u8; 32]>::from(Sha256::digest(&b)));
        if !force && current.is_some() && current == *read(&self.seen) {
            return;
        }
        match self.read() {
            Ok((map, digest)) => {
                let old = read(&self.keys).clone();
                let names = |m: &KeyMap| -> BTreeSet<String> {
                    m.values()
                        .map(|e| format!("{}/{}", e.caller.tenant, e.caller.subject))
                        .collect()
                };
                let (before, after) = (names(&old), names(&map));
                let added: Vec<&String> = after.difference(&before).collect();
                let removed: Vec<&String> = before.difference(&after).collect();
                tracing::info!(
                    file = %path.display(),
                    keys = map.len(),
                    added = ?added,
                    removed = ?removed,
                    "API keys reloaded"
                );
                *write(&self.keys) = Arc::new(map);
                *write(&self.seen) = digest;
            }
            Err(e) => {
                let mut seen = write(&self.seen);
                if force || current.is_none() || current != *seen {
                    tracing::error!(error = %e, "API key file not reloaded; keeping the previous keys");
                }
                if current.is_some() {
                    *seen = current;
                }
            }
        }
    }
}

pub(super) fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

pub(super) fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_lines() {
        let (key, line) = new_key("acme", "ci").unwrap();
        assert!(key.starts_with(KEY_PREFIX));
        assert!(!line.contains(&key));
        let mut map = KeyMap::new();
        parse_keys(&format!("# keys\n\n{line}  # the CI\n"), "f", &mut map).unwrap();
        assert_eq!(map.len(), 1);
        let entry = map.get(&key_digest(&key)).unwrap();
        assert_eq!(entry.caller.tenant, "acme");
        assert_eq!(entry.caller.subject, "ci");
        let e = parse_keys(&format!("{line}\n{line}\n"), "f", &mut KeyMap::new()).unwrap_err();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_keys("acme ci sha256:zz\n", "f", &mut KeyMap::new()).unwrap_err();
        assert!(e.contains("line 1") && !e.contains("zz"), "{e}");
        assert!(parse_keys("a/b ci sha256:00\n", "f", &mut KeyMap::new()).is_err());
        assert!(new_key("acme", "two words").is_err());
        assert!(new_key("bad tenant!", "x").is_err());
    }
}
