//! Why a mesh or a mesh file was refused.
//!
//! Every refusal names the rule that failed, how many elements break it and the first few of
//! them, so a user can find the problem in their modelling tool. [`MeshError::code`] gives a
//! stable machine-readable code the HTTP and gRPC layers map to problem types and status codes
//! without parsing messages.

use std::fmt;

/// How many offending indices an error keeps. Enough to find the problem in a modeller, small
/// enough that a mesh with a million bad faces still gives a one-line message.
pub const MAX_REPORTED: usize = 8;

/// The first few offending items of some kind plus how many there are in total.
///
/// Collect with [`Offenders::push`]; it keeps at most [`MAX_REPORTED`] items, so building one
/// never allocates in proportion to the input.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Offenders<T> {
    /// Total number of offending items.
    pub count: usize,
    /// The first (at most [`MAX_REPORTED`]) of them, in input order.
    pub first: Vec<T>,
}

impl<T> Default for Offenders<T> {
    fn default() -> Self {
        Offenders {
            count: 0,
            first: Vec::new(),
        }
    }
}

impl<T> Offenders<T> {
    /// Count one more offender, keeping it if fewer than [`MAX_REPORTED`] are kept so far.
    pub fn push(&mut self, item: T) {
        self.count += 1;
        if self.first.len() < MAX_REPORTED {
            self.first.push(item);
        }
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }
}

impl<T: fmt::Debug> fmt::Display for Offenders<T> {
    /// The kept items, `"4, 9, 17"`, with `", …"` appended when some were not kept.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, item) in self.first.iter().enumerate() {
            if i > 0 {
                write!(f, ", ")?;
            }
            write!(f, "{item:?}")?;
        }
        if self.count > self.first.len() {
            write!(f, ", …")?;
        }
        Ok(())
    }
}

/// Which file format a parse error came from.
pub type FormatName = &'static str;

/// Everything that can be wrong with a mesh or a mesh file.
///
/// Vertex and face indices are 0-based indices into the arrays given to
/// [`Mesh::new`](super::Mesh::new); a file's surface errors come wrapped in
/// [`MeshError::InFile`] in the file's own numbering, and an OBJ's non-finite coordinates are named by
/// 0-based `v` line (unused lines are checked too) and its out-of-range faces by 0-based `f`
/// line.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MeshError {
    /// Nothing to fair: no vertices or no triangles.
    #[error(
        "empty mesh: {vertices} vertices and {faces} triangles; at least one triangle is needed"
    )]
    Empty { vertices: usize, faces: usize },

    /// The file holds points or line segments but no triangles.
    #[error(
        "the file has no triangles, only {points} point and {lines} line elements; \
         fairing needs a triangle surface"
    )]
    PointsOrLinesOnly { points: usize, lines: usize },

    /// Some coordinates are NaN or infinite.
    #[error("{} vertices have non-finite (NaN or infinite) coordinates; first: {}", .vertices.count, .vertices)]
    NonFinite { vertices: Offenders<usize> },

    /// Some coordinates are finite but larger in magnitude than
    /// `MAX_COORDINATE`: the flow's squared quantities would
    /// overflow or lose all precision later, so they are refused when the mesh is read.
    #[error(
        "{} vertices have coordinates of magnitude above {limit:e}; first: {}; scale the model down",
        .vertices.count,
        .vertices
    )]
    CoordinateOutOfRange {
        vertices: Offenders<usize>,
        limit: f64,
    },

    /// Some triangle corners name a vertex that does not exist.
    #[error(
        "{} triangles reference vertices out of range (the mesh has {vertex_count} vertices); \
         first: {}",
        .faces.count,
        .faces
    )]
    IndexOutOfRange {
        faces: Offenders<usize>,
        vertex_count: usize,
    },

    /// Triangles with a repeated vertex index or exactly zero area.
    ///
    /// Tiny but non-zero areas are legal: real scans have slivers with angles of 0.01°.
    #[error(
        "{} triangles are degenerate (a repeated vertex or exactly zero area); first: {}",
        .faces.count,
        .faces
    )]
    DegenerateFaces { faces: Offenders<usize> },

    /// Vertices that no triangle uses: they have no area, so the flow cannot move them.
    #[error("{} vertices are not used by any triangle; first: {}", .vertices.count, .vertices)]
    UnreferencedVertices { vertices: Offenders<usize> },

    /// Edges shared by more than two triangles (listed as sorted vertex pairs).
    #[error(
        "{} edges are shared by more than two triangles (non-manifold edges); first: {}",
        .edges.count,
        .edges
    )]
    NonManifoldEdges { edges: Offenders<[usize; 2]> },

    /// Vertices where two or more separate fans of triangles touch (a "bowtie").
    #[error(
        "{} vertices join separate fans of triangles (non-manifold vertices, e.g. a bowtie); \
         first: {}",
        .vertices.count,
        .vertices
    )]
    NonManifoldVertices { vertices: Offenders<usize> },

    /// A connected piece (e.g. a Möbius strip) has no consistent orientation.
    #[error(
        "connected component {component} (containing triangle {face}) is not orientable, \
         e.g. a Möbius strip"
    )]
    NonOrientable { component: usize, face: usize },

    /// An input exceeds a configured [`Limits`](super::Limits) value.
    #[error("too large: {value} {what} exceeds the limit of {limit}")]
    TooLarge {
        what: &'static str,
        value: usize,
        limit: usize,
    },

    /// The bytes are not a valid file of the claimed format.
    #[error("cannot parse {format}: {detail}")]
    Parse { format: FormatName, detail: String },

    /// A glTF refers to a resource outside the upload. Only `data:` URIs and the GLB BIN chunk
    /// are accepted: following a path or URL would let an upload read the server's files or
    /// make it fetch from the network.
    #[error("external URI {uri:?} refused: only data: URIs and the GLB BIN chunk are accepted")]
    ExternalUri { uri: String },

    /// A buffer, buffer view or accessor points past the end of the data it lives in.
    #[error("truncated or out-of-bounds buffer data: {detail}")]
    TruncatedBuffer { detail: String },

    /// New positions given for writing do not match the surface's vertex count.
    #[error("expected {expected} positions (one per welded vertex), got {got}")]
    PositionCount { expected: usize, got: usize },

    /// The content is clearly another format than the one it was sent as (e.g. an OFF file
    /// sent as OBJ, which would otherwise read as an OBJ without faces).
    #[error(
        "the file was sent as {declared} but it is {found}: send it as {found} \
         (Content-Type {mime}, or a .{extension} file name)"
    )]
    FormatMismatch {
        declared: FormatName,
        found: FormatName,
        mime: &'static str,
        extension: &'static str,
    },

    /// The content is not a mesh file at all but a common wrapper (gzip, zip, UTF-16 text).
    #[error("the file sent as {declared} is {what}")]
    NotAMesh {
        declared: FormatName,
        what: &'static str,
    },

    /// A mesh rule a file breaks, in the file's own numbering: `error`'s vertex indices are
    /// the file's vertices (OBJ `v` lines in order, PLY/OFF vertex records, STL's distinct
    /// corners, glTF accessor vertices; from 0) and its face indices the file's faces (OBJ `f`
    /// statements, PLY/OFF face records, STL and glTF triangles; from 0); `location` names
    /// them as a person finds them (OBJ line numbers).
    #[error("{error}; in the file: {location}")]
    InFile {
        error: Box<MeshError>,
        location: String,
    },

    /// Valid but outside what Willow handles (e.g. sparse or quantized positions).
    #[error("unsupported: {detail}")]
    Unsupported { detail: String },
}

