//! Weights by Hub id (`weights = { hub = "org/name", revision = "…" }`) against a loopback fake
//! hub that speaks the Hub's file API (`GET /{repo}/resolve/{revision}/{file}` with `Range`,
//! answering `etag`, `x-repo-commit` and `Content-Range` as huggingface.co does): a file not in
//! the cache is downloaded into the standard layout (blobs, snapshots, refs), a second load reads
//! the cache without asking, a file the repo lacks is absent (and remembered as such), and with
//! the hub gone the cache still serves; a file neither cached nor downloadable is an error that
//! names the repo, the revision and the file. No real network.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use vlmfuse_models::WeightSource;

const COMMIT: &str = "9f8e7d6c5b4a39281706f5e4d3c2b1a098765432";

struct FakeHub {
    url: String,
    requests: Arc<Mutex<Vec<String>>>,
    stop: Arc<AtomicBool>,
}

impl Drop for FakeHub {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop.
        let _ = TcpStream::connect(self.url.trim_start_matches("http://"));
    }
}

fn etag_of(b: &[u8]) -> String {
    // Any stable per-content string works as a blob name; the Hub uses the sha256 or git oid.
    let h = b.iter().fold(0xcbf29ce484222325u64, |h, &x| {
        (h ^ x as u64).wrapping_mul(0x100000001b3)
    });
    format!("{h:016x}")
}

fn answer(mut s: TcpStream, files: &BTreeMap<String, Vec<u8>>, log: &Mutex<Vec<String>>) {
    let mut r = BufReader::new(s.try_clone().unwrap());
    let mut line = String::new();
    if r.read_line(&mut line).is_err() || line.is_empty() {
        return;
    }
    let mut range: Option<(usize, Option<usize>)> = None;
    loop {
        let mut h = String::new();
        if r.read_line(&mut h).is_err() || h.trim().is_empty() {
            break;
        }
        let (k, v) = h.split_once(':').unwrap_or(("", ""));
        if k.eq_ignore_ascii_case("range") {
            let spec = v.trim().trim_start_matches("bytes=");
            let (a, b) = spec.split_once('-').unwrap_or((spec, ""));
            range = Some((a.parse().unwrap_or(0), b.parse().ok()));
        }
    }
    let path = line.split_whitespace().nth(1).unwrap_or("").to_string();
    log.lock().unwrap().push(path.clone());
    // /{org}/{name}/resolve/{revision}/{file}
    let parts: Vec<&str> = path.trim_start_matches('/').splitn(5, '/').collect();
    let body = (parts.len() == 5 && parts[2] == "resolve")
        .then(|| files.get(&format!("{}/{}/{}", parts[0], parts[1], parts[4])))
        .flatten();
    let resp = match body {
        None => b"HTTP/1.1 404 Not Found\r\nx-error-code: EntryNotFound\r\ncontent-length: 0\r\nconnection: close\r\n\r\n".to_vec(),
        Some(b) => {
            let (a, e) = match range {
                Some((a, e)) => (a.min(b.len()), e.map_or(b.len(), |e| (e + 1).min(b.len()))),
                None => (0, b.len()),
            };
            let mut out = format!(
                "HTTP/1.1 206 Partial Content\r\netag: \"{}\"\r\nx-repo-commit: {COMMIT}\r\n\
                 content-range: bytes {a}-{}/{}\r\ncontent-length: {}\r\nconnection: close\r\n\r\n",
                etag_of(b),
                e.saturating_sub(1),
                b.len(),
                e - a
            )
            .into_bytes();
            out.extend_from_slice(&b[a..e]);
            out
        }
    };
    let _ = s.write_all(&resp);
    let _ = s.flush();
    let mut sink = [0u8; 64];
    let _ = s.set_read_timeout(Some(std::time::Duration::from_millis(50)));
    let _ = s.read(&mut sink);
}

fn fake_hub(files: BTreeMap<String, Vec<u8>>) -> FakeHub {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", l.local_addr().unwrap());
    let requests = Arc::new(Mutex::new(Vec::new()));
    let stop = Arc::new(AtomicBool::new(false));
    let (log, halt) = (requests.clone(), stop.clone());
    let files = Arc::new(files);
    std::thread::spawn(move || {
        for s in l.incoming() {
            if halt.load(Ordering::SeqCst) {
                break;
            }
            if let Ok(s) = s {
                let (files, log) = (files.clone(), log.clone());
                std::thread::spawn(move || answer(s, &files, &log));
            }
        }
    });
    FakeHub {
        url,
        requests,
        stop,
    }
}

fn files() -> BTreeMap<String, Vec<u8>> {
    let mut m = BTreeMap::new();
    m.insert(
        "org/tiny/config.json".to_string(),
        br#"{"model_type": "tiny", "hidden_size": 8}"#.to_vec(),
    );
    // Large enough to be read in more than one piece.
    let weights: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
    m.insert("org/tiny/model.safetensors".to_string(), weights);
    m
}

