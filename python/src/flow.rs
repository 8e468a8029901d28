//! `willow_fair._native.Flow`: one flow on one mesh, its factorizations kept between steps,
//! driven by the library's stopping rules (`flow::stopping::Run`, as `willow fair` is).
//!
//! The state sits behind a mutex that is only ever taken with the GIL released: a step runs
//! on its own while other Python threads go on, two threads stepping one flow take turns, and
//! no thread ever waits for the GIL while holding the flow.

use crate::arrays;
use crate::errors::{flow_error, mesh_error};
use crate::metrics::{metrics_dict, metrics_list};
use crate::params::flow_params;
use numpy::{PyArray2, PyReadonlyArray2};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::sync::{Mutex, MutexGuard};
use willow::flow::region::Region;
use willow::flow::stopping::{Event, Outcome, Run};
use willow::flow::{new_flow, Boundary, BoundaryAngles, FlowParams};
use willow::mesh::io::{Asset, Limits};
use willow::metrics::StepMetrics;

/// A flow and what maps its surface back to the caller's arrays.
struct State {
    run: Run,
    /// The caller's arrays, welded as a file's vertices are (`Asset::from_indexed`).
    asset: Asset,
    /// Why the run ended, once it has.
    stop: Option<(Outcome, String)>,
}

impl State {
    fn build(
        positions: Vec<[f64; 3]>,
        triangles: Vec<[usize; 3]>,
        mut params: FlowParams,
        steps: usize,
    ) -> PyResult<State> {
        let asset = Asset::from_indexed(positions, triangles, &Limits::default())
            .map_err(|e| mesh_error(e, true))?;
        surface_numbering(&mut params, &asset)?;
        params.validate().map_err(flow_error)?;
        let flow = new_flow(asset.surface(), &params).map_err(flow_error)?;
        let run = Run::new(flow, &params, steps).map_err(flow_error)?;
        Ok(State {
            run,
            asset,
            stop: None,
        })
    }

    /// The next step's metrics, or `None` once the run is over.
    fn advance(&mut self) -> PyResult<Option<StepMetrics>> {
        if self.stop.is_some() {
            return Ok(None);
        }
        match self.run.advance().map_err(flow_error)? {
            Event::Step(m) => Ok(Some(m)),
            Event::Stopped { outcome, reason } => {
                self.stop = Some((outcome, reason));
                Ok(None)
            }
        }
    }

    /// The surface in the caller's numbering: the one copy of the positions a caller gets.
    fn vertices(&self) -> Vec<[f64; 3]> {
        self.asset.file_world_positions(self.run.flow().positions())
    }
}

/// Vertex indices in the parameters (vertex regions, per-vertex boundary angles) are the
/// caller's; the flow numbers the welded surface.
fn surface_numbering(params: &mut FlowParams, asset: &Asset) -> PyResult<()> {
    let count = asset.file_vertex_count();
    let refused = |what: &str, v: usize| {
        PyValueError::new_err(format!(
            "{what}: vertex {v} is not a vertex of any face (V has {count} rows)"
        ))
    };
    for region in &mut params.regions {
        match region {
            Region::Vertices(list) => {
                *list = asset
                    .surface_vertices(list)
                    .map_err(|v| refused("regions", v))?;
            }
            Region::Group(name) => {
                return Err(PyValueError::new_err(format!(
                    "regions: group {name:?}: arrays have no named groups; pass the group's \
                     vertex indices as a vertex region"
                )));
            }
            Region::Sphere { .. } | Region::Box { .. } => {}
        }
    }
    if let Boundary::Prescribed(p) = &mut params.boundary {
        if let BoundaryAngles::PerVertex(list) = &mut p.angles {
            let file: Vec<usize> = list.iter().map(|&(v, _)| v).collect();
            let surface = asset
                .surface_vertices(&file)
                .map_err(|v| refused("boundary_rotation", v))?;
            for ((v, _), s) in list.iter_mut().zip(surface) {
                *v = s;
            }
        }
    }
    Ok(())
}

/// The native half of `willow_fair.Flow` (see python/willow_fair/__init__.py for the API).
#[pyclass(module = "willow_fair._native", name = "Flow", frozen)]
pub struct NativeFlow {
    state: Mutex<State>,
}

impl NativeFlow {
    /// The state, or why it cannot be had: a panic in an earlier call left it half-stepped.
    fn lock(&self) -> PyResult<MutexGuard<'_, State>> {
        self.state.lock().map_err(|_| {
            PyRuntimeError::new_err(
                "this Flow failed with an internal error in an earlier call and cannot go on",
            )
        })
    }
}

#[pymethods]
impl NativeFlow {
    /// `vertices` float64 (n, 3), `faces` int32/int64 (m, 3), `params` the JSON object of
    /// `FlowParams` fields, `steps` at most this many steps (`None`: no limit).
    #[new]
    #[pyo3(signature = (vertices, faces, params, steps=None))]
    fn new(
        py: Python<'_>,
        vertices: PyReadonlyArray2<'_, f64>,
        faces: &Bound<'_, PyAny>,
        params: &str,
        steps: Option<usize>,
    ) -> PyResult<Self> {
        let positions = arrays::positions(&vertices, "V")?;
        let triangles = arrays::triangles(faces, "F")?;
        let params = flow_params(params)?;
        // Welding, validation and the first factorizations can take seconds on a large mesh.
        let state = py.detach(move || {
            State::build(positions, triangles, params, steps.unwrap_or(usize::MAX))
        })?;
        Ok(NativeFlow {
            state: Mutex::new(state),
        })
    }

    /// One step: its metrics dict, or `None` once the run is over (then `outcome` says why).
    fn step<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let step = py.detach(|| self.lock()?.advance())?;
        step.map(|m| metrics_dict(py, &m)).transpose()
    }

    /// Every remaining step, with the GIL released throughout: the list of their metrics.
    fn run<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let steps = py.detach(|| {
            let mut state = self.lock()?;
            let mut steps = Vec::new();
            while let Some(m) = state.advance()? {
                steps.push(m);
            }
            Ok::<_, PyErr>(steps)
        })?;
        metrics_list(py, &steps)
    }

    /// The current surface in the caller's numbering, a new float64 (n, 3) array.
    #[getter]
    fn vertices<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let v = py.detach(|| Ok::<_, PyErr>(self.lock()?.vertices()))?;
        arrays::positions_array(py, v)
    }

    /// Why the run ended (`completed`, `converged`, ...: the CLI's names), `None` before.
    #[getter]
    fn outcome(&self, py: Python<'_>) -> PyResult<Option<&'static str>> {
        py.detach(|| Ok(self.lock()?.stop.as_ref().map(|(o, _)| o.name())))
    }

    /// The sentence that says why, `None` before the run has ended.
    #[getter]
    fn reason(&self, py: Python<'_>) -> PyResult<Option<String>> {
        py.detach(|| Ok(self.lock()?.stop.as_ref().map(|(_, r)| r.clone())))
    }

    /// The metrics of the input surface (step 0).
    #[getter]
    fn initial_metrics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m = py.detach(|| Ok::<_, PyErr>(self.lock()?.run.flow().initial_metrics()))?;
        metrics_dict(py, &m)
    }

    /// The metrics of the surface the flow is on (step 0 before any step).
    #[getter]
    fn last_metrics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m = py.detach(|| Ok::<_, PyErr>(*self.lock()?.run.last_metrics()))?;
        metrics_dict(py, &m)
    }
}
