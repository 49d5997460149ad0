//! `/v1/fuse` requests per second with a 10k-round bank, against `/healthz` on the same server
//! in the same run: the ratio is the cost of fusion (kNN over the bank, Shapley-ready signals,
//! a durable group-committed insert) over the HTTP stack alone.
//!
//! `cargo bench -p vlmfuse --bench http [-- BANK SECONDS CLIENTS]` (defaults 10000 5 16).
//!
//! `-- --replicas [BANK SECONDS CLIENTS]`: `/v1/fuse` throughput and latency on the embedded
//! SQLite store, on PostgreSQL with one replica, and with three (one writer, two followers that
//! forward to it; the load spread over all three), in one run on a PostgreSQL server the bench
//! starts on a loopback port (docs/ARCHITECTURE.md, "Replicas").
//! The bank is written straight into the database (the rebuild on start is what a restarted
//! service does), so the run does not spend minutes on 10k fsynced feedbacks first.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vlmfuse_fusion::{Engine, FusionConfig, Ontology, RoundRecord};
use vlmfuse_store::{Identity, Location, NewRound, Store, StoredFeedback};
use vlmfuse_testkit::rng::Lcg as Rng;

const D: usize = 128;
const REPORTERS: [&str; 3] = ["vlaad", "videollama2", "videollava"];

fn record(rng: &mut Rng, ont: &Ontology) -> RoundRecord {
    let mut reports = BTreeMap::new();
    for r in REPORTERS {
        let labs = (0..ont.len())
            .filter(|_| rng.f() < 0.15)
            .map(|k| ont.id(k).to_string())
            .collect();
        reports.insert(r.to_string(), labs);
    }
    RoundRecord {
        id: None,
        context: (0..D).map(|_| rng.f() - 0.5).collect(),
        reports,
        truth: Some(
            (0..ont.len())
                .filter(|_| rng.f() < 0.15)
                .map(|k| ont.id(k).to_string())
                .collect(),
        ),
    }
}

fn prefill(at: &Location, bank: u64) {
    let ont = Ontology::paper();
    let reporters: Vec<String> = REPORTERS.map(String::from).to_vec();
    let engine = Engine::new(FusionConfig::default(), ont.clone(), reporters.clone()).unwrap();
    let mut store = Store::open_at(at, Duration::ZERO).unwrap();
    store
        .check_identity(&Identity {
            reporters,
            labels: ont.labels().iter().map(|l| l.id.clone()).collect(),
        })
        .unwrap();
    let mut rng = Rng(42);
    let mut rounds = Vec::new();
    let mut fbs = Vec::new();
    let mut outcome = None;
    for seq in 0..bank {
        let rec = record(&mut rng, &ont);
        let (round, truth) = engine.parse(&rec).unwrap();
        let mut inf = engine.infer(&round);
        inf.q = (0..ont.len()).map(|_| rng.f()).collect();
        let truth = truth.unwrap();
        let o = outcome
            .get_or_insert_with(|| engine.credit(&inf.signals, &inf.w_used, &truth, 0))
            .clone();
        fbs.push(StoredFeedback {
            seq,
            labelled_order: seq,
            rounds_before: bank,
            truth,
            outcome: o,
            source: "human".into(),
        });
        rounds.push(NewRound {
            round,
            inference: inf,
            request: serde_json::Value::Null,
            created_ms: 0,
            thumbnails: Vec::new(),
        });
    }
    store.insert_rounds(0, &rounds).unwrap();
    store.insert_feedback(&fbs).unwrap();
}

/// One request of the load: a route and, for a POST, its JSON body.
#[derive(Clone)]
enum Req {
    Get(String),
    Post(String, Vec<u8>),
}

/// `clients` keep-alive connections (one reqwest client each, so none shares a socket), each
/// sending one request at a time for `secs` seconds.
fn load(requests: Arc<Vec<Req>>, clients: usize, secs: f64) -> (f64, Vec<f64>) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicU64::new(0));
    let tasks: Vec<_> = (0..clients)
        .map(|c| {
            let (reqs, stop, done) = (requests.clone(), stop.clone(), done.clone());
            rt.spawn(async move {
                let client = reqwest::Client::builder()
                    .no_proxy()
                    .pool_max_idle_per_host(1)
                    .build()
                    .unwrap();
                let mut lat = Vec::new();
                let mut i = c;
                while !stop.load(Ordering::Relaxed) {
                    let t = Instant::now();
                    let resp = match &reqs[i % reqs.len()] {
                        Req::Get(url) => client.get(url).send().await,
                        Req::Post(url, body) => {
                            client
                                .post(url)
                                .header("content-type", "application/json")
                                .body(body.clone())
                                .send()
                                .await
                        }
                    }
                    .unwrap();
                    assert_eq!(resp.status(), 200);
                    resp.bytes().await.unwrap();
                    lat.push(t.elapsed().as_secs_f64());
                    done.fetch_add(1, Ordering::Relaxed);
                    i += clients;
                }
                lat
            })
        })
        .collect();
    let start = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(secs));
    stop.store(true, Ordering::Relaxed);
    let mut lat: Vec<f64> = rt.block_on(async {
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.unwrap());
        }
        all
    });
    let rps = done.load(Ordering::Relaxed) as f64 / start.elapsed().as_secs_f64();
    lat.sort_by(f64::total_cmp);
    let pct = |p: f64| lat[((lat.len() - 1) as f64 * p) as usize] * 1e3;
    (rps, vec![pct(0.5), pct(0.99)])
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let bank: u64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(10_000);
    let secs: f64 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(5.0);
    let clients: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(16);

    if std::env::args().any(|a| a == "--replicas") {
        return replicas(bank, secs, clients);
    }
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let t = Instant::now();
    prefill(&Location::Sqlite { dir: data.clone() }, bank);
    eprintln!(
        "prefilled {bank} labelled rounds in {:.1} s",
        t.elapsed().as_secs_f64()
    );

    let mut child = Command::new(env!("CARGO_BIN_EXE_vlmfuse"))
        .args(["serve", "--listen", "127.0.0.1:0", "--data-dir"])
        .arg(&data)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    let addr = line
        .trim()
        .strip_prefix("vlmfuse listening on http://")
        .expect("listening line")
        .to_string();
    eprintln!(
        "server up at {addr} in {:.2} s (rebuild of {bank} rounds included)",
        started.elapsed().as_secs_f64()
    );

    let ont = Ontology::paper();
    let mut rng = Rng(7);
    let fuse: Vec<Req> = (0..512)
        .map(|_| {
            let mut rec = record(&mut rng, &ont);
            rec.truth = None;
            Req::Post(
                format!("http://{addr}/v1/fuse"),
                serde_json::to_vec(&rec).unwrap(),
            )
        })
        .collect();
    let health = vec![Req::Get(format!("http://{addr}/healthz"))];

    let (h_rps, h_lat) = load(Arc::new(health), clients, secs);
    let (f_rps, f_lat) = load(Arc::new(fuse), clients, secs);
    println!("bank {bank}, d {D}, {clients} keep-alive clients, {secs} s each");
    println!(
        "/healthz : {h_rps:>9.0} req/s  p50 {:.3} ms  p99 {:.3} ms",
        h_lat[0], h_lat[1]
    );
    println!(
        "/v1/fuse : {f_rps:>9.0} req/s  p50 {:.3} ms  p99 {:.3} ms",
        f_lat[0], f_lat[1]
    );
    println!("fuse / healthz = {:.4}", f_rps / h_rps);
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let _ = child.wait();
}

