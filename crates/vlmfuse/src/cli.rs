//! The `vlmfuse` command line: one binary for the service (`serve`), the paper's evaluation
//! protocol (`eval`), the benchmarks (`bench`), bulk loading (`import`), the labeler (`label`)
//! one reporter on one clip (`describe`), labels from a vehicle-signal track (`annotate`) and
//! from an object detector (`detect`).

use crate::{annotate, bench, config, describe, detect, eval, import, label, serve};
use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "vlmfuse",
    version,
    about = "Shapley-credited, context-aware fusion of VLM reports"
)]
pub struct Cli {
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Run the HTTP service.
    Serve(Box<config::ServeArgs>),
    /// Replay a rounds file under the paper's protocol and print the metrics table.
    Eval(eval::EvalArgs),
    /// Measure the engine (fuse-then-feedback per round, batched against per-query kNN).
    Bench(bench::BenchArgs),
    /// Store a rounds file in a data directory as if it had come through /v1/fuse and
    /// /v1/feedback (the server must not be running on it).
    Import(Box<import::ImportArgs>),
    /// Label VLM answers with the configured labeler and show the evidence for each label.
    Label(label::LabelArgs),
    /// Run one configured reporter on one clip: its answer and labels, and with `--dump` the
    /// in-process model's inputs and first-token logits (to check a checkpoint).
    Describe(describe::DescribeArgs),
    /// Derive driving labels (brake, stop, turns, merge, ...) from a vehicle-signal track,
    /// with the evidence for each; `--simulate N` scores the rules on simulated clips.
    Annotate(annotate::AnnotateArgs),
    /// Detect objects in an image or a clip's frames with a YOLO ONNX export, track them and
    /// derive driving labels (traffic light, pedestrian in the path, stop sign) with evidence.
    Detect(detect::DetectArgs),
}

/// Parses the command line, runs the command, and prints an error with its causes.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Serve(args) => serve::run(*args),
        Cmd::Eval(args) => eval::run(args),
        Cmd::Bench(args) => bench::run(args),
        Cmd::Import(args) => import::run(*args),
        Cmd::Label(args) => label::run(args),
        Cmd::Describe(args) => describe::run(args),
        Cmd::Annotate(args) => annotate::run(args),
        Cmd::Detect(args) => detect::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    /// clap's own consistency checks (unique ids, valid defaults) over the whole command line.
    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
