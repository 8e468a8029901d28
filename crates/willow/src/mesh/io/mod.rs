//! Reading and writing OBJ, glTF, GLB, STL, PLY and OFF while keeping everything the flow does not touch.
//!
//! An [`Asset`] holds three views of one file:
//!
//! - the **file vertices**, in the user's own numbering: for OBJ the `v` lines, in file order
//!   and count (unused ones included); for glTF/GLB the vertices of each POSITION accessor, in
//!   the file's local space. Streamed frames and [`Asset::file_positions`] use this order;
//! - the **split vertices** (internal): file vertices split at UV seams and hard normals
//!   (for OBJ each distinct `v/vt/vn` corner; for glTF the accessor vertices themselves), which
//!   carry one UV and one normal each, as glTF and GPUs want them; and
//! - the **surface** ([`Asset::surface`]): split vertices welded by exact world-space position
//!   into one validated, oriented [`Mesh`], which is what the flow moves.
//!
//! The maps split vertex → welded vertex and split vertex → file vertex are kept, so new
//! positions scatter back to every copy of a vertex identically and seams never open. Writing
//! replaces positions (and recomputes normals) but keeps the rest of the file: for OBJ the text
//! itself, byte for byte apart from the numbers on `v` and `vn` lines; for glTF the document.
//!
//! Uploads are untrusted: nothing here reads a file or the network, every size is checked
//! against [`Limits`] before allocation, and every malformed input is a [`MeshError`].

mod affine;
mod filled;
mod format;
mod gltf;
mod groups;
mod locate;
mod obj;
mod off;
mod ply;
mod refined;
mod repair;
mod stl;
mod text;
mod weld;

pub(crate) use affine::Affine;
pub use format::{foreign_content, Format, ALL_FORMATS};
pub use refined::Refinement;
pub use repair::Repairs;

use super::{Mesh, MeshError};
use std::collections::HashMap;
use std::fmt;

pub use super::Limits;

/// A run of split vertices sharing one local→world transform (one glTF POSITION accessor).
#[derive(Clone, Debug)]
pub(crate) struct Block {
    pub(crate) start: usize,
    pub(crate) len: usize,
    pub(crate) to_world: Affine,
    pub(crate) to_local: Affine,
}

/// The file's split vertices (see the module docs) and triangles, before welding.
#[derive(Clone, Debug)]
pub(crate) struct FileGeometry {
    /// Positions as stored, in each block's local space.
    pub(crate) local: Vec<[f64; 3]>,
    /// Consecutive blocks covering every split vertex.
    pub(crate) blocks: Vec<Block>,
    /// Triangles over split vertices, in the order the surface's faces follow.
    pub(crate) triangles: Vec<[usize; 3]>,
    /// Per split vertex UV in glTF's convention (origin top left), if the file has UVs.
    pub(crate) uvs: Option<Vec<Option<[f64; 2]>>>,
    /// Per split vertex identity of its stored normal (OBJ `vn` index, or glTF normal value),
    /// if the file has normals: copies of a welded vertex with the same key are smooth, with
    /// different keys a crease.
    pub(crate) normal_keys: Option<Vec<u64>>,
    /// The file's own face number of each triangle (OBJ `f` statements, PLY/OFF face
    /// records, counted from 0), when polygons were fan-triangulated; `None`: triangle `t` is
    /// the file's face `t` (STL, glTF, meshes made in code).
    pub(crate) face_of_triangle: Option<Vec<u32>>,
    /// Split vertices `local.len() - copies.len()..` are copies `repair` made: the original
    /// split vertex of each (see repair.rs).
    pub(crate) copies: Vec<usize>,
}

impl FileGeometry {
    /// One untransformed block over `local`, with no UVs, normals or face numbers: what
    /// every format but glTF starts from.
    pub(crate) fn one_block(local: Vec<[f64; 3]>, triangles: Vec<[usize; 3]>) -> Self {
        let len = local.len();
        FileGeometry {
            local,
            blocks: vec![Block {
                start: 0,
                len,
                to_world: Affine::IDENTITY,
                to_local: Affine::IDENTITY,
            }],
            triangles,
            uvs: None,
            normal_keys: None,
            face_of_triangle: None,
            copies: Vec::new(),
        }
    }

