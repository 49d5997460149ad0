//! `vlmfuse serve`: configuration → service → router → socket, and a graceful shutdown.

use crate::config::{Config, ServeArgs};
use crate::http::{app, AppState};
use crate::service::Service;
use crate::telemetry::Metrics;
use anyhow::Context;
use std::sync::Arc;
use std::thread::JoinHandle;

/// A started service: the router's state and the writer thread to join after the last request.
pub struct Started {
    pub state: AppState,
    pub writer: JoinHandle<()>,
}

/// Opens the store, rebuilds the engine, loads the pipeline and starts the writer, with a
/// metrics recorder of its own (see [`crate::telemetry`]). Tests serve the result in-process
/// through [`app`]; [`run`] puts it on a socket.
pub async fn build(cfg: Config) -> anyhow::Result<Started> {
    let metrics = Metrics::new()?;
    build_with(cfg, metrics).await
}

async fn build_with(cfg: Config, metrics: Metrics) -> anyhow::Result<Started> {
    let (service, writer) = Service::start(Arc::new(cfg), metrics).await?;
    Ok(Started {
        state: AppState::new(Arc::new(service)),
        writer,
    })
}

/// Hands freed heap back to the OS once a second (glibc's `malloc_trim`). Decoded frames and
/// model activations are tens of MB per request, freed at its end; glibc keeps them in its
/// per-thread arenas, so after a burst the RSS stayed at the peak's level although nothing was
/// live (measured in the soak test: 157 MB one second after the load, 48 MB idle before it).
async fn return_freed_memory() {
    let mut tick = tokio::time::interval(std::time::Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tick.tick().await;
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim only returns free pages to the kernel; it takes the arena locks
        // itself and is safe to call from any thread at any time.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
    tracing::info!("shutting down: finishing requests in flight");
}

/// Serves until SIGTERM or Ctrl-C, then finishes the requests in flight and lets the writer
/// commit everything queued.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let cfg = Config::load(&args)?;
    let addr = cfg.listen_addr()?;
    let limits = cfg.conn_limits();
    let metrics = Metrics::new()?;
    // In the binary, a metric emitted outside a request's scope is kept too.
    metrics.install_global()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("tokio runtime")?;
    let Started { state, writer } = rt.block_on(build_with(cfg, metrics))?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("cannot listen on {addr}"))?;
        let local = listener.local_addr()?;
        state.service.set_address(local);
        // Tests and scripts read this line to learn the port when listening on port 0.
        println!("vlmfuse listening on http://{local}");
        tracing::info!("listening on http://{local}");
        let _trim = tokio::spawn(return_freed_memory());
        crate::conn::serve(listener, app(state), limits, shutdown_signal())
            .await
            .context("serving")
    })?;
    drop(rt);
    // Every sender is gone with the router: the writer drains its queue, commits and returns.
    writer
        .join()
        .map_err(|_| anyhow::anyhow!("the writer thread panicked"))?;
    Ok(())
}
