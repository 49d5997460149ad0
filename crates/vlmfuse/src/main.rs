//! `vlmfuse`: one binary for the service (`serve`), the paper's evaluation protocol (`eval`) and
//! the benchmarks (`bench`).

mod bench;
mod config;
mod eval;
mod plots;
mod server;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "vlmfuse",
    version,
    about = "Shapley-credited, context-aware fusion of VLM reports"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the HTTP service.
    Serve(Box<server::ServeArgs>),
    /// Replay a rounds file under the paper's protocol and print the metrics table.
    Eval(eval::EvalArgs),
    /// Measure the engine (fuse-then-feedback per round, batched against per-query kNN).
    Bench(bench::BenchArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Serve(args) => server::main(*args),
        Cmd::Eval(args) => eval::run(args),
        Cmd::Bench(args) => bench::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
