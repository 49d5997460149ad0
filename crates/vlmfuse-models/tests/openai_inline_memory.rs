//! An inline clip (`video_url` mode without a template) is held about once as base64 in the
//! request body, not five times over (file, base64 string, JSON value, serialised bytes, a copy
//! per attempt). A counting allocator measures the peak while the reporter sends a 6 MiB clip
//! twice (one retry) to a sink server that discards what it reads.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::{BufRead, BufReader, Read, Write};
use std::sync::atomic::{AtomicUsize, Ordering};
use vlmfuse_models::{ClipInput, ClipMeta, OpenAiReporter, OpenAiReporterConfig, Reporter};

struct Counting;
static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            let now = CURRENT.fetch_add(l.size(), Ordering::Relaxed) + l.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        CURRENT.fetch_sub(l.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static A: Counting = Counting;

/// Answers 503 to the first request and a chat completion to the second, reading each body
/// into a fixed buffer (its own memory does not grow with the request).
fn sink() -> String {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    std::thread::spawn(move || {
        for (n, s) in l.incoming().enumerate() {
            let Ok(s) = s else { break };
            let mut r = BufReader::new(s.try_clone().unwrap());
            let mut len = 0usize;
            loop {
                let mut line = String::new();
                if r.read_line(&mut line).unwrap_or(0) == 0 {
                    break;
                }
                let lower = line.to_ascii_lowercase();
                if let Some(v) = lower.strip_prefix("content-length:") {
                    len = v.trim().parse().unwrap();
                }
                if line == "\r\n" {
                    break;
                }
            }
            let mut buf = [0u8; 65536];
            while len > 0 {
                let k = r.read(&mut buf[..len.min(65536)]).unwrap();
                if k == 0 {
                    break;
                }
                len -= k;
            }
            let mut s = s;
            let resp = if n == 0 {
                "HTTP/1.1 503 Service Unavailable\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
                    .to_string()
            } else {
                let body = r#"{"choices":[{"message":{"content":"brake"}}],"model":"m"}"#;
                format!(
                    "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
                    body.len()
                )
            };
            let _ = s.write_all(resp.as_bytes());
        }
    });
    format!("http://{addr}")
}

#[test]
fn an_inline_clip_is_held_about_once() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("clip.mp4");
    let size = 6 << 20;
    std::fs::write(&path, vec![7u8; size]).unwrap();
    let clip = ClipInput {
        path,
        frames: Vec::new().into(),
        meta: ClipMeta::default(),
    };
    let url = sink();
    let r = OpenAiReporter::new(OpenAiReporterConfig {
        base_url: url,
        model: "m".into(),
        retries: 1,
        backoff_initial_ms: 1,
        timeout_s: 30.0,
        ..Default::default()
    })
    .unwrap();
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let out = rt.block_on(r.run(&clip)).unwrap();
    assert_eq!(out.text, "brake");
    let peak = PEAK.load(Ordering::Relaxed) - base;
    let b64 = size * 4 / 3;
    eprintln!(
        "peak {:.1} MiB for a {:.1} MiB clip ({:.1} MiB as base64)",
        peak as f64 / 1048576.0,
        size as f64 / 1048576.0,
        b64 as f64 / 1048576.0
    );
    assert!(
        peak < b64 * 3 / 2,
        "peak {peak} bytes for a {b64}-byte base64 body: more than one copy"
    );
}