fn count(hub: &FakeHub, file: &str) -> usize {
    hub.requests
        .lock()
        .unwrap()
        .iter()
        .filter(|p| p.ends_with(file))
        .count()
}

#[test]
fn a_hub_id_downloads_into_the_cache_once_and_then_works_offline() {
    let cache = tempfile::tempdir().unwrap();
    let hub = fake_hub(files());
    let src = WeightSource::hub("org/tiny", "main")
        .with_cache_dir(cache.path())
        .with_endpoint(&hub.url);

    let cfg = src.resolve("config.json").unwrap();
    let snapshot = cache
        .path()
        .join("models--org--tiny")
        .join("snapshots")
        .join(COMMIT);
    assert_eq!(cfg, snapshot.join("config.json"));
    let v: serde_json::Value = src.read_json("config.json").unwrap();
    assert_eq!(v["hidden_size"], 8);
    let w = src.safetensors_files().unwrap();
    assert_eq!(w, vec![snapshot.join("model.safetensors")]);
    assert_eq!(
        std::fs::read(&w[0]).unwrap(),
        files()["org/tiny/model.safetensors"],
        "the bytes, whole"
    );
    // The standard layout: the ref, and the blobs the snapshot links to.
    assert_eq!(
        std::fs::read_to_string(cache.path().join("models--org--tiny/refs/main"))
            .unwrap()
            .trim(),
        COMMIT
    );
    assert!(
        cache
            .path()
            .join("models--org--tiny/blobs")
            .read_dir()
            .unwrap()
            .count()
            >= 2
    );

    // A file the repo lacks is absent, and remembered: not asked for again.
    assert_eq!(
        src.resolve_optional("preprocessor_config.json").unwrap(),
        None
    );
    let asked = count(&hub, "preprocessor_config.json");
    assert_eq!(asked, 1);
    assert_eq!(
        src.resolve_optional("preprocessor_config.json").unwrap(),
        None
    );
    assert_eq!(
        count(&hub, "preprocessor_config.json"),
        asked,
        "the 404 is remembered"
    );

    // A second load reads the cache: no request.
    let before = hub.requests.lock().unwrap().len();
    src.resolve("config.json").unwrap();
    src.safetensors_files().unwrap();
    assert_eq!(hub.requests.lock().unwrap().len(), before);

    // The hub gone: the cache still serves.
    let url = hub.url.clone();
    drop(hub);
    let gone = WeightSource::hub("org/tiny", "main")
        .with_cache_dir(cache.path())
        .with_endpoint(&url);
    assert_eq!(gone.resolve("config.json").unwrap(), cfg);
}

#[test]
fn a_file_neither_cached_nor_downloadable_names_the_repo_and_file() {
    let cache = tempfile::tempdir().unwrap();
    // A port nothing listens on.
    let dead = {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}", l.local_addr().unwrap())
    };
    let src = WeightSource::hub("org/absent", "v3")
        .with_cache_dir(cache.path())
        .with_endpoint(&dead);
    let e = src.resolve("config.json").unwrap_err();
    assert_eq!(e.kind(), "download_failed");
    let msg = e.to_string();
    for part in ["org/absent", "v3", "config.json", "HF cache"] {
        assert!(msg.contains(part), "{part} not in: {msg}");
    }

    // A repo the hub does not have: the required file is missing, named with the URL asked.
    let hub = fake_hub(files());
    let src = WeightSource::hub("org/unknown", "main")
        .with_cache_dir(cache.path())
        .with_endpoint(&hub.url);
    let e = src.resolve("config.json").unwrap_err();
    assert_eq!(e.kind(), "missing_weights");
    assert!(
        e.to_string()
            .contains("org/unknown/resolve/main/config.json"),
        "{e}"
    );

    // Offline: the cache only, no request at all.
    let off = WeightSource::hub("org/tiny", "main")
        .with_cache_dir(cache.path())
        .with_endpoint(&hub.url)
        .offline();
    let e = off.resolve("config.json").unwrap_err();
    assert_eq!(e.kind(), "missing_weights");
    assert_eq!(count(&hub, "org/tiny/resolve/main/config.json"), 0);
}

#[test]
fn weights_by_hub_id_read_from_toml() {
    #[derive(serde::Deserialize)]
    struct W {
        weights: WeightSource,
    }
    let w: W = toml::from_str(
        "weights = { hub = \"org/tiny\", revision = \"v1\", endpoint = \"http://mirror:8080\" }",
    )
    .unwrap();
    assert_eq!(
        w.weights,
        WeightSource::hub("org/tiny", "v1").with_endpoint("http://mirror:8080")
    );
    let w: W = toml::from_str("weights = { hub = \"org/tiny\", offline = true }").unwrap();
    assert_eq!(w.weights, WeightSource::hub("org/tiny", "main").offline());
}
