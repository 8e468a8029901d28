//! `fill_holes`: the library's hole filling (`willow::flow::holes::fill_asset_holes`, what
//! `willow fair --fill-holes` and a job's `fill_holes` run) on arrays: Liepa triangulation,
//! refinement, a thin-plate start and the conformal flow with the surface's frames held along
//! each loop, the patch vertices and faces appended after the caller's.

use crate::arrays;
use crate::errors::mesh_error;
use numpy::{PyArray2, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use willow::flow::holes::fill_asset_holes;
use willow::flow::FlowParams;
use willow::mesh::holes::HoleSize;
use willow::mesh::io::{Asset, Limits};

/// `(V, F, filled, left_open)`: the closed mesh, the holes closed, and the vertex counts of
/// the loops the size left open.
type Filled<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<i64>>,
    usize,
    Vec<usize>,
);

/// `size` as `HoleSize::parse` reads it: `"all"`, an integer (boundary vertices) or a
/// decimal (model units); the Python side writes it from `None`, an int or a float.
#[pyfunction]
#[pyo3(signature = (vertices, faces, size="all"))]
pub fn fill_holes<'py>(
    py: Python<'py>,
    vertices: PyReadonlyArray2<'_, f64>,
    faces: &Bound<'_, PyAny>,
    size: &str,
) -> PyResult<Filled<'py>> {
    let size = HoleSize::parse(size).map_err(|e| PyValueError::new_err(format!("max: {e}")))?;
    let positions = arrays::positions(&vertices, "V")?;
    let triangles = arrays::triangles(faces, "F")?;
    let (v, f, filled, left_open) = py
        .detach(|| {
            let limits = Limits::default();
            let asset = Asset::from_indexed(positions, triangles, &limits)?;
            let holes = fill_asset_holes(&asset, size, &FlowParams::default(), &limits)?;
            let closed = &holes.asset;
            Ok((
                closed.file_world_positions(&closed.surface().positions),
                closed.file_triangles(),
                holes.filled,
                holes.left_open,
            ))
        })
        .map_err(|e| mesh_error(e, true))?;
    Ok((
        arrays::positions_array(py, v)?,
        arrays::triangles_array(py, &f)?,
        filled,
        left_open,
    ))
}
