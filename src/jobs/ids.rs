//! [`JobId`]: a job's identifier, a text that has been checked. Ids reach the core from URLs
//! and request fields; only text of the form the core itself hands out is ever looked up, and
//! in the file store an id becomes a path, so the check belongs to the type, not to a backend.

use super::error::JobError;
use serde::{Deserialize, Serialize};
use std::borrow::Borrow;
use std::fmt;
use std::ops::Deref;

/// A job's identifier: a UUID v4 in its hyphenated lower-case text form. Made by
/// [`JobId::random`] or checked by [`JobId::parse`]; reads as a `&str` wherever one is wanted.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct JobId(String);

impl JobId {
    /// A fresh id.
    pub fn random() -> JobId {
        JobId(uuid::Uuid::new_v4().to_string())
    }

    /// `text` as a job id; [`JobError::NotFound`] naming it when no job can have that id.
    pub fn parse(text: &str) -> Result<JobId, JobError> {
        if well_formed(text) {
            Ok(JobId(text.to_string()))
        } else {
            Err(JobError::NotFound(text.to_string()))
        }
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// Whether `text` has the form of the ids the core hands out (jobs' and uploads': UUID text):
/// 1–64 hex digits and hyphens. Nothing else is looked up, and nothing else becomes a path.
pub fn well_formed(text: &str) -> bool {
    !text.is_empty() && text.len() <= 64 && text.bytes().all(|b| b.is_ascii_hexdigit() || b == b'-')
}

impl Deref for JobId {
    type Target = str;
    fn deref(&self) -> &str {
        &self.0
    }
}

impl AsRef<str> for JobId {
    fn as_ref(&self) -> &str {
        &self.0
    }
}

impl Borrow<str> for JobId {
    fn borrow(&self) -> &str {
        &self.0
    }
}

impl fmt::Display for JobId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl From<JobId> for String {
    fn from(id: JobId) -> String {
        id.0
    }
}

impl TryFrom<String> for JobId {
    type Error = JobError;
    fn try_from(text: String) -> Result<JobId, JobError> {
        if well_formed(&text) {
            Ok(JobId(text))
        } else {
            Err(JobError::NotFound(text))
        }
    }
}

impl PartialEq<str> for JobId {
    fn eq(&self, other: &str) -> bool {
        self.0 == other
    }
}

impl PartialEq<&str> for JobId {
    fn eq(&self, other: &&str) -> bool {
        self.0 == *other
    }
}

impl PartialEq<String> for JobId {
    fn eq(&self, other: &String) -> bool {
        &self.0 == other
    }
}

impl PartialEq<JobId> for String {
    fn eq(&self, other: &JobId) -> bool {
        *self == other.0
    }
}

impl PartialEq<JobId> for str {
    fn eq(&self, other: &JobId) -> bool {
        self == other.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_ids_parse_and_foreign_text_does_not() {
        let id = JobId::random();
        assert_eq!(JobId::parse(&id).ok(), Some(id.clone()));
        assert_eq!(id.len(), 36);
        for bad in ["", "../etc/passwd", "not-hex-zz", &"a".repeat(65)] {
            assert!(
                matches!(JobId::parse(bad), Err(JobError::NotFound(t)) if t == bad),
                "{bad:?}"
            );
        }
        let json = serde_json::to_string(&id).expect("serialize");
        assert_eq!(json, format!("\"{id}\""));
        assert!(serde_json::from_str::<JobId>("\"x/y\"").is_err());
    }
}
