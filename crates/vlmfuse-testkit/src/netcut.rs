//! A loopback TCP relay that can be cut like a network partition: [`Relay::cut`] stops moving
//! bytes in both directions but keeps every socket open, so neither end sees a reset or a close
//! (as when packets are dropped on the way), only silence.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

pub struct Relay {
    port: u16,
    cut: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

fn pump(mut from: TcpStream, mut to: TcpStream, cut: Arc<AtomicBool>, stop: Arc<AtomicBool>) {
    let _ = from.set_read_timeout(Some(Duration::from_millis(20)));
    let mut buf = vec![0u8; 64 * 1024];
    while !stop.load(Ordering::SeqCst) {
        if cut.load(Ordering::SeqCst) {
            // Silence: nothing read, nothing written, nothing closed.
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        match from.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => {
                if to.write_all(&buf[..n]).is_err() {
                    break;
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => break,
        }
    }
    // A cut relay never closes (a partition sends no FIN); a stopped one lets go.
    if !cut.load(Ordering::SeqCst) {
        let _ = to.shutdown(std::net::Shutdown::Write);
    } else {
        std::mem::forget((from, to));
    }
}

impl Relay {
    /// Relays connections on a free loopback port to `upstream` (`host:port`).
    pub fn start(upstream: &str) -> std::io::Result<Relay> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        let port = listener.local_addr()?.port();
        let (cut, stop) = (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicBool::new(false)),
        );
        let (c, s, up) = (cut.clone(), stop.clone(), upstream.to_string());
        std::thread::spawn(move || {
            for client in listener.incoming() {
                if s.load(Ordering::SeqCst) {
                    break;
                }
                let Ok(client) = client else { continue };
                let Ok(server) = TcpStream::connect(&up) else {
                    continue;
                };
                for (a, b) in [
                    (client.try_clone(), server.try_clone()),
                    (server.try_clone(), client.try_clone()),
                ] {
                    if let (Ok(a), Ok(b)) = (a, b) {
                        let (c, s) = (c.clone(), s.clone());
                        std::thread::spawn(move || pump(a, b, c, s));
                    }
                }
            }
        });
        Ok(Relay { port, cut, stop })
    }

    pub fn port(&self) -> u16 {
        self.port
    }

    /// From now on, silence both ways on every relayed connection.
    pub fn cut(&self) {
        self.cut.store(true, Ordering::SeqCst);
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop so it sees the stop.
        let _ = TcpStream::connect(("127.0.0.1", self.port));
    }
}
