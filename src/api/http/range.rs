//! Single byte ranges on mesh downloads (`/result`, `/frames/{step}`), RFC 9110 §14: so a
//! client can resume a large result instead of starting over.
//!
//! - `Range: bytes=a-b`, `bytes=a-` and `bytes=-n` answer `206 Partial Content` with
//!   `Content-Range: bytes first-last/length`;
//! - a range that starts at or past the end (or `bytes=-0`) answers `416 Range Not
//!   Satisfiable` with `Content-Range: bytes */length`;
//! - every download answer says `Accept-Ranges: bytes`.
//!
//! What is ignored, as RFC 9110 lets a server do (the answer is the whole file, `200`): a
//! `Range` of several ranges (a `multipart/byteranges` answer would buy a client of mesh files
//! nothing that two requests do not), another unit, a malformed value, and any `Range` sent
//! with `If-Range`. The downloads carry no validator (no `ETag`, no `Last-Modified`), so an
//! `If-Range` can never match one, and §13.1.5 says a server then MUST ignore the `Range`.
//! Without `If-Range` the bytes are safe to resume: a job's result and a kept frame never
//! change once they can be downloaded (a resumed job that writes a step again renders it
//! under a new name, and serves the new one whole).

use axum::http::{header, HeaderMap, Method};

/// One byte range as asked, before the length is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Asked {
    /// `first-` or `first-last`.
    From { first: u64, last: Option<u64> },
    /// `-n`: the last `n` bytes.
    Suffix(u64),
}

/// What to send, once the length is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Answer {
    /// `200` with everything.
    Whole,
    /// `206` with bytes `first..=last`.
    Part { first: u64, last: u64 },
    /// `416`.
    Unsatisfiable,
}

/// The single byte range a request asks for, or `None` when it is to be served whole (see the
/// module docs for what is ignored).
pub(super) fn asked(method: &Method, headers: &HeaderMap) -> Option<Asked> {
    // Range is defined for GET only (§14.2); a HEAD answers as the whole GET would.
    if method != Method::GET || headers.contains_key(header::IF_RANGE) {
        return None;
    }
    let mut values = headers.get_all(header::RANGE).iter();
    let (Some(value), None) = (values.next(), values.next()) else {
        return None;
    };
    parse(value.to_str().ok()?)
}

/// `bytes=…` with exactly one range in it.
fn parse(value: &str) -> Option<Asked> {
    let (unit, set) = value.trim().split_once('=')?;
    if !unit.trim().eq_ignore_ascii_case("bytes") {
        return None;
    }
    // Empty list elements are allowed (§5.6.1: `bytes=0-1,` is one range).
    let mut ranges = set.split(',').map(str::trim).filter(|r| !r.is_empty());
    let (Some(range), None) = (ranges.next(), ranges.next()) else {
        return None;
    };
    let (first, last) = range.split_once('-')?;
    match (first, last) {
        ("", n) => Some(Asked::Suffix(digits(n)?)),
        (a, "") => Some(Asked::From {
            first: digits(a)?,
            last: None,
        }),
        (a, b) => {
            let (first, last) = (digits(a)?, digits(b)?);
            // `last < first` is invalid, not unsatisfiable (§14.1.1): ignored.
            (last >= first).then_some(Asked::From {
                first,
                last: Some(last),
            })
        }
    }
}

/// A run of ASCII digits as a number; one too large for u64 is u64::MAX, which no download
/// reaches (so `bytes=99999999999999999999999-` is unsatisfiable, not malformed).
fn digits(s: &str) -> Option<u64> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(s.bytes().fold(0u64, |n, d| {
        n.saturating_mul(10).saturating_add(u64::from(d - b'0'))
    }))
}

/// What to send of a download of `len` bytes for `asked`.
pub(super) fn answer(asked: Option<Asked>, len: u64) -> Answer {
    match asked {
        None => Answer::Whole,
        // Nothing to range over; §14.1.1 would make `-n` satisfiable with zero bytes, and
        // the whole (empty) answer says the same.
        Some(_) if len == 0 => Answer::Whole,
        Some(Asked::Suffix(0)) => Answer::Unsatisfiable,
        Some(Asked::Suffix(n)) => Answer::Part {
            first: len.saturating_sub(n),
            last: len - 1,
        },
        Some(Asked::From { first, .. }) if first >= len => Answer::Unsatisfiable,
        Some(Asked::From { first, last }) => Answer::Part {
            first,
            last: last.map_or(len - 1, |l| l.min(len - 1)),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn headers(pairs: &[(&'static str, &'static str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.append(*k, HeaderValue::from_static(v));
        }
        h
    }

    fn get(range: &'static str, len: u64) -> Answer {
        answer(asked(&Method::GET, &headers(&[("range", range)])), len)
    }

    #[test]
    fn single_ranges_are_resolved_against_the_length() {
        let part = |first, last| Answer::Part { first, last };
        assert_eq!(get("bytes=0-9", 100), part(0, 9));
        assert_eq!(get("bytes=90-", 100), part(90, 99));
        assert_eq!(get("bytes=90-1000", 100), part(90, 99));
        assert_eq!(get("bytes=-10", 100), part(90, 99));
        assert_eq!(get("bytes=-1000", 100), part(0, 99));
        assert_eq!(get("BYTES = 5-5 ,", 100), part(5, 5));
        assert_eq!(get("bytes=99-99", 100), part(99, 99));
    }

    #[test]
    fn ranges_past_the_end_are_unsatisfiable() {
        assert_eq!(get("bytes=100-", 100), Answer::Unsatisfiable);
        assert_eq!(get("bytes=100-200", 100), Answer::Unsatisfiable);
        assert_eq!(get("bytes=-0", 100), Answer::Unsatisfiable);
        assert_eq!(
            get("bytes=99999999999999999999999-", 100),
            Answer::Unsatisfiable
        );
    }

    /// Several ranges, other units, malformed values, `If-Range` and non-GET methods: the
    /// whole download.
    #[test]
    fn everything_else_is_served_whole() {
        for range in [
            "bytes=0-1,5-6",
            "items=0-1",
            "bytes=5-1",
            "bytes=a-b",
            "bytes=-",
            "bytes=",
            "bytes 0-1",
            "bytes=+1-2",
            "bytes=0x1-2",
        ] {
            assert_eq!(get(range, 100), Answer::Whole, "{range}");
        }
        let h = headers(&[("range", "bytes=0-1"), ("if-range", "\"x\"")]);
        assert_eq!(answer(asked(&Method::GET, &h), 100), Answer::Whole);
        let h = headers(&[("range", "bytes=0-1")]);
        assert_eq!(answer(asked(&Method::HEAD, &h), 100), Answer::Whole);
        let h = headers(&[("range", "bytes=0-1"), ("range", "bytes=2-3")]);
        assert_eq!(answer(asked(&Method::GET, &h), 100), Answer::Whole);
        assert_eq!(get("bytes=0-1", 0), Answer::Whole);
    }
}