    /// Split vertices read from the file (not copies made by `repair`).
    pub(crate) fn read_count(&self) -> usize {
        self.local.len() - self.copies.len()
    }

    /// The split vertex read from the file that `sv` is (or is a copy of).
    pub(crate) fn original(&self, sv: usize) -> usize {
        sv.checked_sub(self.read_count())
            .and_then(|k| self.copies.get(k).copied())
            .unwrap_or(sv)
    }
}

/// Welded vertex of a split vertex that no triangle uses.
const UNWELDED: usize = usize::MAX;

#[derive(Clone)]
enum Source {
    Obj(obj::ObjSource),
    Gltf(gltf::GltfSource),
    Stl(stl::StlSource),
    Ply(ply::PlySource),
    Off(off::OffSource),
    /// Made in code ([`Asset::from_mesh`]): no file to keep; file vertices are the welded ones.
    Code,
    /// Subdivided ([`Asset::refined`]): the file's vertices, then the new ones.
    Refined(refined::RefinedSource),
}

impl Source {
    /// The file vertex (see [`Asset::file_vertex_count`]) of split vertex `sv`.
    pub(crate) fn file_vertex_of_split(&self, sv: usize) -> usize {
        self.v_of_split()
            .and_then(|v| v.get(sv).copied())
            .unwrap_or(sv)
    }

    /// Split vertex → file vertex where the two differ (OBJ `v` lines, a refined asset).
    fn v_of_split(&self) -> Option<&[usize]> {
        match self {
            Source::Obj(src) => Some(src.v_of_split()),
            Source::Refined(src) => Some(&src.v_of_split),
            _ => None,
        }
    }

    /// Whether the file's vertex records are its split vertices one for one, in file order
    /// (PLY and OFF): a result in another indexed format then keeps that numbering.
    fn numbers_split_vertices(&self) -> bool {
        // Arrays made in code ([`Asset::from_indexed`]) number their vertices as given; for
        // [`Asset::from_mesh`] split and welded vertices are one, so nothing changes there.
        matches!(self, Source::Ply(_) | Source::Off(_) | Source::Code)
    }

    /// Per file vertex, its stored position, where file vertices are not split vertices.
    fn stored_positions(&self) -> Option<Vec<[f64; 3]>> {
        match self {
            Source::Obj(src) => Some(src.stored_positions()),
            Source::Refined(src) => Some(src.stored.clone()),
            _ => None,
        }
    }
}

/// A mesh file read into memory: its welded surface plus everything needed to write it back.
#[derive(Clone)]
pub struct Asset {
    format: Format,
    surface: Mesh,
    file: FileGeometry,
    /// Split vertex → welded vertex (`UNWELDED` if unused).
    to_welded: Vec<usize>,
    /// Per split vertex normal group (`UNWELDED` if unused) and the number of groups, when the
    /// file has normals: a group is the copies of one welded vertex sharing a stored normal.
    normal_groups: Option<(Vec<usize>, usize)>,
    source: Source,
    /// What `read_repaired` changed (empty otherwise).
    repairs: Repairs,
}

impl fmt::Debug for Asset {
    /// A summary: the buffers may be hundreds of megabytes.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Asset")
            .field("format", &self.format)
            .field("file_vertices", &self.file_vertex_count())
            .field("split_vertices", &self.file.local.len())
            .field("welded_vertices", &self.surface.vertex_count())
            .field("faces", &self.surface.face_count())
            .field("has_uvs", &self.file.uvs.is_some())
            .field("has_normals", &self.normal_groups.is_some())
            .finish()
    }
}

impl Asset {
    /// Parses and validates a file held in memory. Never touches the filesystem or network.
    ///
    /// `Format::Gltf` and `Format::Glb` both accept either container (told apart by the GLB
    /// magic bytes), since uploads are often mislabelled; the format only chooses the parser
    /// family. Checks `limits.max_bytes` first, then vertex and face counts before allocating.
    ///
    /// Content that is plainly something else gets a specific error rather than the parser's
    /// confusion: gzip, zip and UTF-16 bodies are named ([`MeshError::NotAMesh`]), and a file
    /// that fails to parse as `format` but sniffs as another format (an OFF or ASCII STL sent
    /// as OBJ) is a [`MeshError::FormatMismatch`] naming the right one.
    pub fn read(bytes: &[u8], format: Format, limits: &Limits) -> Result<Asset, MeshError> {
        Asset::read_with(bytes, format, limits, false)
    }

