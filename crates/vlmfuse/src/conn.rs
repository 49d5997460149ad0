//! The socket edge of `vlmfuse serve`: an accept loop with a connection cap, and per-connection
//! deadlines against slowloris clients. `axum::serve` has neither: a client could hold a
//! connection forever by sending half a header line, or by idling, and open as many as the
//! process has file descriptors.
//!
//! Each connection is in one of three states, seen from its socket:
//! - a request in flight (the router has it): no deadline here; the request timeouts apply;
//! - between requests with part of a request head received: the whole head must arrive within
//!   `header_read_timeout` of its first byte (hyper's own header timer also runs while a
//!   keep-alive connection idles, so it cannot tell a slow head from an idle client);
//! - idle (nothing received since the last answer, or since accept): closed after
//!   `idle_timeout`.
//!
//! Writes have a deadline too: an answer that makes no progress for `idle_timeout` (a client
//! that pipelines requests and never reads the answers fills the socket's send buffer) ends
//! the connection, so such clients cannot hold every connection slot. Shutdown waits at most
//! `shutdown_timeout` for the connections to finish.
//!
//! The cap is a semaphore taken before `accept`: past it, new connections wait in the kernel's
//! backlog, unserved, until one closes.

use axum::Router;
use hyper_util::rt::TokioIo;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio::time::{Instant, Sleep};
use tower::ServiceExt;

/// The per-connection limits, from `[server]`.
#[derive(Debug, Clone, Copy)]
pub struct ConnLimits {
    pub header_read_timeout: Duration,
    pub idle_timeout: Duration,
    pub max_connections: usize,
    /// How long a shutdown waits for open connections before it returns anyway.
    pub shutdown_timeout: Duration,
}

/// What the router side tells the socket side of one connection.
struct Shared {
    /// Requests the router is working on.
    in_flight: usize,
    /// Requests dispatched so far: a head that was dispatched no longer owes its deadline.
    dispatched: u64,
    /// When the connection last became idle (accept, or the end of its last request).
    idle_since: Instant,
    /// The reader of the connection, woken when a request ends: hyper does not poll the
    /// socket again after it wrote an answer, so the idle deadline would otherwise not be set
    /// until the client sent something.
    reader: Option<std::task::Waker>,
}

#[derive(Clone)]
struct ConnState(Arc<Mutex<Shared>>);

impl ConnState {
    fn new() -> Self {
        Self(Arc::new(Mutex::new(Shared {
            in_flight: 0,
            dispatched: 0,
            idle_since: Instant::now(),
            reader: None,
        })))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Shared> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A request reached the router; the guard marks its end (also when it is dropped
    /// unfinished: the client went away).
    fn begin(&self) -> RequestGuard {
        let mut s = self.lock();
        s.in_flight += 1;
        s.dispatched += 1;
        RequestGuard(self.clone())
    }
}

struct RequestGuard(ConnState);

impl Drop for RequestGuard {
    fn drop(&mut self) {
        let reader = {
            let mut s = self.0.lock();
            s.in_flight -= 1;
            s.idle_since = Instant::now();
            if s.in_flight == 0 {
                s.reader.take()
            } else {
                None
            }
        };
        if let Some(w) = reader {
            w.wake();
        }
    }
}

/// The socket with the deadlines of the module doc applied to its reads.
struct Guarded {
    io: TcpStream,
    state: ConnState,
    limits: ConnLimits,
    /// When the first byte of a not yet dispatched request head arrived, and how many
    /// requests had been dispatched then.
    head: Option<(Instant, u64)>,
    timer: Pin<Box<Sleep>>,
    /// Since when writes have made no progress (`None` while they do).
    stalled_since: Option<Instant>,
    write_timer: Pin<Box<Sleep>>,
}

impl Guarded {
    fn new(io: TcpStream, state: ConnState, limits: ConnLimits) -> Self {
        Self {
            io,
            state,
            limits,
            head: None,
            timer: Box::pin(tokio::time::sleep(Duration::ZERO)),
            stalled_since: None,
            write_timer: Box::pin(tokio::time::sleep(Duration::ZERO)),
        }
    }

    /// A write that returned `Pending`: pending still, or an error once writes have made no
    /// progress for `idle_timeout` (the client stopped reading).
    fn write_stalled<T>(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<T>> {
        let since = *self.stalled_since.get_or_insert_with(Instant::now);
        let deadline = since + self.limits.idle_timeout;
        let stalled = || {
            Poll::Ready(Err(io::Error::new(
                io::ErrorKind::TimedOut,
                "the client read nothing of the answer within server.idle_timeout_s",
            )))
        };
        if Instant::now() >= deadline {
            return stalled();
        }
        if self.write_timer.deadline() != deadline {
            self.write_timer.as_mut().reset(deadline);
        }
        match self.write_timer.as_mut().poll(cx) {
            Poll::Ready(()) => stalled(),
            Poll::Pending => Poll::Pending,
        }
    }

    fn wrote<T>(&mut self, r: Poll<io::Result<T>>, cx: &mut Context<'_>) -> Poll<io::Result<T>> {
        match r {
            Poll::Pending => self.write_stalled(cx),
            done => {
                self.stalled_since = None;
                done
            }
        }
    }

    /// The deadline in force, and what it is for; none while a request is in flight.
    fn deadline(&mut self, cx: &Context<'_>) -> Option<(Instant, &'static str)> {
        let mut s = self.state.lock();
        s.reader = Some(cx.waker().clone());
        if let Some((_, at)) = self.head {
            if s.dispatched > at {
                self.head = None;
            }
        }
        if s.in_flight > 0 {
            return None;
        }
        Some(match self.head {
            Some((since, _)) => (
                since + self.limits.header_read_timeout,
                "request head not received within server.header_read_timeout_s",
            ),
            None => (
                s.idle_since + self.limits.idle_timeout,
                "connection idle for server.idle_timeout_s",
            ),
        })
    }
}

impl AsyncRead for Guarded {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                if buf.filled().len() > before && self.head.is_none() {
                    let s = self.state.lock();
                    let (idle, dispatched) = (s.in_flight == 0, s.dispatched);
                    drop(s);
                    if idle {
                        self.head = Some((Instant::now(), dispatched));
                    }
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => {
                let Some((deadline, why)) = self.deadline(cx) else {
                    return Poll::Pending;
                };
                if Instant::now() >= deadline {
                    return Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, why)));
                }
                self.timer.as_mut().reset(deadline);
                match self.timer.as_mut().poll(cx) {
                    Poll::Ready(()) => {
                        Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, why)))
                    }
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write(cx, buf);
        self.wrote(r, cx)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let r = Pin::new(&mut self.io).poll_flush(cx);
        self.wrote(r, cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.wrote(r, cx)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }
}

