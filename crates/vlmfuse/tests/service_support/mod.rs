//! Shared by the `service_*` tests: start the real binary on a loopback port, a tiny HTTP/1.1
//! client (no TLS, no async: a test should see exactly the bytes the server sent), and a
//! deterministic rounds generator.
#![allow(dead_code)]

use serde_json::Value;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

pub const BIN: &str = env!("CARGO_BIN_EXE_vlmfuse");

pub struct Server {
    pub child: Child,
    pub addr: String,
    pub data_dir: PathBuf,
}

impl Server {
    /// Starts `vlmfuse serve` on an ephemeral port and waits for its "listening" line.
    pub fn start(data_dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Server {
        std::fs::create_dir_all(data_dir).unwrap();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(data_dir.join("server.log"))
            .unwrap();
        let mut cmd = Command::new(BIN);
        cmd.arg("serve")
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--data-dir")
            .arg(data_dir)
            .args(args)
            .env("RUST_LOG", "warn")
            .env_remove("VLMFUSE_CONFIG")
            .env_remove("VLMFUSE_API_KEY")
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log));
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("spawn vlmfuse");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if let Some(a) = line.strip_prefix("vlmfuse listening on http://") {
                    let _ = tx.send(a.trim().to_string());
                }
            }
        });
        let addr = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(a) => a,
            Err(_) => {
                let _ = child.kill();
                let log = std::fs::read_to_string(data_dir.join("server.log")).unwrap_or_default();
                panic!("server did not start; log:\n{log}");
            }
        };
        Server {
            child,
            addr,
            data_dir: data_dir.to_path_buf(),
        }
    }

    pub fn req(&self, method: &str, path: &str, body: Option<&Value>) -> Resp {
        let b = body.map(|v| serde_json::to_vec(v).unwrap());
        request(
            &self.addr,
            method,
            path,
            &[("content-type", "application/json")],
            b.as_deref(),
        )
        .unwrap_or_else(|e| panic!("{method} {path}: {e}"))
    }

    pub fn get(&self, path: &str) -> Resp {
        self.req("GET", path, None)
    }

    pub fn post(&self, path: &str, body: &Value) -> Resp {
        self.req("POST", path, Some(body))
    }

    pub fn state(&self) -> Value {
        let r = self.get("/v1/state");
        assert_eq!(r.status, 200);
        r.json()
    }

    /// SIGKILL: no chance to flush anything.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn sigterm(&self) {
        let st = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(st.success());
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[derive(Debug, Clone)]
pub struct Resp {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Resp {
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "status {}: body is not JSON ({e}): {}",
                self.status,
                String::from_utf8_lossy(&self.body)
            )
        })
    }

    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// Asserts an error response: the status and the `{"error", "kind"}` shape.
    pub fn expect_error(&self, status: u16, kind: &str) {
        let v = self.json();
        assert_eq!(self.status, status, "body: {v}");
        assert_eq!(v["kind"], kind, "body: {v}");
        assert!(
            v["error"].as_str().is_some_and(|s| !s.is_empty()),
            "body: {v}"
        );
    }
}

/// One HTTP/1.1 request on a fresh connection (`Connection: close`).
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&[u8]>,
) -> std::io::Result<Resp> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    if let Some(b) = body {
        head.push_str(&format!("Content-Length: {}\r\n", b.len()));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes())?;
    if let Some(b) = body {
        // A server may answer (413) before reading everything; that is not our error.
        let _ = s.write_all(b);
    }
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    parse_response(&raw)
}

