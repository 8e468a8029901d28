//! The `willow` command: parse flags, set up, hand off. No numerics and no routes here.

mod cli;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "willow",
    version,
    about = "Mesh fairing by conformal Willmore flow"
)]
struct Args {
    #[command(subcommand)]
    command: Command,
}

// Parsed once per process: the size of the `serve` flags (auth included) does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Fair a mesh file and write the result (format by extension: .obj, .gltf, .glb).
    Fair(cli::fair::FairArgs),
    /// Measure per-step time and peak memory of the conformal flow against implicit MCF.
    Bench(cli::bench::BenchArgs),
    /// Flow a planar polyline to a round curve, keeping its edge lengths (format: .json, .obj).
    Curve(cli::curve::CurveArgs),
    /// Run the fairing service: HTTP/1.1, h2c and gRPC on one port (jobs kept in --data-dir).
    Serve(willow_service::api::server::ServeArgs),
    /// Manage API keys for `serve --auth keys` (`keys new --tenant T --name N`).
    Keys(cli::keys::KeysArgs),
}

fn main() -> ExitCode {
    let args = Args::parse();
    match args.command {
        Command::Fair(a) => cli::fair::run(a),
        Command::Bench(a) => cli::bench::run(a),
        Command::Curve(a) => cli::curve::run(a),
        Command::Keys(a) => cli::keys::run(a),
        Command::Serve(a) => match willow_service::api::server::run(a) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            }
        },
    }
}