/// Serves `app` on `listener` until `shutdown` completes, then stops accepting, lets every
/// open connection finish its request in flight (idle ones close at once) and returns, after
/// `limits.shutdown_timeout` at the latest (the connections left are dropped with the runtime).
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    shutdown: impl Future<Output = ()>,
) -> io::Result<()> {
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            p = permits.clone().acquire_owned() => p.expect("the semaphore is never closed"),
            _ = &mut shutdown => break,
        };
        let (stream, _peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(s) => s,
                Err(e) => {
                    // Out of descriptors (EMFILE) and the like: wait, do not spin.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let app = app.clone();
        let mut stop = stop_rx.clone();
        tokio::spawn(async move {
            let state = ConnState::new();
            let io = TokioIo::new(Guarded::new(stream, state.clone(), limits));
            let svc =
                hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
                    let guard = state.begin();
                    let app = app.clone();
                    async move {
                        let resp = app.oneshot(req.map(axum::body::Body::new)).await;
                        drop(guard);
                        resp
                    }
                });
            // HTTP/1.1, as axum::serve served it here (axum's http2 feature is off).
            let conn = hyper::server::conn::http1::Builder::new()
                .serve_connection(io, svc)
                .with_upgrades();
            tokio::pin!(conn);
            tokio::select! {
                res = conn.as_mut() => {
                    if let Err(e) = res {
                        tracing::debug!("connection closed: {e}");
                    }
                }
                _ = async { let _ = stop.wait_for(|s| *s).await; } => {
                    conn.as_mut().graceful_shutdown();
                    let _ = conn.as_mut().await;
                }
            }
            drop(permit);
        });
    }
    drop(listener);
    let _ = stop_tx.send(true);
    // Every connection holds a permit until it ends.
    let all = u32::try_from(limits.max_connections).unwrap_or(u32::MAX);
    if tokio::time::timeout(limits.shutdown_timeout, permits.acquire_many(all))
        .await
        .is_err()
    {
        let open = limits.max_connections - permits.available_permits();
        tracing::warn!(
            open,
            "shutdown: connections still open after server.shutdown_timeout_s; leaving them"
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    fn limits(max_connections: usize) -> ConnLimits {
        ConnLimits {
            header_read_timeout: Duration::from_secs(5),
            idle_timeout: Duration::from_millis(500),
            max_connections,
            shutdown_timeout: Duration::from_millis(700),
        }
    }

    /// 4 MiB per answer: a client that never reads fills the socket buffers at once.
    fn app() -> Router {
        Router::new().route("/big", axum::routing::get(|| async { vec![b'z'; 4 << 20] }))
    }

    /// Connects and pipelines requests it never reads the answers of.
    async fn stalled_client(addr: std::net::SocketAddr) -> TcpStream {
        let mut c = TcpStream::connect(addr).await.unwrap();
        let reqs = "GET /big HTTP/1.1\r\nhost: x\r\n\r\n".repeat(50);
        c.write_all(reqs.as_bytes()).await.unwrap();
        c
    }

    async fn get_big(addr: std::net::SocketAddr) -> usize {
        let mut c = TcpStream::connect(addr).await.unwrap();
        c.write_all(b"GET /big HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
            .await
            .unwrap();
        let mut buf = Vec::new();
        c.read_to_end(&mut buf).await.unwrap();
        buf.len()
    }

    /// With one connection slot, a client that pipelines and never reads holds it only until
    /// its writes have stalled for `idle_timeout`; then the next client is served.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_client_that_never_reads_loses_its_slot() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(listener, app(), limits(1), async {
            let _ = rx.await;
        }));
        let _stalled = stalled_client(addr).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
        let t = std::time::Instant::now();
        let got = tokio::time::timeout(Duration::from_secs(5), get_big(addr))
            .await
            .expect("the second client was never served");
        assert!(got > 4 << 20, "{got} bytes");
        assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
        tx.send(()).unwrap();
        server.await.unwrap().unwrap();
    }

    /// Shutdown returns within its deadline even while a connection is stuck mid-answer.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn shutdown_has_a_deadline() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let mut l = limits(4);
        // Longer than the test waits: only the shutdown deadline can end it in time.
        l.idle_timeout = Duration::from_secs(60);
        let server = tokio::spawn(serve(listener, app(), l, async {
            let _ = rx.await;
        }));
        let _stalled = stalled_client(addr).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
        let t = std::time::Instant::now();
        tx.send(()).unwrap();
        tokio::time::timeout(Duration::from_secs(5), server)
            .await
            .expect("shutdown waited past its deadline")
            .unwrap()
            .unwrap();
        assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    }
}
