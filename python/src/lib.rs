//! `willow_fair._native`: the extension module of the Python package `willow-fair`, on the
//! `willow` library alone. The Python side (`python/willow_fair/`) checks arrays and turns
//! keywords into the library's JSON form; this side builds the flow, runs it with the GIL
//! released, and hands back numpy arrays and the CLI's metric dicts.

mod arrays;
mod errors;
mod flow;
mod holes;
mod io;
mod metrics;
mod params;

use pyo3::prelude::*;

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<flow::NativeFlow>()?;
    m.add_function(wrap_pyfunction!(holes::fill_holes, m)?)?;
    m.add_function(wrap_pyfunction!(io::read, m)?)?;
    m.add_function(wrap_pyfunction!(io::write, m)?)?;
    m.add_function(wrap_pyfunction!(params::flow_params_defaults, m)?)?;
    m.add_function(wrap_pyfunction!(params::nested_fields, m)?)?;
    m.add_function(wrap_pyfunction!(params::check_params, m)?)?;
    m.add("FlowError", m.py().get_type::<errors::FlowError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