    /// [`Asset::read`] with the opt-in repair: degenerate faces are dropped, and vertices whose
    /// faces form several fans (bowties, the ends of edges with three or more faces) are split
    /// into one vertex per fan. [`Asset::repairs`] says what changed, in file numbering. A file
    /// that needs no repair reads exactly as with [`Asset::read`].
    ///
    /// Written back in its own format, a file keeps its own faces and vertex sharing (dropped
    /// faces stay in an OBJ/PLY/OFF/glTF, a split vertex gets its first fan's position); other
    /// formats carry the repaired surface.
    pub fn read_repaired(
        bytes: &[u8],
        format: Format,
        limits: &Limits,
    ) -> Result<Asset, MeshError> {
        Asset::read_with(bytes, format, limits, true)
    }

    /// What [`Asset::read_repaired`] changed (empty for [`Asset::read`]).
    pub fn repairs(&self) -> &Repairs {
        &self.repairs
    }

    /// What a result written in the input's own format cannot keep of the input as it was,
    /// one sentence each, for people: a meshopt- or Draco-compressed glTF written back as
    /// plain data, quantized POSITION/NORMAL re-quantized over the faired box (or, where a new
    /// node transform would move something else, written as float32), morph targets dropped.
    /// Empty when the input is kept as it was.
    pub fn notes(&self) -> Vec<String> {
        match &self.source {
            Source::Gltf(src) => src.notes.clone(),
            Source::Refined(src) => src.notes.clone(),
            _ => Vec::new(),
        }
    }

    /// A glTF's NORMAL per file vertex (see [`Asset::file_vertex_count`]) as the file stores
    /// it, decoded (meshopt's octahedral filter, Draco) and dequantized, in the accessor's
    /// local space; `None` for a vertex without one, and for files of other formats. What a
    /// decoder test compares with the uncompressed file; results recompute normals instead.
    pub fn file_normals(&self) -> Option<Vec<Option<[f64; 3]>>> {
        match &self.source {
            Source::Gltf(src) => src.normals.clone(),
            _ => None,
        }
    }

    fn read_with(
        bytes: &[u8],
        format: Format,
        limits: &Limits,
        repair: bool,
    ) -> Result<Asset, MeshError> {
        limits.check_bytes(bytes.len())?;
        if let Some(what) = foreign_content(bytes) {
            return Err(MeshError::NotAMesh {
                declared: format_name(format),
                what,
            });
        }
        Asset::read_as(bytes, format, limits, repair).map_err(|e| {
            let same_family = |f: Format| {
                f == format
                    || matches!(
                        (f, format),
                        (Format::Gltf | Format::Glb, Format::Gltf | Format::Glb)
                    )
            };
            match Format::sniff(bytes) {
                Some(found) if !same_family(found) && !e.is_too_large() => {
                    MeshError::FormatMismatch {
                        declared: format_name(format),
                        found: format_name(found),
                        mime: found.mime(),
                        extension: found.extension(),
                    }
                }
                _ => e,
            }
        })
    }

    fn read_as(
        bytes: &[u8],
        format: Format,
        limits: &Limits,
        repair: bool,
    ) -> Result<Asset, MeshError> {
        match format {
            Format::Obj => {
                let (file, src) = obj::read(bytes, limits)?;
                Asset::assemble(format, file, Source::Obj(src), limits, repair)
            }
            Format::Gltf | Format::Glb => {
                let (file, src) = gltf::read(bytes, format, limits)?;
                Asset::assemble(format, file, Source::Gltf(src), limits, repair)
            }
            Format::Stl => {
                let (file, src) = stl::read(bytes, limits)?;
                Asset::assemble(format, file, Source::Stl(src), limits, repair)
            }
            Format::Ply => {
                let (file, src) = ply::read(bytes, limits)?;
                Asset::assemble(format, file, Source::Ply(src), limits, repair)
            }
            Format::Off => {
                let (file, src) = off::read(bytes, limits)?;
                Asset::assemble(format, file, Source::Off(src), limits, repair)
            }
        }
    }

