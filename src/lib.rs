//! The Willow service: fairing jobs over the [`willow`] numeric library.
//!
//! Data flows one way, from the edges into the numeric core:
//!
//! - [`api`]: the transports (HTTP with its web page, gRPC), authentication and the error
//!   mapping at the edge;
//! - [`jobs`]: the job core (admission, worker, watch) over its ports, with the embedded
//!   (SQLite, files) and NATS backends; it knows no transport;
//! - the numeric library [`willow`] (mesh, geometry, linalg, flow, curve, metrics), which knows
//!   neither.

pub mod api;
pub mod jobs;
