//! Text scanning shared by the line- and word-based formats (OBJ, OFF, ASCII PLY and STL).
//!
//! Every reader reports 1-based line numbers and keeps byte offsets so writers can splice new
//! numbers into the user's own text. Line ends are `\n`, `\r\n` or a lone `\r` (classic Mac
//! OS, and some exporters still write it): all three end a line, so a CR-only file is not
//! read as one long line.

use super::{foreign_content, MeshError};

/// The bytes as UTF-8 text, or an error that names what they are when they are not text.
pub(crate) fn utf8<'a>(bytes: &'a [u8], format: &'static str) -> Result<&'a str, MeshError> {
    std::str::from_utf8(bytes).map_err(|e| match foreign_content(bytes) {
        Some(what) => MeshError::parse(format, format!("this is {what}, not {format} text")),
        None => MeshError::parse(format, format!("not UTF-8 text: {e}")),
    })
}

/// The lines of `text` with the byte offset where each starts, without their line end.
/// A UTF-8 byte order mark at the start is skipped (offsets still count from the file's
/// first byte, so written files keep the mark).
pub(crate) fn lines_with_offsets(text: &str) -> impl Iterator<Item = (usize, &str)> {
    let bytes = text.as_bytes();
    let mut at = 0usize;
    let bom = '\u{feff}'.len_utf8();
    if text.starts_with('\u{feff}') {
        at = bom;
    }
    std::iter::from_fn(move || {
        if at > bytes.len() || (at == bytes.len() && at > 0 && ends_line(bytes, at)) {
            return None;
        }
        let start = at;
        let mut end = start;
        while end < bytes.len() && bytes[end] != b'\n' && bytes[end] != b'\r' {
            end += 1;
        }
        at = match (bytes.get(end), bytes.get(end + 1)) {
            (Some(b'\r'), Some(b'\n')) => end + 2,
            (Some(_), _) => end + 1,
            // The last line: the next call ends the iteration.
            (None, _) => bytes.len() + 1,
        };
        // `start..end` lies between ASCII line ends (or the ends of the text), so it is on
        // character boundaries.
        Some((start, text.get(start..end).unwrap_or("")))
    })
}

/// True when the byte before `at` ends a line, i.e. the text ended with a line end and no
/// empty last line should be reported after it.
fn ends_line(bytes: &[u8], at: usize) -> bool {
    matches!(bytes.get(at.wrapping_sub(1)), Some(b'\n' | b'\r'))
}

/// The whitespace-separated words of `text`, each with its byte offset and its 0-based line
/// number (line ends as in [`lines_with_offsets`]).
pub(crate) struct Words<'a> {
    text: &'a str,
    at: usize,
    line: usize,
}

impl<'a> Words<'a> {
    pub(crate) fn new(text: &'a str, at: usize) -> Self {
        Words { text, at, line: 0 }
    }

    /// The byte offset just past the last word returned.
    pub(crate) fn offset(&self) -> usize {
        self.at
    }
}

impl<'a> Iterator for Words<'a> {
    type Item = (usize, usize, &'a str);

    fn next(&mut self) -> Option<Self::Item> {
        let bytes = self.text.as_bytes();
        while let Some(&b) = bytes.get(self.at) {
            match b {
                b'\n' => {
                    if self.at == 0 || bytes[self.at - 1] != b'\r' {
                        self.line += 1;
                    }
                }
                b'\r' => self.line += 1,
                b' ' | b'\t' | b'\x0c' | b'\x0b' => {}
                _ => break,
            }
            self.at += 1;
        }
        let start = self.at;
        while let Some(&b) = bytes.get(self.at) {
            if b.is_ascii_whitespace() || b == b'\x0b' {
                break;
            }
            self.at += 1;
        }
        if start == self.at {
            return None;
        }
        // Words end at ASCII whitespace or the end of the text: character boundaries.
        Some((
            self.line,
            start,
            self.text.get(start..self.at).unwrap_or(""),
        ))
    }
}

/// A coordinate as text that parses back to exactly `x`: Rust's shortest round-trip digits,
/// in exponent form only where plain digits would be long (|x| < 1e-5 or ≥ 1e16).
pub(crate) fn coordinate(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 || (1e-5..1e16).contains(&a) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// Three coordinates separated by single spaces.
pub(crate) fn triple(p: [f64; 3]) -> String {
    format!(
        "{} {} {}",
        coordinate(p[0]),
        coordinate(p[1]),
        coordinate(p[2])
    )
}

/// `text` with each `(range, replacement)` spliced in; `edits` must be sorted and disjoint.
pub(crate) fn splice(text: &str, edits: &[(std::ops::Range<usize>, String)]) -> Vec<u8> {
    let mut out = String::with_capacity(text.len() + text.len() / 4);
    let mut at = 0;
    for (span, new) in edits {
        out.push_str(text.get(at..span.start).unwrap_or(""));
        out.push_str(new);
        at = span.end;
    }
    out.push_str(text.get(at..).unwrap_or(""));
    out.into_bytes()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_end_at_lf_crlf_and_lone_cr() {
        let text = "v 1 2 3\r\n\r\nf 1 2 3";
        let lines: Vec<(usize, &str)> = lines_with_offsets(text).collect();
        assert_eq!(lines, vec![(0, "v 1 2 3"), (9, ""), (11, "f 1 2 3")]);
        let cr: Vec<(usize, &str)> = lines_with_offsets("a\rb\r\rc\r").collect();
        assert_eq!(cr, vec![(0, "a"), (2, "b"), (4, ""), (5, "c")]);
        let bom: Vec<(usize, &str)> = lines_with_offsets("\u{feff}v 1\n").collect();
        assert_eq!(bom, vec![(3, "v 1")]);
        assert_eq!(lines_with_offsets("").count(), 1);
    }

    #[test]
    fn words_carry_offsets_and_line_numbers() {
        let words: Vec<(usize, usize, &str)> = Words::new("a b\r\nc\rd\n\ne", 0).collect();
        assert_eq!(
            words,
            vec![
                (0, 0, "a"),
                (0, 2, "b"),
                (1, 5, "c"),
                (2, 7, "d"),
                (4, 10, "e")
            ]
        );
    }

    #[test]
    fn coordinates_print_so_that_they_parse_back_exactly() {
        for x in [
            0.0,
            -0.0,
            1.0 / 3.0,
            1e-7,
            -2.5e-300,
            1e16,
            f64::MAX,
            123456.789,
        ] {
            let s = coordinate(x);
            assert_eq!(s.parse::<f64>().unwrap().to_bits(), x.to_bits(), "{s}");
        }
    }
}
