//! `willow keys new`: make an API key for `willow serve --auth keys`.

use clap::{Args, Subcommand};
use std::process::ExitCode;

#[derive(Args)]
pub struct KeysArgs {
    #[command(subcommand)]
    pub command: KeysCommand,
}

#[derive(Subcommand)]
pub enum KeysCommand {
    /// Print a new random API key (once: only its hash is kept) and the line to add to the key
    /// file (--api-keys-file) or WILLOW_API_KEYS.
    New {
        /// The tenant the key acts for (1-64 of A-Z a-z 0-9 . _ -).
        #[arg(long)]
        tenant: String,
        /// A name for the key, shown in logs (1-64 characters, no spaces), e.g. `ci` or `alice`.
        #[arg(long)]
        name: String,
    },
}

pub fn run(args: KeysArgs) -> ExitCode {
    match args.command {
        KeysCommand::New { tenant, name } => {
            match willow_service::api::auth::new_key(&tenant, &name) {
                Ok((key, line)) => {
                    // stdout: the key, then the line (scripts take them apart); stderr: how.
                    eprintln!("API key (shown only now; give it to the client as `Authorization: Bearer <key>`):");
                    println!("{key}");
                    eprintln!(
                        "Add this line to the key file (--api-keys-file) or WILLOW_API_KEYS:"
                    );
                    println!("{line}");
                    ExitCode::SUCCESS
                }
                Err(e) => super::fail(super::EXIT_BAD_INPUT, e),
            }
        }
    }
}
