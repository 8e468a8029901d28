//! Surface errors told in the file's own numbering (issue 27, item 3): the validator numbers
//! the welded surface, which no user has seen; this maps its vertices and triangles back to the
//! file's vertices and faces, and says where they are (OBJ line numbers; STL corners by
//! position, since STL has no vertex numbers).

use super::{FileGeometry, Format, MeshError, Source};
use crate::mesh::error::Offenders;

/// Where the surface's vertices and triangles come from in the file.
pub(crate) struct Origins<'a> {
    pub(crate) format: Format,
    pub(crate) source: &'a Source,
    pub(crate) file: &'a FileGeometry,
    /// Surface vertex → a split vertex of it.
    pub(crate) split_of_surface: Vec<usize>,
    /// Split vertex → file vertex.
    pub(crate) file_of_split: &'a dyn Fn(usize) -> usize,
}

impl Origins<'_> {
    fn vertex(&self, v: usize) -> usize {
        self.split_of_surface
            .get(v)
            .map_or(v, |&sv| (self.file_of_split)(sv))
    }

    fn face(&self, t: usize) -> usize {
        match &self.file.face_of_triangle {
            Some(faces) => faces.get(t).map_or(t, |&f| f as usize),
            None => t,
        }
    }

    /// Human names of file vertices: OBJ `v` line numbers, STL positions, else indices.
    fn vertex_names(&self, vs: &[usize]) -> Vec<String> {
        match (self.source, self.format) {
            (Source::Obj(src), _) => src
                .v_line_numbers(vs)
                .iter()
                .zip(vs)
                .map(|(line, v)| match line {
                    Some(l) => format!("`v` on line {l}"),
                    None => format!("vertex {v}"),
                })
                .collect(),
            (_, Format::Stl) => vs
                .iter()
                .map(|&v| match self.file.local.get(v) {
                    Some(p) => format!("the corner at ({}, {}, {})", p[0], p[1], p[2]),
                    None => format!("corner {v}"),
                })
                .collect(),
            (_, Format::Ply | Format::Off) => vs.iter().map(|v| format!("vertex {v}")).collect(),
            _ => vs.iter().map(|v| format!("accessor vertex {v}")).collect(),
        }
    }

    fn face_names(&self, fs: &[usize]) -> Vec<String> {
        fs.iter()
            .map(|&f| match (self.source, self.format) {
                (Source::Obj(src), _) => match src.face_line(f) {
                    Some(l) => format!("the face on line {l}"),
                    None => format!("face {f}"),
                },
                (_, Format::Stl | Format::Gltf | Format::Glb) => format!("triangle {f}"),
                _ => format!("face {f}"),
            })
            .collect()
    }

    fn vertices(&self, o: &Offenders<usize>) -> (Offenders<usize>, String) {
        let first: Vec<usize> = o.first.iter().map(|&v| self.vertex(v)).collect();
        let names = self.vertex_names(&first).join(", ");
        (
            Offenders {
                count: o.count,
                first,
            },
            names,
        )
    }

    fn faces(&self, o: &Offenders<usize>) -> (Offenders<usize>, String) {
        let first: Vec<usize> = o.first.iter().map(|&t| self.face(t)).collect();
        let names = self.face_names(&first).join(", ");
        (
            Offenders {
                count: o.count,
                first,
            },
            names,
        )
    }

    /// `e` in the file's numbering, wrapped with where the offenders are; errors that name no
    /// surface element are returned as they are.
    pub(crate) fn locate(&self, e: MeshError) -> MeshError {
        let (error, location) = match e {
            MeshError::NonFinite { vertices } => {
                let (vertices, at) = self.vertices(&vertices);
                (MeshError::NonFinite { vertices }, at)
            }
            MeshError::CoordinateOutOfRange { vertices, limit } => {
                let (vertices, at) = self.vertices(&vertices);
                (MeshError::CoordinateOutOfRange { vertices, limit }, at)
            }
            MeshError::UnreferencedVertices { vertices } => {
                let (vertices, at) = self.vertices(&vertices);
                (MeshError::UnreferencedVertices { vertices }, at)
            }
            MeshError::NonManifoldVertices { vertices } => {
                let (vertices, at) = self.vertices(&vertices);
                (MeshError::NonManifoldVertices { vertices }, at)
            }
            MeshError::NonManifoldEdges { edges } => {
                let first: Vec<[usize; 2]> = edges
                    .first
                    .iter()
                    .map(|e| {
                        let (a, b) = (self.vertex(e[0]), self.vertex(e[1]));
                        [a.min(b), a.max(b)]
                    })
                    .collect();
                let flat: Vec<usize> = first.iter().flatten().copied().collect();
                let names = self.vertex_names(&flat);
                let at = names
                    .chunks(2)
                    .map(|p| format!("the edge between {}", p.join(" and ")))
                    .collect::<Vec<_>>()
                    .join(", ");
                let edges = Offenders {
                    count: edges.count,
                    first,
                };
                (MeshError::NonManifoldEdges { edges }, at)
            }
            MeshError::DegenerateFaces { faces } => {
                let (faces, at) = self.faces(&faces);
                (MeshError::DegenerateFaces { faces }, at)
            }
            MeshError::IndexOutOfRange {
                faces,
                vertex_count,
            } => {
                let (faces, at) = self.faces(&faces);
                (
                    MeshError::IndexOutOfRange {
                        faces,
                        vertex_count,
                    },
                    at,
                )
            }
            MeshError::NonOrientable { component, face } => {
                let face = self.face(face);
                let at = self.face_names(&[face]).join("");
                (MeshError::NonOrientable { component, face }, at)
            }
            other => return other,
        };
        MeshError::InFile {
            error: Box::new(error),
            location,
        }
    }
}
