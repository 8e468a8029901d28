//! numpy arrays in and out. The Python side has already checked dtypes and shapes and made
//! the arrays C-contiguous (its messages name the argument); these checks only keep a direct
//! caller of `_native` from reaching a panic.

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// `V`, a float64 (n, 3) array, as the library's positions (the one copy the library needs:
/// its mesh owns them).
pub fn positions(v: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f64; 3]>> {
    let view = v.as_array();
    if view.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must be a float64 array of shape (n, 3), got shape {:?}",
            view.shape()
        )));
    }
    Ok(view
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}

/// `F`, an int32 or int64 (m, 3) array of 0-based vertex indices, as the library's triangles.
/// A negative index is refused here (the library's `usize` cannot hold it); one past `V` is
/// refused by the library, which names the faces.
pub fn triangles(f: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<[usize; 3]>> {
    if let Ok(a) = f.extract::<PyReadonlyArray2<'_, i64>>() {
        return rows(&a, name);
    }
    if let Ok(a) = f.extract::<PyReadonlyArray2<'_, i32>>() {
        return rows(&a, name);
    }
    Err(PyValueError::new_err(format!(
        "{name} must be an int32 or int64 array of shape (m, 3)"
    )))
}

fn rows<T>(a: &PyReadonlyArray2<'_, T>, name: &str) -> PyResult<Vec<[usize; 3]>>
where
    T: numpy::Element + Copy + std::fmt::Display,
    usize: TryFrom<T>,
{
    let view = a.as_array();
    if view.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must be an int32 or int64 array of shape (m, 3), got shape {:?}",
            view.shape()
        )));
    }
    let index = |row: usize, x: T| {
        usize::try_from(x).map_err(|_| {
            PyValueError::new_err(format!(
                "{name} row {row} holds the negative index {x} (indices are 0-based)"
            ))
        })
    };
    view.rows()
        .into_iter()
        .enumerate()
        .map(|(i, r)| Ok([index(i, r[0])?, index(i, r[1])?, index(i, r[2])?]))
        .collect()
}

/// Positions as a new float64 (n, 3) array: the vector becomes the array's buffer, no copy.
pub fn positions_array(py: Python<'_>, p: Vec<[f64; 3]>) -> PyResult<Bound<'_, PyArray2<f64>>> {
    let n = p.len();
    let a = Array2::from_shape_vec((n, 3), p.into_flattened())
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}

/// Triangles as a new int64 (m, 3) array.
pub fn triangles_array<'py>(
    py: Python<'py>,
    t: &[[usize; 3]],
) -> PyResult<Bound<'py, PyArray2<i64>>> {
    let flat: Vec<i64> = t
        .iter()
        .flatten()
        .map(|&v| i64::try_from(v).unwrap_or(i64::MAX))
        .collect();
    let a = Array2::from_shape_vec((t.len(), 3), flat)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}