/// `vlmfuse serve` on a loopback port with `args`; the child and its address.
fn serve(data: &std::path::Path, args: &[&str]) -> (std::process::Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_vlmfuse"))
        .args(["serve", "--listen", "127.0.0.1:0", "--data-dir"])
        .arg(data)
        .args(args)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    let addr = line
        .trim()
        .strip_prefix("vlmfuse listening on http://")
        .expect("listening line")
        .to_string();
    (child, addr)
}

/// `/v1/fuse` on SQLite, on PostgreSQL with one replica and with three, in one run.
fn replicas(bank: u64, secs: f64, clients: usize) {
    let pg = vlmfuse_testkit::pg::PgServer::start().expect("PostgreSQL for the bench");
    let tmp = tempfile::tempdir().unwrap();
    let ont = Ontology::paper();
    let mut rng = Rng(7);
    let bodies: Vec<Vec<u8>> = (0..512)
        .map(|_| {
            let mut rec = record(&mut rng, &ont);
            rec.truth = None;
            serde_json::to_vec(&rec).unwrap()
        })
        .collect();
    println!("/v1/fuse, bank {bank}, d {D}, {clients} keep-alive clients, {secs} s each");
    println!("| store | replicas | req/s | p50 ms | p99 ms |");
    println!("|---|---|---|---|---|");
    for (store, n) in [("sqlite", 1usize), ("postgres", 1), ("postgres", 3)] {
        let url = match store {
            "sqlite" => None,
            _ => Some(pg.create_db(&format!("bench_{n}")).unwrap()),
        };
        let dirs: Vec<_> = (0..n)
            .map(|i| tmp.path().join(format!("{store}-{n}-{i}")))
            .collect();
        prefill(
            &match &url {
                None => Location::Sqlite {
                    dir: dirs[0].clone(),
                },
                Some(u) => {
                    let mut o = vlmfuse_store::pg::PgOptions::new(u.clone(), &dirs[0]);
                    o.lease_wait = Duration::ZERO;
                    Location::Postgres(o)
                }
            },
            bank,
        );
        let mut children = Vec::new();
        let mut addrs = Vec::new();
        for (i, d) in dirs.iter().enumerate() {
            let name = format!("r{i}");
            let mut args = vec![];
            if let Some(u) = &url {
                args.extend(["--store-url", u.as_str(), "--store-lease-wait-s", "0"]);
                args.extend(["--store-replica-name", name.as_str()]);
            }
            let (c, a) = serve(d, &args);
            children.push(c);
            addrs.push(a);
        }
        // The followers learn the writer's address from the lease row within a moment.
        let t = Instant::now();
        let client = reqwest::blocking::Client::builder()
            .no_proxy()
            .build()
            .unwrap();
        for a in &addrs[1..] {
            while t.elapsed() < Duration::from_secs(30) {
                let v: serde_json::Value = client
                    .get(format!("http://{a}/v1/state"))
                    .send()
                    .and_then(|r| r.json())
                    .unwrap_or_default();
                if v["replica"]["writer"].is_string() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            std::thread::sleep(Duration::from_millis(500));
        }
        let reqs: Vec<Req> = bodies
            .iter()
            .enumerate()
            .map(|(i, b)| Req::Post(format!("http://{}/v1/fuse", addrs[i % n]), b.clone()))
            .collect();
        let (rps, lat) = load(Arc::new(reqs), clients, secs);
        println!(
            "| {store} | {n} | {rps:.0} | {:.2} | {:.2} |",
            lat[0], lat[1]
        );
        for mut c in children {
            let _ = Command::new("kill")
                .args(["-TERM", &c.id().to_string()])
                .status();
            let _ = c.wait();
        }
    }
}