    /// Welds the split vertices by exact world position and validates the result.
    fn assemble(
        format: Format,
        mut file: FileGeometry,
        source: Source,
        limits: &Limits,
        repair: bool,
    ) -> Result<Asset, MeshError> {
        limits.check_vertices(file.local.len())?;
        limits.check_faces(file.triangles.len())?;
        let mut world = Vec::new();
        world
            .try_reserve_exact(file.local.len())
            .map_err(|_| MeshError::TooLarge {
                what: "vertices (out of memory)",
                value: file.local.len(),
                limit: limits.max_vertices,
            })?;
        for b in &file.blocks {
            for p in file.local.get(b.start..b.start + b.len).unwrap_or(&[]) {
                world.push(b.to_world.apply(*p));
            }
        }
        let mut repairs = Repairs::default();
        if repair {
            repair::drop_degenerate(&mut file, &world, &mut repairs);
        }
        // See weld.rs: by exact position first; only if that surface is refused, again by
        // corners, so coincident vertices the file keeps apart stay apart.
        let fast = weld::by_position(&world, &file.triangles).ok_or_else(|| {
            MeshError::parse(format_name(format), "triangle references a missing vertex")
        })?;
        let (to_welded, surface) = match Mesh::with_limits(fast.positions, fast.triangles, limits) {
            Ok(surface) => (fast.to_welded, surface),
            Err(e) if e.is_too_large() => return Err(e),
            Err(_) => {
                let file_of_split = |sv: usize| source.file_vertex_of_split(sv);
                let mut w = weld::by_corners(&world, &file.triangles, &file_of_split, !repair);
                if repair {
                    repair::split_copies(&mut file, &mut w, &file_of_split, &mut repairs);
                }
                let mut split_of_surface = vec![UNWELDED; w.positions.len()];
                for (ft, st) in file.triangles.iter().zip(&w.triangles) {
                    for (&sv, &v) in ft.iter().zip(st) {
                        if let Some(slot) = split_of_surface.get_mut(v) {
                            if *slot == UNWELDED {
                                *slot = sv;
                            }
                        }
                    }
                }
                match Mesh::with_limits(w.positions, w.triangles, limits) {
                    Ok(surface) => (w.to_welded, surface),
                    Err(e) => {
                        let file_of_any =
                            |sv: usize| source.file_vertex_of_split(file.original(sv));
                        let origins = locate::Origins {
                            format,
                            source: &source,
                            file: &file,
                            split_of_surface,
                            file_of_split: &file_of_any,
                        };
                        return Err(origins.locate(e));
                    }
                }
            }
        };

        let normal_groups = file
            .normal_keys
            .as_ref()
            .map(|keys| normal_groups_of(&to_welded, keys));
        Ok(Asset {
            format,
            surface,
            file,
            to_welded,
            normal_groups,
            source,
            repairs,
        })
    }

    /// An asset for a mesh made in code (e.g. [`generate`](super::generate)), so it can be
    /// written as OBJ, glTF or GLB. Validates and orients it like [`Mesh::new`]; vertex order
    /// is kept (file vertex `i` is welded vertex `i`). It has no UVs, normals or materials.
    pub fn from_mesh(mesh: Mesh, limits: &Limits) -> Result<Asset, MeshError> {
        let file_triangles = mesh.triangles.clone();
        let surface = Mesh::with_limits(mesh.positions, mesh.triangles, limits)?;
        let n = surface.vertex_count();
        let file = FileGeometry::one_block(surface.positions.clone(), file_triangles);
        Ok(Asset {
            format: Format::Obj,
            surface,
            file,
            to_welded: (0..n).collect(),
            normal_groups: None,
            source: Source::Code,
            repairs: Repairs::default(),
        })
    }