impl MeshError {
    /// A stable machine-readable code, e.g. `"non_manifold_edge"`. The API layers put it in
    /// problem+json `type`s and gRPC error details; it never changes once released.
    pub fn code(&self) -> &'static str {
        match self {
            MeshError::Empty { .. } => "empty_mesh",
            MeshError::PointsOrLinesOnly { .. } => "no_triangles",
            MeshError::NonFinite { .. } => "non_finite_coordinate",
            MeshError::CoordinateOutOfRange { .. } => "coordinate_out_of_range",
            MeshError::IndexOutOfRange { .. } => "index_out_of_range",
            MeshError::DegenerateFaces { .. } => "degenerate_face",
            MeshError::UnreferencedVertices { .. } => "unreferenced_vertex",
            MeshError::NonManifoldEdges { .. } => "non_manifold_edge",
            MeshError::NonManifoldVertices { .. } => "non_manifold_vertex",
            MeshError::NonOrientable { .. } => "non_orientable",
            MeshError::TooLarge { .. } => "too_large",
            MeshError::Parse { .. } => "parse_error",
            MeshError::ExternalUri { .. } => "external_uri",
            MeshError::TruncatedBuffer { .. } => "truncated_buffer",
            MeshError::PositionCount { .. } => "position_count_mismatch",
            MeshError::FormatMismatch { .. } => "format_mismatch",
            MeshError::NotAMesh { .. } => "not_a_mesh",
            MeshError::Unsupported { .. } => "unsupported",
            MeshError::InFile { error, .. } => error.code(),
        }
    }

    /// True when the input itself is bad (a client error: HTTP 422 / gRPC INVALID_ARGUMENT)
    /// rather than over a limit (HTTP 413 / RESOURCE_EXHAUSTED).
    pub fn is_too_large(&self) -> bool {
        match self {
            MeshError::InFile { error, .. } => error.is_too_large(),
            e => matches!(e, MeshError::TooLarge { .. }),
        }
    }

    pub(crate) fn parse(format: FormatName, detail: impl Into<String>) -> Self {
        MeshError::Parse {
            format,
            detail: detail.into(),
        }
    }

    pub(crate) fn truncated(detail: impl Into<String>) -> Self {
        MeshError::TruncatedBuffer {
            detail: detail.into(),
        }
    }

    pub(crate) fn unsupported(detail: impl Into<String>) -> Self {
        MeshError::Unsupported {
            detail: detail.into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offenders_keep_the_first_few_and_count_all() {
        let mut o = Offenders::default();
        for i in 0..20usize {
            o.push(i * 2);
        }
        assert_eq!(o.count, 20);
        assert_eq!(
            o.first,
            (0..MAX_REPORTED).map(|i| i * 2).collect::<Vec<_>>()
        );
        assert_eq!(o.to_string(), "0, 2, 4, 6, 8, 10, 12, 14, …");
    }

    #[test]
    fn messages_name_count_and_first_indices() {
        let mut faces = Offenders::default();
        faces.push(3);
        faces.push(7);
        let e = MeshError::DegenerateFaces { faces };
        assert_eq!(
            e.to_string(),
            "2 triangles are degenerate (a repeated vertex or exactly zero area); first: 3, 7"
        );
        assert_eq!(e.code(), "degenerate_face");
    }
}