pub fn parse_response(raw: &[u8]) -> std::io::Result<Resp> {
    let bad = |m: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, m.to_string());
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| bad("no end of headers"))?;
    let head = std::str::from_utf8(&raw[..end]).map_err(|_| bad("headers not UTF-8"))?;
    let mut lines = head.split("\r\n");
    let status_line = lines.next().ok_or_else(|| bad("empty response"))?;
    let status: u16 = status_line
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| bad("bad status line"))?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect();
    let mut body = raw[end + 4..].to_vec();
    let chunked = headers.iter().any(|(k, v)| {
        k.eq_ignore_ascii_case("transfer-encoding") && v.eq_ignore_ascii_case("chunked")
    });
    if chunked {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let nl = rest
                .windows(2)
                .position(|w| w == b"\r\n")
                .ok_or_else(|| bad("bad chunk"))?;
            let size =
                usize::from_str_radix(std::str::from_utf8(&rest[..nl]).unwrap_or("").trim(), 16)
                    .map_err(|_| bad("bad chunk size"))?;
            if size == 0 {
                break;
            }
            out.extend_from_slice(&rest[nl + 2..nl + 2 + size]);
            rest = &rest[nl + 2 + size + 2..];
        }
        body = out;
    }
    Ok(Resp {
        status,
        headers,
        body,
    })
}

pub use vlmfuse_fusion::ontology::PAPER_LABELS as LABELS;

pub const REPORTERS: [&str; 3] = ["vlaad", "videollama2", "videollava"];

/// A SPEC §8 rounds stream with structure the method can learn: contexts cluster around a few
/// scene centres, each scene has typical labels, and each reporter is reliable in some scenes
/// and noisy in others. About 1 round in 8 is unlabelled and 1 in 10 misses a reporter.
pub fn generate_rounds(n: usize, d: usize, seed: u64) -> Vec<Value> {
    let mut s = seed;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    let scenes = 5;
    let centres: Vec<Vec<f64>> = (0..scenes)
        .map(|_| (0..d).map(|_| next() - 0.5).collect())
        .collect();
    let typical: Vec<Vec<usize>> = (0..scenes)
        .map(|c| vec![(2 * c) % 14, (3 * c + 1) % 14, (5 * c + 4) % 14])
        .collect();
    (0..n)
        .map(|i| {
            let c = (next() * scenes as f64) as usize % scenes;
            let context: Vec<f64> = centres[c]
                .iter()
                .map(|v| v + 0.3 * (next() - 0.5))
                .collect();
            let truth: Vec<&str> = typical[c]
                .iter()
                .filter(|_| next() < 0.6)
                .map(|&k| LABELS[k])
                .collect();
            let mut reports = serde_json::Map::new();
            for (r, name) in REPORTERS.iter().enumerate() {
                if next() < 0.1 {
                    continue;
                }
                let noise = if (r + c).is_multiple_of(3) { 0.4 } else { 0.08 };
                let mut labs: Vec<&str> = Vec::new();
                for (k, lab) in LABELS.iter().enumerate() {
                    let on = truth.contains(lab);
                    let flip = next() < if on { noise } else { noise / 4.0 };
                    if on != flip {
                        labs.push(LABELS[k]);
                    }
                }
                reports.insert((*name).into(), labs.into());
            }
            if reports.is_empty() {
                reports.insert("vlaad".into(), Value::Array(vec![]));
            }
            let mut v = serde_json::json!({
                "id": format!("g-{i:05}"),
                "context": context,
                "reports": reports,
            });
            if next() >= 0.125 {
                v["truth"] = truth.into();
            }
            v
        })
        .collect()
}

/// The reporters of a rounds list, sorted, as `eval` orders them.
pub fn sorted_reporters(rounds: &[Value]) -> Vec<String> {
    let mut names: Vec<String> = rounds
        .iter()
        .flat_map(|r| r["reports"].as_object().unwrap().keys().cloned())
        .collect();
    names.sort();
    names.dedup();
    names
}

pub fn write_jsonl(path: &Path, rounds: &[Value]) {
    let mut f = std::fs::File::create(path).unwrap();
    for r in rounds {
        writeln!(f, "{}", serde_json::to_string(r).unwrap()).unwrap();
    }
}

pub fn read_jsonl(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}
