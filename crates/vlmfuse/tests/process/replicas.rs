//! Replicas on one PostgreSQL database (a real server, started on a loopback port with a
//! temporary data directory and stopped by PID): one writer at a time through the lease, a
//! standby that takes over after `kill -9` of the writer and loses nothing acknowledged, and a
//! writer whose database session is cut that stops writing before another takes over.

use crate::replay::{assert_identical, replay, rounds, truth, Progress};
use crate::support::*;
use serde_json::{json, Value};
use std::process::Command;
use std::time::{Duration, Instant};
use vlmfuse_testkit::pg::PgServer;
use vlmfuse_testkit::rounds::sorted_reporters;

fn pg() -> PgServer {
    PgServer::start().unwrap_or_else(|e| panic!("PostgreSQL for the replica tests: {e}"))
}

/// A replica's flags: the shared database, waiting for the lease as a standby, a short lease
/// timeout, and frequent snapshots.
fn replica<'a>(url: &'a str, name: &'a str, reporters: &'a str) -> Vec<&'a str> {
    vec![
        "--reporters",
        reporters,
        "--store-url",
        url,
        "--store-standby",
        "true",
        "--store-replica-name",
        name,
        "--store-lease-timeout-s",
        "3",
        "--snapshot-every",
        "37",
    ]
}

