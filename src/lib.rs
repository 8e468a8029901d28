//! The Willow service: fairing jobs over the [`willow`] numeric library.
//!
//! Data flows one way, from the edges into the numeric core:
//!
//! - [`api`]: the transports (HTTP with its web page, gRPC), authentication and the error
//!   mapping at the edge;
//! - [`jobs`]: the job core (admission, worker, watch) over its ports, with the embedded
//!   (SQLite, files) and NATS backends; it knows no transport (its job spec derives the
//!   OpenAPI schema the API serves: see [`jobs`]);
//! - the numeric library [`willow`] (mesh, linalg, geometry, metrics, denoise, flow, curve),
//!   which knows neither.
//!
//! The `willow` binary (`src/main.rs`, its subcommands in `src/cli/`) sits beside `api`: `fair`,
//! `curve` and `bench` run the library's flows in the process, `fair` checking its flags as a
//! job's [`jobs::JobSpec`] (so the CLI and the service refuse the same parameters); `keys`
//! mints API keys with [`api::auth`]; `serve` hands off to [`api::server`].

pub mod api;
pub mod jobs;
