//! The tests that need the real binary: a `kill -9` or a SIGTERM, or `vlmfuse eval`'s command
//! line. The server is started on a loopback port and spoken to with reqwest's blocking client.
#![allow(dead_code)]

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;
pub use vlmfuse_testkit::resp::Resp;

pub const BIN: &str = env!("CARGO_BIN_EXE_vlmfuse");

pub struct Server {
    pub child: Child,
    pub addr: String,
    pub data_dir: PathBuf,
}

impl Server {
    /// Starts `vlmfuse serve` on an ephemeral port and waits for its "listening" line.
    pub fn start(data_dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Server {
        Self::spawn(data_dir, args, env).wait(Duration::from_secs(60))
    }

    /// Starts `vlmfuse serve` on an ephemeral port without waiting for it to listen (a
    /// standby listens only once it holds the writer lease).
    pub fn spawn(data_dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Starting {
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
        Starting {
            child: Some(child),
            rx,
            data_dir: data_dir.to_path_buf(),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    pub fn get(&self, path: &str) -> Resp {
        read(client().get(self.url(path)).send())
    }

    pub fn post(&self, path: &str, body: &Value) -> Resp {
        try_post(&self.addr, path, body).unwrap_or_else(|e| panic!("POST {path}: {e}"))
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

/// A server process that has not said it listens yet.
pub struct Starting {
    child: Option<Child>,
    rx: mpsc::Receiver<String>,
    pub data_dir: PathBuf,
}

impl Starting {
    /// Its address once it listens, without waiting; `None` while it does not.
    pub fn listening(&mut self) -> Option<String> {
        self.rx.try_recv().ok()
    }

    /// The child's exit status if it has exited.
    pub fn exited(&mut self) -> Option<std::process::ExitStatus> {
        self.child
            .as_mut()
            .and_then(|c| c.try_wait().ok().flatten())
    }

    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, |c| c.id())
    }

    /// The server, once it listens (within `timeout`, or the test fails with its log).
    pub fn wait(mut self, timeout: Duration) -> Server {
        match self.rx.recv_timeout(timeout) {
            Ok(addr) => self.into_server(addr),
            Err(_) => {
                let mut c = self.child.take().unwrap();
                let _ = c.kill();
                let _ = c.wait();
                let log =
                    std::fs::read_to_string(self.data_dir.join("server.log")).unwrap_or_default();
                panic!("server did not start; log:\n{log}");
            }
        }
    }

    /// The server listening at `addr` (which [`Starting::listening`] gave).
    pub fn into_server(mut self, addr: String) -> Server {
        Server {
            child: self.child.take().unwrap(),
            addr,
            data_dir: self.data_dir.clone(),
        }
    }
}

impl Drop for Starting {
    fn drop(&mut self) {
        if let Some(c) = self.child.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// One client for every test request: no proxy (the server is on loopback), patient enough
/// for a debug build.
pub fn client() -> reqwest::blocking::Client {
    static CLIENT: std::sync::OnceLock<reqwest::blocking::Client> = std::sync::OnceLock::new();
    CLIENT
        .get_or_init(|| {
            reqwest::blocking::Client::builder()
                .no_proxy()
                .timeout(Duration::from_secs(120))
                .build()
                .unwrap()
        })
        .clone()
}

/// POSTs JSON; an error means the server could not be reached (it died).
pub fn try_post(addr: &str, path: &str, v: &Value) -> reqwest::Result<Resp> {
    client()
        .post(format!("http://{addr}{path}"))
        .json(v)
        .send()
        .map(read_response)
}

/// Reads a blocking response (an error means the server could not be reached).
pub fn read(r: reqwest::Result<reqwest::blocking::Response>) -> Resp {
    read_response(r.expect("request"))
}

fn read_response(r: reqwest::blocking::Response) -> Resp {
    let status = r.status().as_u16();
    let headers = r
        .headers()
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_str().unwrap_or("").to_string()))
        .collect();
    let body = r.bytes().map(|b| b.to_vec()).unwrap_or_default();
    Resp {
        status,
        headers,
        body,
    }
}