/// The first of `standbys` to listen, with its index, within `timeout`.
fn first_to_listen(standbys: &mut [Starting], timeout: Duration) -> (usize, String) {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        for (i, s) in standbys.iter_mut().enumerate() {
            if let Some(a) = s.listening() {
                return (i, a);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("no standby took over within {timeout:?}");
}

#[test]
fn a_standby_takes_over_after_kill_9_and_continues_as_one_sqlite_server() {
    let tmp = tempfile::tempdir().unwrap();
    let (all, _) = rounds(tmp.path());
    let rounds = &all[..all.len().min(240)];
    let reporters = sorted_reporters(rounds).join(",");

    // The reference: one server on SQLite, uninterrupted.
    let (dir_a, rounds_a, reporters_a) = (
        tmp.path().join("sqlite"),
        rounds.to_vec(),
        reporters.clone(),
    );
    let reference = std::thread::spawn(move || {
        let srv = Server::start(&dir_a, &["--reporters", &reporters_a], &[]);
        let mut prog = Progress::default();
        assert!(replay(&srv.addr, &rounds_a, &mut prog));
        (prog.seen, srv.state())
    });

    let db = pg();
    let url = db.create_db("replicas").unwrap();
    let first = Server::start(
        &tmp.path().join("r1"),
        &replica(&url, "r1", &reporters),
        &[],
    );
    let ready = first.get("/readyz").json();
    assert_eq!(
        ready["components"]["store"]["backend"], "postgres",
        "{ready}"
    );
    assert_eq!(ready["components"]["store"]["role"], "writer", "{ready}");
    assert_eq!(ready["components"]["store"]["replica"], "r1", "{ready}");
    let mut standbys = vec![
        Server::spawn(
            &tmp.path().join("r2"),
            &replica(&url, "r2", &reporters),
            &[("RUST_LOG", "info")],
        ),
        Server::spawn(
            &tmp.path().join("r3"),
            &replica(&url, "r3", &reporters),
            &[("RUST_LOG", "info")],
        ),
    ];
    // One writer: while the first holds the lease, neither standby opens its port.
    std::thread::sleep(Duration::from_secs(2));
    for s in &mut standbys {
        assert!(
            s.listening().is_none(),
            "a second writer started beside the first"
        );
        assert!(s.exited().is_none(), "a standby gave up waiting");
    }

    let mut prog = Progress::default();
    let half = rounds.len() / 2;
    assert!(replay(&first.addr, &rounds[..half], &mut prog));
    // kill -9 of the writer with requests in flight, once the second half has begun to commit.
    let (pid, addr) = (first.child.id().to_string(), first.addr.clone());
    let killer = std::thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline {
            let stored = client()
                .get(format!("http://{addr}/v1/state"))
                .send()
                .ok()
                .and_then(|r| r.json::<Value>().ok())
                .and_then(|v| v["rounds"].as_u64())
                .unwrap_or(0);
            if stored as usize > half + 2 {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Command::new("kill").args(["-9", &pid]).status().unwrap();
        Instant::now()
    });
    let finished = replay(&first.addr, rounds, &mut prog);
    let killed_at = killer.join().unwrap();
    assert!(
        !finished,
        "the replay finished before the kill; kill earlier"
    );
    drop(first);
    let acked = prog.seen.len();
    assert!(acked > half, "nothing got through after the half");

    let (i, addr) = first_to_listen(&mut standbys, Duration::from_secs(60));
    let failover = killed_at.elapsed();
    eprintln!(
        "failover: a standby listened {:.2} s after kill -9 of the writer",
        failover.as_secs_f64()
    );
    let taken = standbys.remove(i);
    let name = if taken.data_dir.ends_with("r2") {
        "r2"
    } else {
        "r3"
    };
    let srv = taken.into_server(addr);
    let ready = srv.get("/readyz").json();
    assert_eq!(ready["components"]["store"]["replica"], name, "{ready}");
    assert!(standbys[0].listening().is_none(), "two standbys took over");
    let log = std::fs::read_to_string(srv.data_dir.join("server.log")).unwrap();
    assert!(log.contains("waiting for the writer lease"), "{log}");

    // Every acknowledged feedback is stored once: its repeat is answered from the store.
    let st = srv.state();
    for (i, s) in prog.seen.iter().enumerate() {
        let Some(fb) = &s.feedback else { continue };
        let body = json!({"round_id": fb["round_id"], "labels": truth(&rounds[i]).unwrap()});
        let r = try_post(&srv.addr, "/v1/feedback", &body).unwrap();
        assert_eq!(r.status, 200, "round {i}");
        assert_eq!(
            r.header("x-vlmfuse-repeated"),
            Some("true"),
            "round {i} was not stored"
        );
        assert_eq!(
            &r.json(),
            fb,
            "round {i}: the repeat differs from the acknowledged answer"
        );
    }
    assert_eq!(
        srv.state(),
        st,
        "repeating acknowledged feedback changed the state"
    );
    // The rest, through the new writer (the fuse in flight at the kill is retried under its
    // request id, so a round committed but never acknowledged is not stored twice).
    assert!(
        replay(&srv.addr, rounds, &mut prog),
        "the new writer failed"
    );
    let state = srv.state();

    let (seen_ref, state_ref) = reference.join().unwrap();
    assert_identical(&seen_ref, &prog.seen);
    for key in [
        "reputations",
        "labelled_rounds",
        "threshold",
        "reporters",
        "dim",
        "rounds",
    ] {
        assert_eq!(
            state_ref[key], state[key],
            "final state {key} differs from SQLite's"
        );
    }
}

#[test]
fn a_writer_whose_session_is_cut_stops_before_another_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let (all, _) = rounds(tmp.path());
    let rounds = &all[..20];
    let reporters = sorted_reporters(rounds).join(",");
    let db = pg();
    let url = db.create_db("partition").unwrap();
    let mut first = Server::start(
        &tmp.path().join("r1"),
        &replica(&url, "r1", &reporters),
        &[],
    );
    let mut standby = Server::spawn(
        &tmp.path().join("r2"),
        &replica(&url, "r2", &reporters),
        &[],
    );
    let mut prog = Progress::default();
    assert!(replay(&first.addr, &rounds[..10], &mut prog));
    assert!(
        standby.listening().is_none(),
        "a second writer started beside the first"
    );

    // The stand-in for a partition: the database ends the writer's session (only the lease
    // holder's: the standby's waiting session stays).
    let cut = db
        .sql(
            "partition",
            "SELECT count(*) FROM (SELECT pg_terminate_backend(pid) FROM pg_locks \
             WHERE locktype = 'advisory' AND granted) t",
        )
        .unwrap();
    assert_eq!(cut, "1");
    let t = Instant::now();
    // The old writer stops: within its heartbeat it refuses writes and exits (75) for its
    // supervisor to restart it as a standby.
    let status = loop {
        if let Some(s) = first.child.try_wait().unwrap() {
            break s;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the cut writer kept running"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(status.code(), Some(75), "{status:?}");
    let log = std::fs::read_to_string(first.data_dir.join("server.log")).unwrap();
    assert!(log.contains("lost the writer lease"), "{log}");
    first.kill9();
    // The standby takes over and holds everything the old writer acknowledged.
    let srv = standby.wait(Duration::from_secs(60));
    let st = srv.state();
    assert_eq!(st["rounds"].as_u64(), Some(10));
    assert_eq!(
        st["labelled_rounds"].as_u64(),
        Some(prog.seen.iter().filter(|s| s.feedback.is_some()).count() as u64)
    );
    assert!(replay(&srv.addr, rounds, &mut prog));
    assert_eq!(srv.state()["rounds"].as_u64(), Some(20));
}

/// A replica's flags as a follower: it serves and forwards while another writes.
fn follower<'a>(url: &'a str, name: &'a str, reporters: &'a str) -> Vec<&'a str> {
    let mut a = replica(url, name, reporters);
    a[5] = "false";
    a.extend(["--store-lease-wait-s", "0"]);
    a
}

#[test]
fn followers_serve_forward_and_one_takes_over_as_one_sqlite_server_would() {
    let tmp = tempfile::tempdir().unwrap();
    let (all, _) = rounds(tmp.path());
    let rounds = &all[..all.len().min(240)];
    let reporters = sorted_reporters(rounds).join(",");
    let (dir_a, rounds_a, reporters_a) = (
        tmp.path().join("sqlite"),
        rounds.to_vec(),
        reporters.clone(),
    );
    let reference = std::thread::spawn(move || {
        let srv = Server::start(&dir_a, &["--reporters", &reporters_a], &[]);
        let mut prog = Progress::default();
        assert!(replay(&srv.addr, &rounds_a, &mut prog));
        (prog.seen, srv.state())
    });

    let db = pg();
    let url = db.create_db("followers").unwrap();
    let writer = Server::start(
        &tmp.path().join("r1"),
        &follower(&url, "r1", &reporters),
        &[],
    );
    let f2 = Server::start(
        &tmp.path().join("r2"),
        &follower(&url, "r2", &reporters),
        &[],
    );
    let f3 = Server::start(
        &tmp.path().join("r3"),
        &follower(&url, "r3", &reporters),
        &[],
    );
    for (s, role) in [(&writer, "writer"), (&f2, "follower"), (&f3, "follower")] {
        let ready = s.get("/readyz").json();
        assert_eq!(ready["components"]["store"]["role"], role, "{ready}");
    }
    assert_eq!(
        f2.get("/readyz").json()["components"]["store"]["writer"],
        "r1"
    );

    // One client, round by round across the three replicas; the writer is killed mid-way.
    let mut addrs = vec![writer.addr.clone(), f2.addr.clone(), f3.addr.clone()];
    let half = rounds.len() / 2;
    let (pid, waddr) = (writer.child.id().to_string(), writer.addr.clone());
    let killed = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let killed_k = killed.clone();
    let killer = std::thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(120);
        while Instant::now() < deadline {
            let stored = client()
                .get(format!("http://{waddr}/v1/state"))
                .send()
                .ok()
                .and_then(|r| r.json::<Value>().ok())
                .and_then(|v| v["rounds"].as_u64())
                .unwrap_or(0);
            if stored as usize > half + 2 {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Command::new("kill").args(["-9", &pid]).status().unwrap();
        killed_k.store(true, std::sync::atomic::Ordering::SeqCst);
        Instant::now()
    });
    let mut prog = Progress::default();
    let mut down_since: Option<Instant> = None;
    let mut longest_gap = Duration::ZERO;
    let deadline = Instant::now() + Duration::from_secs(300);
    while prog.seen.len() < rounds.len() {
        assert!(
            Instant::now() < deadline,
            "the replicas stopped making progress"
        );
        let k = prog.seen.len();
        if killed.load(std::sync::atomic::Ordering::SeqCst) && addrs[0] == writer.addr {
            addrs.remove(0);
        }
        let addr = addrs[k % addrs.len()].clone();
        if replay(&addr, &rounds[..k + 1], &mut prog) {
            if let Some(t) = down_since.take() {
                longest_gap = longest_gap.max(t.elapsed());
            }
        } else {
            down_since.get_or_insert_with(Instant::now);
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let killed_at = killer.join().unwrap();
    assert!(killed.load(std::sync::atomic::Ordering::SeqCst));
    eprintln!(
        "followers: writes were unavailable for {:.2} s around kill -9 of the writer ({:.1} s ago)",
        longest_gap.as_secs_f64(),
        killed_at.elapsed().as_secs_f64()
    );
    // One of the followers writes now; the other forwards to it.
    let roles: Vec<Value> = [&f2, &f3]
        .iter()
        .map(|s| s.get("/readyz").json()["components"]["store"]["role"].clone())
        .collect();
    assert!(
        roles.contains(&json!("writer")) && roles.contains(&json!("follower")),
        "{roles:?}"
    );

    let (seen_ref, state_ref) = reference.join().unwrap();
    assert_identical(&seen_ref, &prog.seen);
    // Both serve the same state once the follower has read the last events.
    for s in [&f2, &f3] {
        let t = Instant::now();
        let st = loop {
            let st = s.state();
            if st["state_seq"] == state_ref["state_seq"] || t.elapsed() > Duration::from_secs(10) {
                break st;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        for key in [
            "reputations",
            "labelled_rounds",
            "threshold",
            "reporters",
            "dim",
            "rounds",
            "state_seq",
        ] {
            assert_eq!(state_ref[key], st[key], "{key} differs from SQLite's");
        }
    }
}

/// POSTs until an answer that is not "unavailable" comes, rotating over `addrs` (skipping the
/// ones that do not answer); the answer.
fn post_until_served(addrs: &[String], start: usize, path: &str, body: &Value) -> Resp {
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut i = start;
    loop {
        assert!(Instant::now() < deadline, "no replica served {path} {body}");
        if let Ok(r) = try_post(&addrs[i % addrs.len()], path, body) {
            if r.status != 503 {
                return r;
            }
        }
        i += 1;
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_burst_from_several_clients_survives_kill_9_of_the_writer() {
    let tmp = tempfile::tempdir().unwrap();
    let (all, _) = rounds(tmp.path());
    let rounds: Vec<Value> = all[..all.len().min(150)].to_vec();
    let reporters = sorted_reporters(&rounds).join(",");
    let db = pg();
    let url = db.create_db("burst").unwrap();
    let writer = Server::start(
        &tmp.path().join("r1"),
        &follower(&url, "r1", &reporters),
        &[],
    );
    let f2 = Server::start(
        &tmp.path().join("r2"),
        &follower(&url, "r2", &reporters),
        &[],
    );
    let f3 = Server::start(
        &tmp.path().join("r3"),
        &follower(&url, "r3", &reporters),
        &[],
    );
    let addrs = vec![writer.addr.clone(), f2.addr.clone(), f3.addr.clone()];

    // Three clients, each its own third of the rounds through its own replica, fuse then
    // feedback, every fuse under a request id; the writer is killed once 40 rounds are in.
    let (pid, waddr) = (writer.child.id().to_string(), writer.addr.clone());
    let killer = std::thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(120);
        let mut stored = 0;
        while Instant::now() < deadline {
            stored = client()
                .get(format!("http://{waddr}/v1/state"))
                .send()
                .ok()
                .and_then(|r| r.json::<Value>().ok())
                .and_then(|v| v["rounds"].as_u64())
                .unwrap_or(0);
            if stored >= 40 {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Command::new("kill").args(["-9", &pid]).status().unwrap();
        stored
    });
    let clients: Vec<_> = (0..3)
        .map(|c| {
            let (rounds, addrs) = (rounds.clone(), addrs.clone());
            std::thread::spawn(move || {
                let mut acked = Vec::new();
                for (i, r) in rounds.iter().enumerate().filter(|(i, _)| i % 3 == c) {
                    let mut body = r.clone();
                    let truth = body.as_object_mut().unwrap().remove("truth");
                    body["request_id"] = json!(format!("burst-{i}"));
                    let fused = post_until_served(&addrs, c, "/v1/fuse", &body);
                    assert_eq!(
                        fused.status,
                        200,
                        "round {i}: {}",
                        String::from_utf8_lossy(&fused.body)
                    );
                    let round_id = fused.json()["round_id"].as_str().unwrap().to_string();
                    let fb = truth.filter(|t| !t.is_null()).map(|t| {
                        let fb = json!({"round_id": round_id, "labels": t});
                        let r = post_until_served(&addrs, c, "/v1/feedback", &fb);
                        assert_eq!(
                            r.status,
                            200,
                            "round {i}: {}",
                            String::from_utf8_lossy(&r.body)
                        );
                        (fb, r.json())
                    });
                    acked.push((i, round_id, fb));
                }
                acked
            })
        })
        .collect();
    let acked: Vec<_> = clients
        .into_iter()
        .flat_map(|c| c.join().unwrap())
        .collect();
    let at_kill = killer.join().unwrap();
    assert!(
        (40..100).contains(&at_kill),
        "the kill came at {at_kill} rounds, not mid-burst"
    );
    drop(writer);

    // Every round once: as many rows as rounds sent, each acknowledged id distinct.
    assert_eq!(acked.len(), rounds.len());
    let stored = db.sql("burst", "SELECT count(*) FROM rounds").unwrap();
    assert_eq!(
        stored,
        rounds.len().to_string(),
        "a retried fuse was stored twice, or one was lost"
    );
    let mut ids: Vec<&String> = acked.iter().map(|(_, id, _)| id).collect();
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), rounds.len());
    // Every acknowledged feedback is stored once: its repeat is answered from the store.
    let live = vec![f2.addr.clone(), f3.addr.clone()];
    let mut labelled = 0;
    for (i, _, fb) in &acked {
        let Some((body, answer)) = fb else { continue };
        labelled += 1;
        let r = post_until_served(&live, *i, "/v1/feedback", body);
        assert_eq!(
            r.header("x-vlmfuse-repeated"),
            Some("true"),
            "round {i} was not stored"
        );
        assert_eq!(&r.json(), answer, "round {i}: the repeat differs");
    }
    let feedback = db.sql("burst", "SELECT count(*) FROM feedback").unwrap();
    assert_eq!(feedback, labelled.to_string());

    // The engine equals a full replay: a fresh replica (no snapshot) rebuilds it from every
    // event, and it, the new writer and the other follower agree.
    let fresh = Server::start(
        &tmp.path().join("r4"),
        &follower(&url, "r4", &reporters),
        &[],
    );
    let want = labelled as u64 + rounds.len() as u64;
    let mut states = Vec::new();
    for s in [&f2, &f3, &fresh] {
        let t = Instant::now();
        let st = loop {
            let st = s.state();
            if st["state_seq"].as_u64() == Some(want) || t.elapsed() > Duration::from_secs(10) {
                break st;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        assert_eq!(st["state_seq"].as_u64(), Some(want), "{st}");
        states.push(st);
    }
    for key in [
        "reputations",
        "labelled_rounds",
        "threshold",
        "reporters",
        "rounds",
    ] {
        assert_eq!(
            states[0][key], states[2][key],
            "{key}: the live engine differs from a full replay"
        );
        assert_eq!(
            states[1][key], states[2][key],
            "{key}: a follower differs from a full replay"
        );
    }
}

/// A partition that drops packets (no reset, no close: the writer's database connection goes
/// silent through a relay that stops moving bytes): the server ends the silent session within the
/// lease timeout, a follower takes over, and the old writer, blocked in its round trip, gives up
/// within the same timeout and exits.
#[test]
fn a_silent_partition_hands_the_lease_over_within_its_timeout() {
    let tmp = tempfile::tempdir().unwrap();
    let (all, _) = rounds(tmp.path());
    let rounds = &all[..30];
    let reporters = sorted_reporters(rounds).join(",");
    let db = pg();
    let url = db.create_db("partition").unwrap();
    let relay = vlmfuse_testkit::netcut::Relay::start(&format!("127.0.0.1:{}", db.port())).unwrap();
    let via = format!(
        "postgres://{}@127.0.0.1:{}/partition",
        vlmfuse_testkit::pg::USER,
        relay.port()
    );
    let mut first = Server::start(
        &tmp.path().join("r1"),
        &follower(&via, "r1", &reporters),
        &[],
    );
    let second = Server::start(
        &tmp.path().join("r2"),
        &follower(&url, "r2", &reporters),
        &[],
    );
    let mut prog = Progress::default();
    for k in 0..15 {
        let addr = if k % 2 == 0 {
            &first.addr
        } else {
            &second.addr
        };
        let t = Instant::now();
        while !replay(addr, &rounds[..k + 1], &mut prog) {
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "round {k} not served"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    relay.cut();
    let cut_at = Instant::now();
    let took_over = loop {
        let role = second.get("/readyz").json()["components"]["store"]["role"].clone();
        if role == "writer" {
            break cut_at.elapsed();
        }
        assert!(
            cut_at.elapsed() < Duration::from_secs(20),
            "no takeover after the partition"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let status = loop {
        if let Some(s) = first.child.try_wait().unwrap() {
            break s;
        }
        assert!(
            cut_at.elapsed() < Duration::from_secs(20),
            "the partitioned writer kept running"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let exited = cut_at.elapsed();
    eprintln!(
        "silent partition: the follower wrote {:.2} s after the cut, the old writer exited ({:?}) after {:.2} s",
        took_over.as_secs_f64(),
        status.code(),
        exited.as_secs_f64()
    );
    assert_eq!(status.code(), Some(75));
    // Lease timeout 3 s: the server ends the silent session in about that, the follower asks
    // every 0.5 s.
    assert!(took_over < Duration::from_secs(8), "{took_over:?}");
    first.kill9();
    assert!(replay(&second.addr, rounds, &mut prog));
    let st = second.state();
    assert_eq!(st["rounds"].as_u64(), Some(30));
}
