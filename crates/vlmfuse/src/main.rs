//! The `vlmfuse` binary; everything lives in the library (`vlmfuse::cli`).

fn main() -> std::process::ExitCode {
    vlmfuse::cli::main()
}
