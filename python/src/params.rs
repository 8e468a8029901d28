//! Keywords to `FlowParams`. The Python side gathers the keywords into the library's own JSON
//! form (`FlowParams` is a serde type with defaults for every field), so every field is a
//! keyword with the library's names and parsing (methods in any case, `Preserve::parse`, ...),
//! and a field a later issue adds needs no edit here.

use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use serde_json::{Map, Value};
use willow::denoise::DenoiseParams;
use willow::flow::filter::SpectralFilter;
use willow::flow::FlowParams;

/// `FlowParams::default()` as JSON: every keyword's name and library default (the Python side
/// puts the CLI's `method` and `threads` over it).
#[pyfunction]
pub fn flow_params_defaults() -> PyResult<String> {
    serde_json::to_string(&FlowParams::default()).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// The fields of the nested parameters the keywords flatten as the CLI does
/// (`denoise_sigma_r`, `filter_k`): `{"denoise": [...], "filter": [...]}`.
#[pyfunction]
pub fn nested_fields() -> PyResult<String> {
    let names = |v: Value| -> Vec<String> {
        match v {
            Value::Object(m) => m.keys().cloned().collect(),
            _ => Vec::new(),
        }
    };
    let to_value =
        |r: Result<Value, serde_json::Error>| r.map_err(|e| PyValueError::new_err(e.to_string()));
    let denoise = names(to_value(serde_json::to_value(DenoiseParams::default()))?);
    let filter = names(to_value(serde_json::to_value(SpectralFilter {
        sigma: 1.0,
        k: 0,
    }))?);
    to_value(serde_json::to_value(
        [("denoise", denoise), ("filter", filter)]
            .into_iter()
            .collect::<std::collections::BTreeMap<_, _>>(),
    ))
    .map(|v| v.to_string())
}

/// Parse (not validate) a JSON object of parameters, as `flow_params` does: the Python side
/// calls it with one keyword at a time, so a type error names its keyword.
#[pyfunction]
pub fn check_params(json: &str) -> PyResult<()> {
    flow_params(json).map(|_| ())
}

/// The parameters of a JSON object of `FlowParams` fields; a name that is not a field is a
/// `TypeError` (as Python's own for an unknown keyword), a value of the wrong type too, any
/// other refusal a `ValueError`. `threads` 0 is every core, as in the CLI. Not validated here:
/// the flow validates when it is built (`FlowParams::validate`'s message).
pub fn flow_params(json: &str) -> PyResult<FlowParams> {
    let map: Map<String, Value> = serde_json::from_str(json)
        .map_err(|e| PyValueError::new_err(format!("parameters: {e}")))?;
    let known = serde_json::to_value(FlowParams::default())
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let unknown: Vec<&str> = map
        .keys()
        .filter(|k| known.get(k.as_str()).is_none())
        .map(String::as_str)
        .collect();
    if !unknown.is_empty() {
        return Err(PyTypeError::new_err(format!(
            "unknown parameters: {}",
            unknown.join(", ")
        )));
    }
    let mut map = map;
    resolve_auto_boundary(&mut map);
    let mut params: FlowParams = serde_json::from_value(Value::Object(map)).map_err(|e| {
        let message = e.to_string();
        if message.starts_with("invalid type") {
            PyTypeError::new_err(message)
        } else {
            PyValueError::new_err(message)
        }
    })?;
    if params.threads == 0 {
        params.threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    }
    Ok(params)
}

/// `boundary: "auto"`, the CLI's default (`willow_service::jobs::spec::BoundarySpec::Auto`,
/// which the library does not have): `fixed` under the conformal flow without regions, where
/// a free border of an open scan crumples (issue 39); `free` otherwise, where the flow keeps
/// the border itself. Closed surfaces ignore either.
fn resolve_auto_boundary(map: &mut Map<String, Value>) {
    let auto = map
        .get("boundary")
        .and_then(Value::as_str)
        .is_some_and(|b| b.eq_ignore_ascii_case("auto"));
    if !auto {
        return;
    }
    let conformal = map
        .get("method")
        .and_then(Value::as_str)
        .is_some_and(|m| m.eq_ignore_ascii_case("conformal"));
    let regions = map
        .get("regions")
        .and_then(Value::as_array)
        .is_some_and(|r| !r.is_empty());
    let resolved = if conformal && !regions {
        "fixed"
    } else {
        "free"
    };
    map.insert("boundary".into(), Value::String(resolved.into()));
}
