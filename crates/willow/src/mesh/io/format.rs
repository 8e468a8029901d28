//! Which mesh format a file is: by extension, by media type, and by its first bytes.
//!
//! Uploads are often mislabelled (`application/octet-stream`, a `.txt` name, Windows' own
//! `application/vnd.ms-pki.stl` for STL), so [`Format::sniff`] looks at the content itself,
//! and [`foreign_content`] names the common things that are not a mesh at all (gzip, zip) so
//! the error can say what was sent instead of failing inside a parser.

use std::path::Path;

/// A mesh file format Willow reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    /// Wavefront OBJ (text), with `vt`/`vn` per corner.
    Obj,
    /// glTF 2.0 JSON with buffers embedded as base64 `data:` URIs.
    Gltf,
    /// glTF 2.0 binary (one JSON chunk, one BIN chunk).
    Glb,
    /// STL, binary or ASCII: a list of triangles, vertices joined by position.
    Stl,
    /// PLY (Stanford polygon file), ASCII or binary either endianness, with per-vertex colours,
    /// normals, UVs and any other properties kept.
    Ply,
    /// OFF (Geomview object file format), including the `C`/`N`/`ST` variants.
    Off,
}

/// Every format, in the order documentation lists them.
pub const ALL_FORMATS: [Format; 6] = [
    Format::Obj,
    Format::Gltf,
    Format::Glb,
    Format::Stl,
    Format::Ply,
    Format::Off,
];

impl Format {
    /// The format named by a file's extension (case-insensitive), if any.
    pub fn from_path(p: &Path) -> Option<Format> {
        Format::from_extension(p.extension()?.to_str()?)
    }

    /// The format of an extension without the dot (case-insensitive), e.g. `"PLY"`.
    pub fn from_extension(ext: &str) -> Option<Format> {
        ALL_FORMATS
            .into_iter()
            .find(|f| ext.eq_ignore_ascii_case(f.extension()))
    }

    /// The format of a media type (parameters such as `; charset=utf-8` are ignored).
    ///
    /// Accepted: the registered `model/obj`, `model/gltf+json`, `model/gltf-binary` and
    /// `model/stl` (IANA, 2018); for STL also the older `application/sla`, the
    /// `model/x.stl-binary`/`model/x.stl-ascii` vendor-tree names and
    /// `application/vnd.ms-pki.stl`, which Windows sends for `.stl` files. PLY and OFF have
    /// no registered type: `model/x-ply` (also `application/ply`, `application/x-ply`,
    /// `text/x-ply`) and `model/x-off` (also `application/x-off`, `text/x-off`).
    pub fn from_mime(m: &str) -> Option<Format> {
        let essence = m.split(';').next()?.trim().to_ascii_lowercase();
        Some(match essence.as_str() {
            "model/obj" => Format::Obj,
            "model/gltf+json" => Format::Gltf,
            "model/gltf-binary" => Format::Glb,
            "model/stl"
            | "application/sla"
            | "model/x.stl-binary"
            | "model/x.stl-ascii"
            | "application/vnd.ms-pki.stl" => Format::Stl,
            "model/x-ply" | "application/ply" | "application/x-ply" | "text/x-ply" => Format::Ply,
            "model/x-off" | "application/x-off" | "text/x-off" => Format::Off,
            _ => return None,
        })
    }

    /// The usual file extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Obj => "obj",
            Format::Gltf => "gltf",
            Format::Glb => "glb",
            Format::Stl => "stl",
            Format::Ply => "ply",
            Format::Off => "off",
        }
    }

    /// The media type written on downloads: the registered one where there is one.
    pub fn mime(self) -> &'static str {
        match self {
            Format::Obj => "model/obj",
            Format::Gltf => "model/gltf+json",
            Format::Glb => "model/gltf-binary",
            Format::Stl => "model/stl",
            Format::Ply => "model/x-ply",
            Format::Off => "model/x-off",
        }
    }

    /// The format the content itself shows, if it is clearly one of ours.
    ///
    /// Binary containers by their magic (`glTF`, `ply`), binary STL by its exact length
    /// (84 + 50·n bytes for the n triangles its header declares; tried before ASCII STL since
    /// many CAD tools start binary headers with `solid` too), OFF by its keyword, ASCII STL by
    /// `solid` followed by a `facet`, glTF JSON by a leading `{`, OBJ by a first statement
    /// that is an OBJ keyword. A UTF-8 byte order mark and leading blank space are skipped.
    pub fn sniff(bytes: &[u8]) -> Option<Format> {
        if bytes.starts_with(b"glTF") {
            return Some(Format::Glb);
        }
        if is_binary_stl(bytes) {
            return Some(Format::Stl);
        }
        let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        let head = &text[..text.len().min(4096)];
        let head = String::from_utf8_lossy(head);
        let trimmed = head.trim_start();
        if trimmed.starts_with("ply") && trimmed[3..].starts_with(['\n', '\r']) {
            return Some(Format::Ply);
        }
        let first_word = trimmed.split_whitespace().next().unwrap_or("");
        if is_off_keyword(first_word) {
            return Some(Format::Off);
        }
        if first_word == "solid" && head.contains("facet") {
            return Some(Format::Stl);
        }
        if trimmed.starts_with('{') {
            return Some(Format::Gltf);
        }
        let statement = trimmed
            .lines()
            .map(str::trim)
            .find(|l| !l.is_empty() && !l.starts_with('#'))
            .and_then(|l| l.split_whitespace().next());
        match statement {
            Some("v" | "vt" | "vn" | "f" | "o" | "g" | "mtllib" | "usemtl" | "s") => {
                Some(Format::Obj)
            }
            _ => None,
        }
    }
}

