//! `read` and `write`: the library's readers and writers (OBJ, glTF, GLB, STL, PLY, OFF) on
//! arrays in the file's own numbering (`Asset::file_vertex_count`): OBJ `v` lines (unused ones
//! included), glTF accessor vertices, PLY/OFF vertex records, STL's distinct corners.

use crate::arrays;
use crate::errors::{mesh_error, mesh_message};
use numpy::{PyArray2, PyReadonlyArray2};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyPermissionError, PyValueError};
use pyo3::prelude::*;
use std::path::{Path, PathBuf};
use willow::mesh::io::{Asset, Format, Limits};

fn io_error(e: std::io::Error, what: &str, path: &Path) -> PyErr {
    let message = format!("cannot {what} {}: {e}", path.display());
    match e.kind() {
        std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(message),
        std::io::ErrorKind::PermissionDenied => PyPermissionError::new_err(message),
        _ => PyOSError::new_err(message),
    }
}

/// A file read as the CLI reads it (its extension, else what its content shows), without
/// repair: a repaired surface has vertices the file's numbering cannot name.
fn read_asset(py: Python<'_>, path: &Path) -> PyResult<Asset> {
    let bytes = std::fs::read(path).map_err(|e| io_error(e, "read", path))?;
    let format = Format::from_path(path)
        .or_else(|| Format::sniff(&bytes))
        .ok_or_else(|| {
            PyValueError::new_err(format!(
                "{}: unknown extension and unrecognized content (expected .obj, .gltf, .glb, \
                 .stl, .ply or .off)",
                path.display()
            ))
        })?;
    py.detach(|| Asset::read(&bytes, format, &Limits::default()))
        .map_err(|e| {
            PyValueError::new_err(format!("{}: {}", path.display(), mesh_message(e, false)))
        })
}

/// `(V, F)`: positions and faces as numpy arrays.
type MeshArrays<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<i64>>);

/// `(V, F)` of a mesh file: float64 (n, 3) world-space positions and int64 (m, 3) 0-based
/// faces, in the file's numbering and wound like the oriented surface.
#[pyfunction]
pub fn read<'py>(py: Python<'py>, path: PathBuf) -> PyResult<MeshArrays<'py>> {
    let asset = read_asset(py, &path)?;
    let v = asset.file_world_positions(&asset.surface().positions);
    Ok((
        arrays::positions_array(py, v)?,
        arrays::triangles_array(py, &asset.file_triangles())?,
    ))
}

/// Write `V`, `F` to `path` in the format of its extension. With `like`, the file `like` is
/// written back with `V` as its positions (its UVs, normals, materials, groups and text kept),
/// so `V` must be in `like`'s numbering and `F` its faces (as `read(like)` gives them);
/// without, a new file of these arrays in their numbering.
#[pyfunction]
#[pyo3(signature = (path, vertices, faces, like=None))]
pub fn write(
    py: Python<'_>,
    path: PathBuf,
    vertices: PyReadonlyArray2<'_, f64>,
    faces: &Bound<'_, PyAny>,
    like: Option<PathBuf>,
) -> PyResult<()> {
    let format = Format::from_path(&path).ok_or_else(|| {
        PyValueError::new_err(format!(
            "path {}: unknown extension (expected .obj, .gltf, .glb, .stl, .ply or .off)",
            path.display()
        ))
    })?;
    let positions = arrays::positions(&vertices, "V")?;
    let triangles = arrays::triangles(faces, "F")?;
    let bytes = match like {
        Some(like) => {
            let asset = read_asset(py, &like)?;
            let welded = welded_like(&asset, &positions, &triangles, &like)?;
            py.detach(|| asset.write(&welded, format))
                .map_err(|e| mesh_error(e, false))?
        }
        None => py
            .detach(|| {
                let asset = Asset::from_indexed(positions, triangles, &Limits::default())?;
                asset.write(&asset.surface().positions, format)
            })
            .map_err(|e| mesh_error(e, true))?,
    };
    std::fs::write(&path, bytes).map_err(|e| io_error(e, "write", &path))
}

/// The welded positions of `asset` that `positions` (in its file numbering) give. Copies of a
/// vertex (a UV seam) are one surface vertex: the last copy's position counts.
fn welded_like(
    asset: &Asset,
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    like: &Path,
) -> PyResult<Vec<[f64; 3]>> {
    if positions.len() != asset.file_vertex_count() {
        return Err(PyValueError::new_err(format!(
            "V has {} rows but like={} has {} vertices",
            positions.len(),
            like.display(),
            asset.file_vertex_count()
        )));
    }
    if triangles != asset.file_triangles().as_slice() {
        return Err(PyValueError::new_err(format!(
            "F is not the faces of like={} (as read() gives them); write(path, V, F) without \
             like= writes a new file",
            like.display()
        )));
    }
    let mut welded = asset.surface().positions.clone();
    for (p, w) in positions.iter().zip(asset.file_to_welded()) {
        if let Some(slot) = w.and_then(|w| welded.get_mut(w)) {
            *slot = *p;
        }
    }
    Ok(welded)
}