    /// An asset for indexed triangle arrays made in code (a numpy array, trimesh, libigl),
    /// welded exactly as a file's vertices are (module docs): vertices at the same exact
    /// position join, so split copies (UV seams, an STL-like soup) move together, unless that
    /// would make the surface non-manifold; vertices no triangle uses are left out of the
    /// surface and keep their position. Its file vertices are the arrays' vertices, in their
    /// order ([`Asset::file_to_welded`], [`Asset::file_world_positions`]); surface errors
    /// come as [`MeshError::InFile`] in that numbering, and a new file written from it keeps
    /// that numbering where the format has one (OBJ, glTF, GLB, PLY, OFF).
    pub fn from_indexed(
        positions: Vec<[f64; 3]>,
        triangles: Vec<[usize; 3]>,
        limits: &Limits,
    ) -> Result<Asset, MeshError> {
        let n = positions.len();
        let mut out_of_range = super::error::Offenders::default();
        for (f, t) in triangles.iter().enumerate() {
            if t.iter().any(|&v| v >= n) {
                out_of_range.push(f);
            }
        }
        if !out_of_range.is_empty() {
            return Err(MeshError::IndexOutOfRange {
                faces: out_of_range,
                vertex_count: n,
            });
        }
        let file = FileGeometry::one_block(positions, triangles);
        Asset::assemble(Format::Obj, file, Source::Code, limits, false)
    }

    /// The welded, validated, consistently oriented surface in world space (glTF node
    /// transforms applied): what the flow moves.
    pub fn surface(&self) -> &Mesh {
        &self.surface
    }

    /// The format the asset was read from.
    pub fn format(&self) -> Format {
        self.format
    }

    /// Writes the asset with new welded world-space positions (same length and order as
    /// `surface().positions`).
    ///
    /// Writing the format it was read from keeps everything else: for glTF/GLB the whole
    /// document (materials, textures, image bytes, samplers, UVs, indices, nodes) with only
    /// POSITION replaced, NORMAL recomputed and TANGENT dropped (stale once positions move;
    /// viewers compute MikkTSpace tangents themselves when none are given); for OBJ the text
    /// byte for byte except the coordinates of every `v` line (in file order, unused ones
    /// keeping their stored position) and the numbers of every `vn` line a face uses
    /// (recomputed). Across formats, positions, UVs, normals and faces carry over (OBJ has no
    /// textures to carry into glTF); faces then follow the oriented surface. A refined asset
    /// written in its input's format keeps the input's document or statements the same way,
    /// with the subdivided vertices and faces in place of the input's (see `refined.rs`).
    pub fn write(&self, positions: &[[f64; 3]], format: Format) -> Result<Vec<u8>, MeshError> {
        self.check_positions(positions)?;
        match (&self.source, format) {
            (Source::Obj(src), Format::Obj) => Ok(obj::write_kept(self, src, positions)),
            (Source::Gltf(src), Format::Gltf | Format::Glb) => {
                gltf::write_document(self, src, positions, format == Format::Glb)
            }
            (Source::Stl(src), Format::Stl) => Ok(stl::write_kept(self, src, positions)),
            (Source::Ply(src), Format::Ply) => ply::write_kept(self, src, positions),
            (Source::Off(src), Format::Off) => Ok(off::write_kept(self, src, positions)),
            (Source::Refined(r), Format::Gltf | Format::Glb) => match r.original.as_ref() {
                Source::Gltf(src) => {
                    gltf::refined::write(self, src, r, positions, format == Format::Glb)
                }
                _ => gltf::write_new(self, positions, format == Format::Glb),
            },
            (Source::Refined(r), Format::Obj) => match r.original.as_ref() {
                Source::Obj(src) => Ok(obj::write_refined(self, src, r, positions)),
                _ => Ok(obj::write_new(self, positions)),
            },
            (_, Format::Obj) => Ok(obj::write_new(self, positions)),
            (_, Format::Gltf | Format::Glb) => {
                gltf::write_new(self, positions, format == Format::Glb)
            }
            (_, Format::Stl) => stl::write_new(self, positions),
            (_, Format::Ply) => ply::write_new(self, positions),
            (_, Format::Off) => Ok(off::write_new(self, positions)),
        }
    }

    /// For a PLY or OFF asset: every split vertex in file order (the file's records, then the
    /// copies a repair made) at its position in `positions` (welded), or at its stored
    /// position for a record no face uses. `None` for other sources, whose results number
    /// vertices as their own writers do. What keeps a PLY's numbering in an OBJ (issue 39).
    pub(crate) fn split_vertex_positions(&self, positions: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        if !self.source.numbers_split_vertices() {
            return None;
        }
        Some(
            self.to_welded
                .iter()
                .zip(&self.file.local)
                .map(|(&w, stored)| if w == UNWELDED { *stored } else { positions[w] })
                .collect(),
        )
    }

