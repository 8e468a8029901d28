//! Subcommands of the `willow` binary, one per file: parse, then apply.

pub mod bench;
pub mod bench_creases;
pub mod bench_denoise;
pub mod bench_genus;
pub mod bench_holes;
pub mod curve;
pub mod fair;
pub mod keys;

use std::process::ExitCode;

/// Exit code for input the program refuses (unreadable, malformed, unsupported).
pub const EXIT_BAD_INPUT: u8 = 2;
/// Exit code for a failure while running (numerical failure, unwritable output).
pub const EXIT_FAILURE: u8 = 1;
/// Exit code for a flow the safeguard stopped early (`FlowError::NoProgress`): the output file
/// holds the last accepted surface, so it is usable, but it is not the requested number of
/// steps. Distinct from 0 so scripts notice, and from 1 so they can keep the file.
pub const EXIT_NO_PROGRESS: u8 = 3;

pub fn fail(code: u8, message: impl std::fmt::Display) -> ExitCode {
    eprintln!("error: {message}");
    ExitCode::from(code)
}

/// Read an input file, or report why not (exit code 2: the input is refused).
pub fn read_input(path: &std::path::Path) -> Result<Vec<u8>, ExitCode> {
    std::fs::read(path).map_err(|e| {
        fail(
            EXIT_BAD_INPUT,
            format!("cannot read {}: {e}", path.display()),
        )
    })
}
