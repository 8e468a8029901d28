//! Steps' metrics as dicts with exactly the keys of `willow fair --json`, in its order: both
//! are serde_json's text of `StepMetrics` (an optional metric the flow did not measure is
//! absent from both, a non-finite number is JSON's `null`, here `None`), read by Python's own
//! `json.loads`, which keeps the order (serde_json's `Value` would sort the keys).

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde::Serialize;
use willow::metrics::StepMetrics;

fn from_json<'py, T: Serialize + ?Sized>(
    py: Python<'py>,
    value: &T,
) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(|e| PyValueError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// One step's metrics dict.
pub fn metrics_dict<'py>(py: Python<'py>, m: &StepMetrics) -> PyResult<Bound<'py, PyAny>> {
    from_json(py, m)
}

/// A list of the steps' metrics dicts.
pub fn metrics_list<'py>(py: Python<'py>, m: &[StepMetrics]) -> PyResult<Bound<'py, PyAny>> {
    from_json(py, m)
}