    /// The number of the file's own vertices, in the user's numbering.
    ///
    /// For OBJ, the `v` lines (all of them, used by a face or not). For glTF/GLB, the
    /// vertices of each POSITION accessor used by a triangle primitive of the scene, accessors
    /// in order of first use (scene nodes depth first, children in order, each mesh's
    /// primitives in order), each accessor's vertices in accessor order. For an asset made in
    /// code, its welded vertices. Streamed frames carry this many positions, in this order.
    pub fn file_vertex_count(&self) -> usize {
        match &self.source {
            Source::Obj(src) => src.v_count(),
            Source::Refined(src) => src.stored.len(),
            _ => self.file.read_count(),
        }
    }

    /// The surface vertex of each of `file_vertices` (file numbering, see
    /// [`Asset::file_vertex_count`]: OBJ `v` lines from 0, glTF accessor vertices in order):
    /// how a vertex a user names in their file is found on the welded surface. `Err` names
    /// the first index that is past the file or on no triangle.
    pub fn surface_vertices(&self, file_vertices: &[usize]) -> Result<Vec<usize>, usize> {
        let count = self.file_vertex_count();
        let mut welded_of_file = vec![UNWELDED; count];
        match self.source.v_of_split() {
            Some(v_of_split) => {
                for (split, &v) in v_of_split.iter().enumerate() {
                    if let (Some(slot), Some(&w)) =
                        (welded_of_file.get_mut(v), self.to_welded.get(split))
                    {
                        *slot = w;
                    }
                }
            }
            None => {
                for (slot, &w) in welded_of_file.iter_mut().zip(&self.to_welded) {
                    *slot = w;
                }
            }
        }
        file_vertices
            .iter()
            .map(|&f| match welded_of_file.get(f) {
                Some(&w) if w != UNWELDED => Ok(w),
                _ => Err(f),
            })
            .collect()
    }

    /// New welded world-space positions scattered to the file's vertex order (see
    /// [`Asset::file_vertex_count`]), in the file's local space (node transforms undone), as
    /// f32: what streamed frames carry. For OBJ, entry `k` is the new position of the k-th `v`
    /// line, which the written OBJ holds (in f64) on that line.
    ///
    /// Vertices no triangle uses keep their stored position. `positions` should have
    /// `surface().vertex_count()` entries; a vertex beyond a shorter slice keeps its stored
    /// position too (this cannot fail, so it degrades rather than panics).
    pub fn file_positions(&self, positions: &[[f64; 3]]) -> Vec<[f32; 3]> {
        self.file_positions_relative(positions, [0.0; 3])
    }

    /// [`Asset::file_positions`] less `origin`, subtracted in f64 before the cast: with
    /// `origin` from [`Asset::frame_origin`] the f32 offsets keep ~1e-7 of the model's size at
    /// any distance from the origin (issue 27, item 4), where f32 coordinates themselves keep
    /// only ~6e-8 of that distance (a 0.5 grid at 5e6).
    pub fn file_positions_relative(
        &self,
        positions: &[[f64; 3]],
        origin: [f64; 3],
    ) -> Vec<[f32; 3]> {
        self.file_positions_f64(positions)
            .into_iter()
            .map(|p| [0, 1, 2].map(|k| (p[k] - origin[k]) as f32))
            .collect()
    }

    /// The origin streamed frames are sent relative to: the centre of the input's bounding
    /// box (in the file's local space, as frames are) when the model lies farther from the
    /// origin than its own size, else exactly zero, so frames of models around the origin
    /// are the plain coordinates they always were. Fixed by the input alone, so a resumed job
    /// streams against the same origin.
    pub fn frame_origin(&self) -> [f64; 3] {
        gltf::far_origin(&self.file_positions_f64(&self.surface().positions)).unwrap_or([0.0; 3])
    }

    /// Triangles over file vertices (see [`Asset::file_vertex_count`]), wound like the
    /// oriented surface and in its face order: for OBJ the `v` indices (0-based) of each
    /// fan-triangulated `f` line.
    pub fn file_triangles(&self) -> Vec<[usize; 3]> {
        let split = self.oriented_split_triangles();
        match self.source.v_of_split() {
            Some(v_of) => split
                .iter()
                .map(|t| t.map(|sv| v_of.get(self.file.original(sv)).copied().unwrap_or(0)))
                .collect(),
            None => split
                .iter()
                .map(|t| t.map(|sv| self.file.original(sv)))
                .collect(),
        }
    }

