//! The library's errors as Python exceptions: what the caller got wrong is a `ValueError`
//! with the library's own message; a flow that fails while running is a `FlowError`.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::PyErr;
use willow::flow::FlowError as LibFlowError;
use willow::mesh::MeshError;

pyo3::create_exception!(
    willow_fair,
    FlowError,
    PyRuntimeError,
    "A flow failed while running (a numerical failure): the parameters and the mesh were \
     accepted, but a step could not be computed."
);

/// A mesh refused by validation or a file refused by its reader. Arrays made in code are their
/// own "file": the inner error already names the caller's vertex and face indices, so the
/// location sentence (written for files) is left out for them.
pub fn mesh_error(e: MeshError, arrays: bool) -> PyErr {
    PyValueError::new_err(mesh_message(e, arrays))
}

/// [`mesh_error`]'s message.
pub fn mesh_message(e: MeshError, arrays: bool) -> String {
    match e {
        MeshError::InFile { error, .. } if arrays => error.to_string(),
        e => e.to_string(),
    }
}

/// Parameters the library refuses (`validate`, or what a flow checks against the mesh) are
/// the caller's to fix; anything else happened while computing.
pub fn flow_error(e: LibFlowError) -> PyErr {
    match e {
        LibFlowError::InvalidParameter { .. } | LibFlowError::Unsupported(_) => {
            PyValueError::new_err(e.to_string())
        }
        e => FlowError::new_err(e.to_string()),
    }
}
