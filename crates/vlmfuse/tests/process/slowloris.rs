//! Slowloris: a client that sends half a header line is dropped after the header-read timeout,
//! an idle keep-alive connection after the idle timeout, and with the connection cap held by N
//! idle connections the N+1-th is not served until one of them goes.

use crate::support::Server;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// Reads until the server closes the connection (Ok(elapsed)) or `within` passes (Err).
fn closed_within(s: &mut TcpStream, within: Duration) -> Result<Duration, String> {
    let t = Instant::now();
    s.set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    let mut buf = [0u8; 4096];
    let mut got = Vec::new();
    while t.elapsed() < within {
        match s.read(&mut buf) {
            Ok(0) => return Ok(t.elapsed()),
            Ok(n) => got.extend_from_slice(&buf[..n]),
            Err(e)
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(_) => return Ok(t.elapsed()),
        }
    }
    Err(format!(
        "still open after {within:?}; read {:?}",
        String::from_utf8_lossy(&got)
    ))
}

/// Sends a whole request and reads the status line, or None within `within`.
fn status_within(s: &mut TcpStream, within: Duration) -> Option<String> {
    s.set_read_timeout(Some(within)).unwrap();
    let mut buf = [0u8; 1024];
    match s.read(&mut buf) {
        Ok(n) if n > 0 => Some(
            String::from_utf8_lossy(&buf[..n])
                .lines()
                .next()
                .unwrap_or("")
                .to_string(),
        ),
        _ => None,
    }
}

const GET: &[u8] = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n";

#[test]
fn slow_headers_and_idle_connections_are_dropped_and_connections_are_capped() {
    let tmp = tempfile::tempdir().unwrap();
    let srv = Server::start(
        &tmp.path().join("d"),
        &[
            "--header-read-timeout-s",
            "0.5",
            "--idle-timeout-s",
            "1.5",
            "--max-connections",
            "3",
        ],
        &[],
    );
    // Half a header line, then nothing: dropped after the header timeout, not the idle one.
    let mut slow = TcpStream::connect(&srv.addr).unwrap();
    slow.write_all(b"GET /healthz HTTP/1.1\r\nHos").unwrap();
    let took = closed_within(&mut slow, Duration::from_secs(5)).unwrap();
    assert!(
        took >= Duration::from_millis(400) && took < Duration::from_millis(1400),
        "dropped after {took:?}"
    );

    // A served keep-alive connection that then idles is dropped after the idle timeout.
    let mut idle = TcpStream::connect(&srv.addr).unwrap();
    idle.write_all(GET).unwrap();
    assert!(status_within(&mut idle, Duration::from_secs(5))
        .unwrap()
        .contains("200"));
    let took = closed_within(&mut idle, Duration::from_secs(6)).unwrap();
    assert!(
        took >= Duration::from_millis(1200) && took < Duration::from_millis(3000),
        "idle connection dropped after {took:?}"
    );

    // Three connections hold the cap; the fourth is accepted by the kernel but not served.
    let mut held: Vec<TcpStream> = (0..3)
        .map(|_| {
            let mut s = TcpStream::connect(&srv.addr).unwrap();
            s.write_all(GET).unwrap();
            assert!(status_within(&mut s, Duration::from_secs(5))
                .unwrap()
                .contains("200"));
            s
        })
        .collect();
    let mut extra = TcpStream::connect(&srv.addr).unwrap();
    extra.write_all(GET).unwrap();
    assert_eq!(
        status_within(&mut extra, Duration::from_millis(700)),
        None,
        "the fourth connection was served past the cap of 3"
    );
    // One goes: the waiting one is served.
    drop(held.pop());
    let st = status_within(&mut extra, Duration::from_secs(5));
    assert!(st.as_deref().is_some_and(|s| s.contains("200")), "{st:?}");
}