    /// Per triangle of [`Asset::file_triangles`], the UV of each corner (glTF convention:
    /// origin at the top left of the image), if the file has UVs; corners without one get
    /// `[0, 0]`. Per corner, because an OBJ `v` has one UV per face around it at a seam.
    pub fn corner_uvs(&self) -> Option<Vec<[[f32; 2]; 3]>> {
        let uvs = self.file.uvs.as_ref()?;
        let uv = |sv: usize| {
            uvs.get(sv)
                .copied()
                .flatten()
                .unwrap_or([0.0; 2])
                .map(|x| x as f32)
        };
        Some(
            self.oriented_split_triangles()
                .iter()
                .map(|t| t.map(uv))
                .collect(),
        )
    }

    /// The welded vertex of each file vertex (see [`Asset::file_vertex_count`]; `None` for
    /// vertices no triangle uses).
    pub fn file_to_welded(&self) -> Vec<Option<usize>> {
        let split = self.to_welded.iter().map(|&w| (w != UNWELDED).then_some(w));
        match self.source.v_of_split() {
            Some(v_of_split) => {
                let mut out = vec![None; self.file_vertex_count()];
                for (&v, w) in v_of_split.iter().zip(split) {
                    if let Some(slot) = out.get_mut(v) {
                        *slot = slot.or(w);
                    }
                }
                out
            }
            None => split.take(self.file.read_count()).collect(),
        }
    }

    fn check_positions(&self, positions: &[[f64; 3]]) -> Result<(), MeshError> {
        if positions.len() != self.surface.vertex_count() {
            return Err(MeshError::PositionCount {
                expected: self.surface.vertex_count(),
                got: positions.len(),
            });
        }
        let mut bad = super::error::Offenders::default();
        for (v, p) in positions.iter().enumerate() {
            if !p.iter().all(|x| x.is_finite()) {
                bad.push(v);
            }
        }
        if !bad.is_empty() {
            return Err(MeshError::NonFinite { vertices: bad });
        }
        Ok(())
    }

    /// Per file vertex position (see [`Asset::file_positions`]), in f64.
    pub(crate) fn file_positions_f64(&self, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        self.per_file_vertex(self.split_positions(positions))
    }

    /// New welded world-space positions scattered to the file's vertex order (see
    /// [`Asset::file_vertex_count`]) in world space and f64: the arrays a caller fairs and
    /// writes back with the file's numbering (the Python package's `read`). Vertices no
    /// triangle uses keep their stored position (OBJ `v` lines, which no transform moves).
    pub fn file_world_positions(&self, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        self.per_file_vertex(self.split_world_positions(positions))
    }

    /// Split vertex positions gathered to file vertices.
    fn per_file_vertex(&self, split: Vec<[f64; 3]>) -> Vec<[f64; 3]> {
        match (self.source.v_of_split(), self.source.stored_positions()) {
            (Some(v_of_split), Some(stored)) => {
                // Every copy of a `v` line has the same stored position, hence one welded
                // vertex: writing each copy's new position gives the same value.
                let mut out = stored;
                for ((&v, p), &w) in v_of_split.iter().zip(split).zip(&self.to_welded) {
                    if let (Some(slot), true) = (out.get_mut(v), w != UNWELDED) {
                        *slot = p;
                    }
                }
                out
            }
            _ => {
                let mut split = split;
                split.truncate(self.file.read_count());
                split
            }
        }
    }

    /// Per split vertex position in world space, in f64 (vertices no triangle uses keep their
    /// stored position).
    pub(crate) fn split_world_positions(&self, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        let mut out = self.file.local.clone();
        for b in &self.file.blocks {
            for fv in b.start..b.start + b.len {
                let w = self.to_welded.get(fv).copied().unwrap_or(UNWELDED);
                if let Some(slot) = out.get_mut(fv) {
                    *slot = positions.get(w).copied().unwrap_or(b.to_world.apply(*slot));
                }
            }
        }
        out
    }