/// Does `bytes` have exactly the length a binary STL with its declared triangle count has?
pub(crate) fn is_binary_stl(bytes: &[u8]) -> bool {
    let Some(count) = bytes.get(80..84) else {
        return false;
    };
    let n = u32::from_le_bytes([count[0], count[1], count[2], count[3]]) as u64;
    84 + 50 * n == bytes.len() as u64
}

/// The OFF header keyword: `OFF` with the optional Geomview prefixes `ST`, `C`, `N`, `4`, `n`
/// in that order (e.g. `COFF`, `NOFF`, `STCNOFF`).
pub(crate) fn is_off_keyword(word: &str) -> bool {
    let Some(prefix) = word.strip_suffix("OFF") else {
        return false;
    };
    let rest = prefix.strip_prefix("ST").unwrap_or(prefix);
    let rest = rest.strip_prefix('C').unwrap_or(rest);
    let rest = rest.strip_prefix('N').unwrap_or(rest);
    let rest = rest.strip_prefix('4').unwrap_or(rest);
    let rest = rest.strip_prefix('n').unwrap_or(rest);
    rest.is_empty()
}

/// A short description of content that is no mesh format at all but a common wrapper or
/// mistake, for errors: `"gzip-compressed data"` etc.
pub fn foreign_content(bytes: &[u8]) -> Option<&'static str> {
    if bytes.starts_with(&[0x1f, 0x8b]) {
        Some("gzip-compressed data (decompress it and send the mesh file itself)")
    } else if bytes.starts_with(b"PK\x03\x04") {
        Some("a zip archive (unzip it and send the mesh file itself)")
    } else if bytes.starts_with(b"\x28\xb5\x2f\xfd") {
        Some("zstd-compressed data (decompress it first)")
    } else if bytes.starts_with(b"BZh") {
        Some("bzip2-compressed data (decompress it first)")
    } else if bytes.starts_with(b"\xFD7zXZ\x00") {
        Some("xz-compressed data (decompress it first)")
    } else if bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]) {
        Some("UTF-16 text (save it as UTF-8)")
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_round_trip_through_extension_and_mime() {
        for f in ALL_FORMATS {
            let name = format!("Model.{}", f.extension().to_uppercase());
            assert_eq!(Format::from_path(Path::new(&name)), Some(f));
            assert_eq!(Format::from_mime(f.mime()), Some(f));
        }
        assert_eq!(
            Format::from_mime("model/gltf+json; charset=utf-8"),
            Some(Format::Gltf)
        );
        assert_eq!(
            Format::from_mime("application/vnd.ms-pki.stl"),
            Some(Format::Stl)
        );
        assert_eq!(Format::from_mime("application/ply"), Some(Format::Ply));
        assert_eq!(Format::from_path(Path::new("a.step")), None);
        assert_eq!(serde_json::to_string(&Format::Glb).unwrap(), "\"glb\"");
        assert_eq!(serde_json::to_string(&Format::Ply).unwrap(), "\"ply\"");
    }

    #[test]
    fn sniffing_tells_formats_apart_by_content() {
        let mut stl = vec![0u8; 84 + 50];
        stl[..5].copy_from_slice(b"solid"); // binary despite the word: the length decides
        stl[80] = 1;
        assert_eq!(Format::sniff(&stl), Some(Format::Stl));
        stl.push(0);
        assert_eq!(Format::sniff(&stl), None);
        let cases: [(&[u8], Option<Format>); 10] = [
            (b"glTF\x02\x00\x00\x00", Some(Format::Glb)),
            (b"ply\nformat ascii 1.0\n", Some(Format::Ply)),
            (b"ply\r\nformat ascii 1.0\r\n", Some(Format::Ply)),
            (b"OFF\n3 1 0\n", Some(Format::Off)),
            (b"COFF 3 1 0\n", Some(Format::Off)),
            (b"solid x\n facet normal 0 0 1\n", Some(Format::Stl)),
            (b"\xEF\xBB\xBF{\"asset\":{}}", Some(Format::Gltf)),
            (b"# made by hand\n\nv 0 0 0\n", Some(Format::Obj)),
            (b"hello", None),
            (b"\x1f\x8b\x08\x00", None),
        ];
        for (bytes, want) in cases {
            assert_eq!(
                Format::sniff(bytes),
                want,
                "{:?}",
                String::from_utf8_lossy(bytes)
            );
        }
        assert!(is_off_keyword("STCNOFF") && !is_off_keyword("OFFX") && !is_off_keyword("XOFF"));
        assert!(foreign_content(b"\x1f\x8b\x08")
            .unwrap()
            .starts_with("gzip"));
        assert_eq!(foreign_content(b"v 1 2 3"), None);
    }
}