    /// Per split vertex position in its block's local space, in f64.
    pub(crate) fn split_positions(&self, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        let mut out = self.file.local.clone();
        for b in &self.file.blocks {
            for fv in b.start..b.start + b.len {
                let w = self.to_welded.get(fv).copied().unwrap_or(UNWELDED);
                if let (Some(p), Some(slot)) = (positions.get(w), out.get_mut(fv)) {
                    *slot = b.to_local.apply(*p);
                }
            }
        }
        out
    }

    /// Split triangles wound like the oriented surface (Mesh::new only ever swaps corners 1
    /// and 2, and keeps face order, so comparing welded corners tells which were flipped).
    pub(crate) fn oriented_split_triangles(&self) -> Vec<[usize; 3]> {
        self.file
            .triangles
            .iter()
            .zip(&self.surface.triangles)
            .map(|(&[a, b, c], s)| {
                let w = |fv: usize| self.to_welded.get(fv).copied().unwrap_or(UNWELDED);
                if [w(a), w(b), w(c)] == *s {
                    [a, b, c]
                } else {
                    [a, c, b]
                }
            })
            .collect()
    }

    /// Area-weighted normal of each normal group, in world space, unit length.
    ///
    /// Grouping by (welded vertex, stored normal) keeps smooth shading across UV seams (the
    /// copies share a stored normal) and creases where the file had split normals.
    pub(crate) fn group_normals(&self, positions: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        let (groups, count) = self.normal_groups.as_ref()?;
        let mut sums = vec![[0.0f64; 3]; *count];
        for (ft, st) in self
            .oriented_split_triangles()
            .iter()
            .zip(&self.surface.triangles)
        {
            let p = |v: usize| positions.get(v).copied().unwrap_or([0.0; 3]);
            let (a, b, c) = (p(st[0]), p(st[1]), p(st[2]));
            // |(b−a)×(c−a)| is twice the area: area weighting comes for free.
            let n = cross(sub(b, a), sub(c, a));
            for &fv in ft {
                if let Some(sum) = groups.get(fv).and_then(|&g| sums.get_mut(g)) {
                    for k in 0..3 {
                        sum[k] += n[k];
                    }
                }
            }
        }
        Some(sums.into_iter().map(normalize_or_z).collect())
    }

    /// Per split vertex world-space unit normal (`[0, 0, 1]` for unused vertices).
    pub(crate) fn split_normals_world(&self, positions: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        let group_normals = self.group_normals(positions)?;
        let (groups, _) = self.normal_groups.as_ref()?;
        Some(
            groups
                .iter()
                .map(|&g| group_normals.get(g).copied().unwrap_or([0.0, 0.0, 1.0]))
                .collect(),
        )
    }
}

/// Per split vertex normal group (`UNWELDED` if unused) and the number of groups: a group is
/// the copies of one welded vertex sharing a stored normal key.
fn normal_groups_of(to_welded: &[usize], keys: &[u64]) -> (Vec<usize>, usize) {
    let mut groups: HashMap<(usize, u64), usize> = HashMap::new();
    let per_vertex: Vec<usize> = to_welded
        .iter()
        .zip(keys)
        .map(|(&w, &k)| {
            if w == UNWELDED {
                return UNWELDED;
            }
            let n = groups.len();
            *groups.entry((w, k)).or_insert(n)
        })
        .collect();
    (per_vertex, groups.len())
}

pub(crate) fn format_name(format: Format) -> &'static str {
    match format {
        Format::Obj => "OBJ",
        Format::Gltf => "glTF",
        Format::Glb => "GLB",
        Format::Stl => "STL",
        Format::Ply => "PLY",
        Format::Off => "OFF",
    }
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(u: [f64; 3], w: [f64; 3]) -> [f64; 3] {
    [
        u[1] * w[2] - u[2] * w[1],
        u[2] * w[0] - u[0] * w[2],
        u[0] * w[1] - u[1] * w[0],
    ]
}

/// Unit vector along `n`, or `+z` for a zero (or non-finite) vector, so a written normal is
/// always valid even where area-weighted normals cancel.
pub(crate) fn normalize_or_z(n: [f64; 3]) -> [f64; 3] {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        [n[0] / len, n[1] / len, n[2] / len]
    } else {
        [0.0, 0.0, 1.0]
    }
}
