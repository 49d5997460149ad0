use super::*;
use vlmfuse_fusion::{FusionConfig, Ontology, RoundRecord};

fn engine() -> Engine {
    engine_with(vlmfuse_fusion::Method::Paper)
}

fn engine_with(method: vlmfuse_fusion::Method) -> Engine {
    engine_cfg(FusionConfig {
        method,
        ..FusionConfig::default()
    })
}

fn engine_cfg(cfg: FusionConfig) -> Engine {
    Engine::new(
        cfg,
        Ontology::paper(),
        vec!["a".into(), "b".into(), "c".into()],
    )
    .unwrap()
}

fn identity(e: &Engine) -> Identity {
    Identity {
        reporters: e.reporters().to_vec(),
        labels: e.ontology().labels().iter().map(|l| l.id.clone()).collect(),
    }
}

/// A deterministic stream of rounds: small LCG, 8-d contexts, reports that mostly agree.
fn record(i: u64) -> RoundRecord {
    let mut s = i
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 33) as f64 / (1u64 << 31) as f64
    };
    let context: Vec<f64> = (0..8).map(|_| next() - 0.3).collect();
    let labels = Ontology::paper();
    let truth: Vec<String> = (0..14)
        .filter(|_| next() < 0.2)
        .map(|k| labels.id(k).to_string())
        .collect();
    let mut reports = std::collections::BTreeMap::new();
    for name in ["a", "b", "c"] {
        if next() < 0.1 {
            continue;
        }
        let mut r: Vec<String> = truth.iter().filter(|_| next() < 0.8).cloned().collect();
        if next() < 0.3 {
            r.push("brake".into());
        }
        reports.insert(name.to_string(), r);
    }
    if reports.is_empty() {
        reports.insert("a".into(), vec![]);
    }
    RoundRecord {
        id: None,
        context,
        reports,
        truth: Some(truth),
    }
}

/// Plays rounds against an engine and a store like the service does: infer, store, then
/// credit, commit, apply.
fn play(engine: &mut Engine, store: &mut Store, from: u64, to: u64) {
    for i in from..to {
        let rec = record(i);
        let (round, truth) = engine.parse(&rec).unwrap();
        if engine.dim().is_none() {
            engine.fix_dim(round.context.len()).unwrap();
        }
        let inf = engine.infer(&round);
        store
            .insert_rounds(
                i,
                &[NewRound {
                    round: round.clone(),
                    inference: inf.clone(),
                    request: serde_json::json!({}),
                    created_ms: 0,
                    thumbnails: Vec::new(),
                }],
            )
            .unwrap();
        engine.observe(i, &round, &inf).unwrap();
        if i % 5 == 4 {
            continue; // an unlabelled round
        }
        let stored = store.round(i).unwrap().unwrap();
        // Exactly, but for the adaptive scan, which is an in-memory cache and not stored.
        let mut want = inf.clone();
        want.scan = None;
        assert_eq!(stored.inference, want, "the inference round-trips exactly");
        let truth = truth.unwrap();
        let outcome = engine.credit(
            &stored.inference.signals,
            &stored.inference.w_used,
            &truth,
            i,
        );
        let fb = StoredFeedback {
            seq: i,
            labelled_order: engine.labelled(),
            rounds_before: i + 1,
            truth: truth.clone(),
            outcome: outcome.clone(),
            source: "human".into(),
        };
        store.insert_feedback(std::slice::from_ref(&fb)).unwrap();
        assert_eq!(store.feedback(i).unwrap(), vec![fb.clone()]);
        engine
            .apply(
                &LabelledRound {
                    seq: i,
                    round,
                    truth,
                    q: inf.q,
                },
                Some(&outcome),
            )
            .unwrap();
    }
}

#[test]
fn a_rebuilt_engine_continues_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine();
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&live)).unwrap();
    play(&mut live, &mut store, 0, 120);
    drop(store);

    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&live)).unwrap();
    let mut rebuilt = engine();
    let rep = store.load_engine(&mut rebuilt).unwrap();
    assert_eq!(rep.rounds, 120);
    assert_eq!(rep.labelled, 96);
    assert_eq!(rep.next_seq, 120);
    assert_eq!(rebuilt.reputations(), live.reputations());
    assert_eq!(rebuilt.stats(), live.stats());
    assert_eq!(
        rebuilt.threshold().thresholds(),
        live.threshold().thresholds()
    );
    assert_eq!(rebuilt.dim(), Some(8));
    // Both continue: same posteriors and reputations.
    let mut store2 = store;
    play(&mut rebuilt, &mut store2, 120, 150);
    let dir2 = tempfile::tempdir().unwrap();
    let mut scratch = Store::open(dir2.path()).unwrap();
    // `live` continues against a scratch store holding the same history.
    let mut live2 = engine();
    play(&mut live2, &mut scratch, 0, 150);
    assert_eq!(rebuilt.reputations(), live2.reputations());
    let probe = live2.parse(&record(999)).unwrap().0;
    assert_eq!(rebuilt.infer(&probe), live2.infer(&probe));
}

#[test]
fn another_configuration_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let e = engine();
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&e)).unwrap();
    drop(store);
    let mut store = Store::open(dir.path()).unwrap();
    let mut other = identity(&e);
    other.reporters.reverse();
    let err = store.check_identity(&other).unwrap_err();
    assert!(matches!(err, StoreError::Mismatch(_)), "{err}");
}

#[test]
fn a_tampered_state_is_detected() {
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine();
    let mut store = Store::open(dir.path()).unwrap();
    play(&mut live, &mut store, 0, 10);
    store
        .db
        .exec("UPDATE state SET reputations = '[0.5, 0.25, 0.25]'", &[])
        .unwrap();
    let err = store.load_engine(&mut engine()).unwrap_err();
    assert!(matches!(err, StoreError::Corrupt(_)), "{err}");
}

#[test]
fn another_dimension_is_refused_in_the_transaction() {
    let dir = tempfile::tempdir().unwrap();
    let mut e = engine();
    let mut store = Store::open(dir.path()).unwrap();
    play(&mut e, &mut store, 0, 1);
    let mut rec = record(1);
    rec.context.push(1.0);
    let (round, _) = engine().parse(&rec).unwrap();
    let inf = engine().infer(&round);
    let err = store
        .insert_rounds(
            1,
            &[NewRound {
                round,
                inference: inf,
                request: serde_json::Value::Null,
                created_ms: 0,
                thumbnails: Vec::new(),
            }],
        )
        .unwrap_err();
    assert!(matches!(err, StoreError::Mismatch(_)));
    assert_eq!(store.counts().unwrap(), (1, 1));
}

#[test]
fn round_ids_are_canonical() {
    assert_eq!(round_id(42), "r-00000042");
    assert_eq!(parse_round_id("r-00000042"), Some(42));
    assert_eq!(parse_round_id("r-42"), None);
    assert_eq!(parse_round_id("r-+0000042"), None);
    assert_eq!(parse_round_id("x-00000042"), None);
    assert_eq!(parse_round_id("r-123456789"), Some(123_456_789));
}

/// Under `adaptive` the unlabelled rounds are state too: a restart replays rounds and feedback
/// in the writer's order and continues exactly.
#[test]
fn an_adaptive_engine_is_rebuilt_from_rounds_and_feedback_in_event_order() {
    use vlmfuse_fusion::Method::Adaptive;
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine_with(Adaptive);
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&live)).unwrap();
    // As the service does on every start, also the first: this records the method.
    store.load_engine(&mut live).unwrap();
    play(&mut live, &mut store, 0, 120);
    drop(store);
    let mut store = Store::open(dir.path()).unwrap();
    let mut rebuilt = engine_with(Adaptive);
    let rep = store.load_engine(&mut rebuilt).unwrap();
    assert_eq!(
        (rep.rounds, rep.labelled, rep.migrated_from),
        (120, 96, None)
    );
    assert_eq!(store.method().unwrap().as_deref(), Some("adaptive"));
    assert_eq!(rebuilt.reputations(), live.reputations());
    let probe = live.parse(&record(999)).unwrap().0;
    assert_eq!(rebuilt.infer(&probe).q, live.infer(&probe).q);
    play(&mut rebuilt, &mut store, 120, 150);
    let scratch = tempfile::tempdir().unwrap();
    let mut live2 = engine_with(Adaptive);
    play(
        &mut live2,
        &mut Store::open(scratch.path()).unwrap(),
        0,
        150,
    );
    assert_eq!(rebuilt.reputations(), live2.reputations());
    assert_eq!(rebuilt.infer(&probe).q, live2.infer(&probe).q);
}

/// A data directory written under `paper` replays under `adaptive` (the rounds are the state):
/// the result is the engine that would have run `adaptive` from the start, the outcomes are
/// rewritten, and the next start under `adaptive` applies them without recomputing.
#[test]
fn a_data_directory_replays_under_the_other_method() {
    use vlmfuse_fusion::Method::{Adaptive, Paper};
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path()).unwrap();
    play(&mut engine_with(Paper), &mut store, 0, 80);
    drop(store);

    let mut store = Store::open(dir.path()).unwrap();
    assert_eq!(store.method().unwrap().as_deref(), Some("paper"));
    let mut migrated = engine_with(Adaptive);
    let rep = store.load_engine(&mut migrated).unwrap();
    assert_eq!(rep.migrated_from.as_deref(), Some("paper"));
    assert_eq!(rep.labelled, 64);
    let scratch = tempfile::tempdir().unwrap();
    let mut native = engine_with(Adaptive);
    play(
        &mut native,
        &mut Store::open(scratch.path()).unwrap(),
        0,
        80,
    );
    assert_eq!(migrated.reputations(), native.reputations());
    let probe = native.parse(&record(999)).unwrap().0;
    assert_eq!(migrated.infer(&probe).q, native.infer(&probe).q);
    drop(store);

    let mut store = Store::open(dir.path()).unwrap();
    assert_eq!(store.method().unwrap().as_deref(), Some("adaptive"));
    let mut again = engine_with(Adaptive);
    let rep = store.load_engine(&mut again).unwrap();
    assert_eq!(rep.migrated_from, None);
    assert_eq!(again.reputations(), native.reputations());
    drop(store);

    // And back: under `paper` it is the paper method's engine again.
    let mut store = Store::open(dir.path()).unwrap();
    let mut back = engine_with(Paper);
    let rep = store.load_engine(&mut back).unwrap();
    assert_eq!(rep.migrated_from.as_deref(), Some("adaptive"));
    let mut paper = engine_with(Paper);
    play(
        &mut paper,
        &mut Store::open(tempfile::tempdir().unwrap().path()).unwrap(),
        0,
        80,
    );
    assert_eq!(back.reputations(), paper.reputations());
}

/// An idempotency key commits with its rounds, survives a reopen, expires by age and is pruned.
#[test]
fn idempotency_keys_commit_with_their_rounds_and_expire() {
    let dir = tempfile::tempdir().unwrap();
    let mut engine = engine();
    let rec = record(0);
    let (round, _) = engine.parse(&rec).unwrap();
    engine.fix_dim(round.context.len()).unwrap();
    let inf = engine.infer(&round);
    let new = NewRound {
        round,
        inference: inf,
        request: serde_json::json!({}),
        created_ms: 0,
        thumbnails: Vec::new(),
    };
    let key = IdempotencyRecord {
        key: "k-1".into(),
        route: "/v1/fuse".into(),
        fingerprint: "abc".into(),
        response: serde_json::json!({"round_id": "r-00000000"}),
        created_ms: 1_000,
    };
    {
        let mut store = Store::open(dir.path()).unwrap();
        store
            .insert_rounds_keyed(0, std::slice::from_ref(&new), std::slice::from_ref(&key))
            .unwrap();
    }
    let mut store = Store::open(dir.path()).unwrap();
    assert_eq!(store.idempotency("k-1", 0).unwrap(), Some(key.clone()));
    assert_eq!(store.idempotency("k-2", 0).unwrap(), None);
    assert_eq!(
        store.idempotency("k-1", 1_001).unwrap(),
        None,
        "expired by age"
    );
    assert_eq!(store.prune_idempotency(999).unwrap(), 0);
    assert_eq!(store.prune_idempotency(1_001).unwrap(), 1);
    assert_eq!(store.idempotency_keys().unwrap(), 0);
    // A failed transaction stores neither the rounds nor the key: seq 0 exists already.
    let err = store.insert_rounds_keyed(0, std::slice::from_ref(&new), std::slice::from_ref(&key));
    assert!(err.is_err());
    assert_eq!(store.idempotency_keys().unwrap(), 0);
}

/// One writer per data directory: a second open, here in the same process, is refused while
/// the first lives and names the directory and the holder; the lock goes with the store.
#[test]
fn a_second_open_of_a_data_directory_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut first = Store::open(dir.path()).unwrap();
    play(&mut engine(), &mut first, 0, 3);
    let err = match Store::open(dir.path()) {
        Err(e) => e,
        Ok(_) => panic!("a second store opened the data directory"),
    };
    let me = std::process::id();
    match &err {
        StoreError::Locked { dir: d, pid } => {
            assert_eq!(d, dir.path());
            assert_eq!(*pid, Some(me));
        }
        other => panic!("{other:?}"),
    }
    let msg = err.to_string();
    assert!(msg.contains(&dir.path().display().to_string()), "{msg}");
    assert!(msg.contains(&format!("pid {me}")), "{msg}");
    // Waiting does not help while the holder lives, and costs about the wait.
    let t = std::time::Instant::now();
    assert!(matches!(
        Store::open_waiting(dir.path(), Duration::from_millis(200)),
        Err(StoreError::Locked { .. })
    ));
    assert!(t.elapsed() >= Duration::from_millis(200));
    // Readers need no lock.
    let reader = Store::open_read_only(dir.path()).unwrap();
    assert_eq!(reader.counts().unwrap(), (3, 3));
    drop(first);
    let mut again = Store::open(dir.path()).unwrap();
    assert_eq!(again.counts().unwrap(), (3, 3));
    assert_eq!(again.prune_idempotency(0).unwrap(), 0);
}

/// Where [`lock_holder`] holds its lock, when this test binary runs as that child.
const HOLDER_ENV: &str = "VLMFUSE_STORE_LOCK_HOLDER_DIR";

/// Not a test of its own: the child process of
/// [`a_lock_held_by_another_process_is_refused_and_dies_with_it`], which opens the store in
/// the directory it is given, says so, and holds it until it is killed. Without the variable
/// it returns at once.
#[test]
fn lock_holder() {
    let Ok(dir) = std::env::var(HOLDER_ENV) else {
        return;
    };
    let _store = Store::open(Path::new(&dir)).unwrap();
    println!("HOLDING {}", std::process::id());
    std::io::stdout().flush().unwrap();
    loop {
        std::thread::sleep(Duration::from_secs(60));
    }
}

#[test]
fn a_lock_held_by_another_process_is_refused_and_dies_with_it() {
    use std::io::BufRead;
    use std::process::{Command, Stdio};

    struct KillOnDrop(std::process::Child);
    impl Drop for KillOnDrop {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    let dir = tempfile::tempdir().unwrap();
    let mut child = KillOnDrop(
        Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "tests::lock_holder", "--nocapture"])
            .env(HOLDER_ENV, dir.path())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let child_pid = child.0.id();
    let mut lines = std::io::BufReader::new(child.0.stdout.take().unwrap()).lines();
    let holding = lines
        .by_ref()
        .map_while(Result::ok)
        .find(|l| l.starts_with("HOLDING"))
        .expect("the child took the lock");
    assert_eq!(holding, format!("HOLDING {child_pid}"));

    match Store::open(dir.path()) {
        Err(StoreError::Locked { dir: d, pid }) => {
            assert_eq!(d, dir.path());
            assert_eq!(pid, Some(child_pid));
        }
        Err(other) => panic!("{other:?}"),
        Ok(_) => panic!("opened a data directory another process holds"),
    }
    // `kill -9`: the kernel releases the lock with the process; nothing stale is left.
    child.0.kill().unwrap();
    child.0.wait().unwrap();
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.counts().unwrap(), (0, 0));
    let pid = std::fs::read_to_string(dir.path().join(LOCK_FILE)).unwrap();
    assert_eq!(pid.trim(), std::process::id().to_string());
}

/// Rounds that only the write-ahead log held, behind a damaged log header: SQLite opens the
/// database without them and says nothing, so the open reports the counts it found.
#[test]
fn a_damaged_write_ahead_log_is_reported_at_open() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path()).unwrap();
    play(&mut engine(), &mut store, 0, 10);
    let db = dir.path().join(DB_FILE);
    let wal = wal_path(&db);
    // A copy of the files as a `kill -9` leaves them: the rounds are in the log only.
    let copy = |damage: bool| {
        let to = tempfile::tempdir().unwrap();
        std::fs::copy(&db, to.path().join(DB_FILE)).unwrap();
        let mut log = std::fs::read(&wal).unwrap();
        assert!(log.len() > 32, "the rounds are in the log");
        if damage {
            // The header's checksum: the whole log is then ignored.
            for b in &mut log[24..32] {
                *b ^= 0xff;
            }
        }
        std::fs::write(wal_path(&to.path().join(DB_FILE)), &log).unwrap();
        to
    };
    let intact = copy(false);
    let damaged = copy(true);
    drop(store);

    let s = Store::open(intact.path()).unwrap();
    assert_eq!(s.counts().unwrap(), (10, 8));
    assert_eq!(s.damaged_wal, None);

    let s = Store::open(damaged.path()).unwrap();
    assert_eq!(s.counts().unwrap(), (0, 0));
    let w = s.damaged_wal.clone().expect("reported");
    assert_eq!((w.frames_recovered, w.rounds, w.feedback), (0, 0, 0));
    assert!(w.wal_bytes > 32 && w.frames_in_file > 0, "{w:?}");

    // A clean close leaves no log, and nothing to report.
    drop(s);
    let s = Store::open(dir.path()).unwrap();
    assert_eq!(s.damaged_wal, None);

    // Killed before its first round: a log of the schema alone, all recovered, is no damage.
    let fresh = tempfile::tempdir().unwrap();
    let held = Store::open(fresh.path()).unwrap();
    let to = tempfile::tempdir().unwrap();
    let fresh_db = fresh.path().join(DB_FILE);
    std::fs::copy(&fresh_db, to.path().join(DB_FILE)).unwrap();
    std::fs::copy(wal_path(&fresh_db), wal_path(&to.path().join(DB_FILE))).unwrap();
    drop(held);
    let s = Store::open(to.path()).unwrap();
    assert_eq!(s.counts().unwrap(), (0, 0));
    assert_eq!(s.damaged_wal, None);
}

/// A file that is not a database (or one SQLite cannot write) is refused with its path: a bare
/// "file is not a database" does not say which file.
#[test]
fn an_unusable_database_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(DB_FILE), vec![b'x'; 4096]).unwrap();
    let e = match Store::open(dir.path()) {
        Ok(_) => panic!("a garbage database opened"),
        Err(e) => e,
    };
    assert!(matches!(e, StoreError::Open { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(
        msg.contains(DB_FILE) && msg.contains("not a database"),
        "{msg}"
    );
}

/// The engine as bytes: equal bytes are the same engine, every float by its bits.
fn bytes(e: &Engine) -> Vec<u8> {
    postcard::to_allocvec(e).unwrap()
}

/// A data directory with `upto` rounds played and a snapshot taken after `at` of them.
fn with_snapshot(
    method: vlmfuse_fusion::Method,
    at: u64,
    upto: u64,
) -> (tempfile::TempDir, Engine) {
    with_snapshot_cfg(
        FusionConfig {
            method,
            ..FusionConfig::default()
        },
        at,
        upto,
    )
}

fn with_snapshot_cfg(cfg: FusionConfig, at: u64, upto: u64) -> (tempfile::TempDir, Engine) {
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine_cfg(cfg);
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&live)).unwrap();
    store.load_engine(&mut live).unwrap();
    play(&mut live, &mut store, 0, at);
    let anchor = store.anchor().unwrap();
    assert_eq!((anchor.rounds, anchor.labelled), (at, live.labelled()));
    snapshot::write(&snapshot::dir_of(dir.path()), &live, &anchor, 2).unwrap();
    play(&mut live, &mut store, at, upto);
    (dir, live)
}

/// Loads the directory twice, from its snapshot and by the full replay.
fn load_both(dir: &Path, method: vlmfuse_fusion::Method) -> (Engine, LoadReport, Engine) {
    load_both_cfg(
        dir,
        FusionConfig {
            method,
            ..FusionConfig::default()
        },
    )
}

fn load_both_cfg(dir: &Path, cfg: FusionConfig) -> (Engine, LoadReport, Engine) {
    let mut store = Store::open(dir).unwrap();
    let mut snap = engine_cfg(cfg.clone());
    let rep = store.load_engine(&mut snap).unwrap();
    let mut full = engine_cfg(cfg);
    let full_rep = store.load_engine_full(&mut full).unwrap();
    assert!(full_rep.snapshot.is_none());
    assert_eq!(
        (rep.rounds, rep.labelled),
        (full_rep.rounds, full_rep.labelled)
    );
    (snap, rep, full)
}

#[test]
fn a_snapshot_plus_its_tail_is_the_full_replay_bit_for_bit() {
    use vlmfuse_fusion::Method::{Adaptive, Paper};
    for method in [Paper, Adaptive] {
        let (dir, live) = with_snapshot(method, 80, 130);
        let (snap, rep, full) = load_both(dir.path(), method);
        let used = rep.snapshot.as_ref().expect("the snapshot is used");
        assert_eq!((used.anchor.rounds, used.anchor.labelled), (80, 64));
        // Under `paper` only feedback is state; under `adaptive` every round after it is too.
        let tail_rounds = if method == Paper { 0 } else { 50 };
        assert_eq!((used.tail_rounds, used.tail_feedback), (tail_rounds, 40));
        assert!(rep.skipped_snapshots.is_empty());
        assert_eq!(
            bytes(&snap),
            bytes(&full),
            "{method:?}: snapshot + tail != full replay"
        );
        assert_eq!(
            bytes(&snap),
            bytes(&live),
            "{method:?}: != the engine that lived it"
        );
        // And both go on alike.
        let probe = live.parse(&record(999)).unwrap().0;
        assert_eq!(snap.infer(&probe), full.infer(&probe));
    }
}

/// With the bounded pool evicting before and after the snapshot (`pool_max` far below the
/// unlabelled rounds played), snapshot + tail is still the full replay, bit for bit.
#[test]
fn a_bounded_pool_snapshot_plus_its_tail_is_the_full_replay_bit_for_bit() {
    let cfg = FusionConfig {
        method: vlmfuse_fusion::Method::Adaptive,
        adaptive: vlmfuse_fusion::AdaptiveConfig {
            pool_max: 6,
            ..Default::default()
        },
        ..FusionConfig::default()
    };
    let (dir, live) = with_snapshot_cfg(cfg.clone(), 80, 160);
    let (_, unlabelled) = live.pool_sizes().unwrap();
    assert!(unlabelled <= 7, "{unlabelled} unlabelled entries kept");
    let (snap, rep, full) = load_both_cfg(dir.path(), cfg);
    assert!(rep.snapshot.is_some(), "the snapshot is used");
    assert_eq!(bytes(&snap), bytes(&full), "snapshot + tail != full replay");
    assert_eq!(bytes(&snap), bytes(&live), "!= the engine that lived it");
}

/// With the approximate kNN index in use before the snapshot (and, in the second setting, fixed
/// during the tail), with evictions on both sides: snapshot + tail is the full replay, bit for
/// bit, and both search alike afterwards.
#[test]
fn an_approximate_index_snapshot_plus_its_tail_is_the_full_replay_bit_for_bit() {
    for ann_min in [20, 100] {
        let cfg = FusionConfig {
            method: vlmfuse_fusion::Method::Adaptive,
            adaptive: vlmfuse_fusion::AdaptiveConfig {
                pool_max: 40,
                ann_min,
                ann_cells: 6,
                ann_probe: 2,
                ann_ef: 60,
                ..Default::default()
            },
            ..FusionConfig::default()
        };
        let (dir, live) = with_snapshot_cfg(cfg.clone(), 80, 170);
        let probes: Vec<Vec<f64>> = (900..920)
            .map(|i| live.parse(&record(i)).unwrap().0.context)
            .collect();
        let (active, _) = live.neighbour_recall(&probes).unwrap();
        assert!(active, "ann_min {ann_min}: the approximate index is in use");
        let (snap, rep, full) = load_both_cfg(dir.path(), cfg);
        assert!(rep.snapshot.is_some(), "the snapshot is used");
        assert_eq!(
            bytes(&snap),
            bytes(&full),
            "ann_min {ann_min}: snapshot + tail != full replay"
        );
        assert_eq!(
            bytes(&snap),
            bytes(&live),
            "ann_min {ann_min}: != the engine that lived it"
        );
        let probe = live.parse(&record(999)).unwrap().0;
        assert_eq!(snap.infer(&probe), full.infer(&probe));
        assert_eq!(snap.infer(&probe), live.infer(&probe));
    }
}

#[test]
fn a_snapshot_of_the_whole_history_leaves_no_tail() {
    let (dir, live) = with_snapshot(vlmfuse_fusion::Method::Adaptive, 60, 60);
    let (snap, rep, full) = load_both(dir.path(), vlmfuse_fusion::Method::Adaptive);
    let used = rep.snapshot.unwrap();
    assert_eq!((used.tail_rounds, used.tail_feedback), (0, 0));
    assert_eq!(bytes(&snap), bytes(&full));
    assert_eq!(bytes(&snap), bytes(&live));
}

/// Each way a snapshot can be wrong is caught before it is used, and the start falls back to
/// the full replay: the engine is the same either way.
#[test]
fn an_unusable_snapshot_is_skipped_with_its_reason() {
    use vlmfuse_fusion::Method::{Adaptive, Paper};
    type Spoil = fn(&Path, &Path);
    let cases: [(&str, Spoil); 6] = [
        ("checksum", |p, _| {
            let mut b = std::fs::read(p).unwrap();
            let mid = b.len() / 2;
            b[mid] ^= 0x40;
            std::fs::write(p, b).unwrap();
        }),
        ("bad magic or too short", |p, _| {
            std::fs::write(p, b"VLMF").unwrap();
        }),
        ("checksum", |p, _| {
            let b = std::fs::read(p).unwrap();
            std::fs::write(p, &b[..b.len() - 9]).unwrap();
        }),
        ("method", |p, dir| {
            // A paper engine's snapshot at the same point of an identical history.
            std::fs::remove_file(p).unwrap();
            file_as_snapshot(dir, engine_with(Paper), 0, 80);
        }),
        ("configuration", |p, dir| {
            let e = Engine::new(
                FusionConfig {
                    method: Adaptive,
                    eta: 0.3,
                    ..FusionConfig::default()
                },
                Ontology::paper(),
                vec!["a".into(), "b".into(), "c".into()],
            )
            .unwrap();
            std::fs::remove_file(p).unwrap();
            file_as_snapshot(dir, e, 0, 80);
        }),
        ("another history", |_, dir| {
            let c = Connection::open(dir.join(DB_FILE)).unwrap();
            c.execute("UPDATE rounds SET created_ms = 7 WHERE seq = 79", [])
                .unwrap();
        }),
    ];
    for (want, spoil) in cases {
        let (dir, live) = with_snapshot(Adaptive, 80, 100);
        let snap_dir = snapshot::dir_of(dir.path());
        let path = snapshot::list(&snap_dir).remove(0);
        spoil(&path, dir.path());
        let (snap, rep, full) = load_both(dir.path(), Adaptive);
        assert!(rep.snapshot.is_none(), "{want}: a spoilt snapshot was used");
        let reasons: Vec<&String> = rep.skipped_snapshots.iter().map(|(_, w)| w).collect();
        assert!(
            reasons.iter().any(|w| w.contains(want)),
            "{want}: skipped for {reasons:?}"
        );
        assert_eq!(bytes(&snap), bytes(&full));
        assert_eq!(bytes(&snap), bytes(&live));
    }
}

/// Where `play`'s history in `dir` stands after 80 rounds (`play` labels every round but each
/// fifth and stamps rounds `created_ms = 0`, so only the feedback's time is `dir`'s own).
fn at_80(dir: &Path) -> snapshot::Anchor {
    let store = Store::open_read_only(dir).unwrap();
    let ms: i64 = store
        .db
        .query_one(
            "SELECT created_ms FROM feedback WHERE labelled_order = 63",
            &[],
        )
        .and_then(|r| r.i64(0))
        .unwrap();
    snapshot::Anchor {
        rounds: 80,
        labelled: 64,
        last_round: Some((79, 0)),
        last_feedback: Some((78, ms)),
    }
}

/// Plays `from..to` into `e` against a scratch store and files it as `dir`'s snapshot after
/// 80 rounds.
fn file_as_snapshot(dir: &Path, mut e: Engine, from: u64, to: u64) {
    let scratch = tempfile::tempdir().unwrap();
    play(&mut e, &mut Store::open(scratch.path()).unwrap(), from, to);
    let a = at_80(dir);
    assert_eq!(e.labelled(), a.labelled);
    snapshot::write(&snapshot::dir_of(dir), &e, &a, 2).unwrap();
}

/// A snapshot that passes every check but holds another engine (here: one that lived other
/// rounds) disagrees with the stored state row: it is dropped for the full replay. (The state
/// row holds the reputations after the last feedback, which a replayed stored outcome restores
/// exactly, so the check bites when the snapshot is the last word on them: no feedback after it.)
#[test]
fn a_snapshot_that_leads_elsewhere_falls_back_to_the_full_replay() {
    use vlmfuse_fusion::Method::Adaptive;
    let (dir, live) = with_snapshot(Adaptive, 80, 80);
    let real = snapshot::list(&snapshot::dir_of(dir.path())).remove(0);
    assert_eq!(snapshot::read(&real).unwrap().0.anchor, at_80(dir.path()));
    std::fs::remove_file(&real).unwrap();
    file_as_snapshot(dir.path(), engine_with(Adaptive), 1000, 1080);
    let (snap, rep, full) = load_both(dir.path(), Adaptive);
    assert!(rep.snapshot.is_none(), "the wrong engine was used");
    assert!(
        rep.skipped_snapshots
            .iter()
            .any(|(_, w)| w.contains("do not lead to the stored state")),
        "{:?}",
        rep.skipped_snapshots
    );
    assert_eq!(bytes(&snap), bytes(&full));
    assert_eq!(bytes(&snap), bytes(&live));
}

#[test]
fn snapshots_are_kept_newest_first_and_pruned() {
    use vlmfuse_fusion::Method::Paper;
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine_with(Paper);
    let mut store = Store::open(dir.path()).unwrap();
    let sd = snapshot::dir_of(dir.path());
    for k in 1..=4u64 {
        play(&mut live, &mut store, (k - 1) * 10, k * 10);
        snapshot::write(&sd, &live, &store.anchor().unwrap(), 2).unwrap();
    }
    std::fs::write(sd.join(".tmp-1-snapshot-x.bin"), b"torn").unwrap();
    let left: Vec<String> = snapshot::list(&sd)
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        left,
        [
            "snapshot-000000000032-000000000040.bin",
            "snapshot-000000000024-000000000030.bin"
        ]
    );
    drop(store);
    let rep = Store::open(dir.path())
        .unwrap()
        .load_engine(&mut engine_with(Paper))
        .unwrap();
    assert_eq!(rep.snapshot.unwrap().anchor.rounds, 40);
    assert!(
        !sd.join(".tmp-1-snapshot-x.bin").exists(),
        "a torn write is removed"
    );
}

/// A schema-1 database (one feedback per round, keyed by `seq`) opens as schema 2 with every
/// feedback kept (as a person's), and rebuilds the same engine.
#[test]
fn a_schema_1_database_is_upgraded_in_place() {
    let dir = tempfile::tempdir().unwrap();
    let mut live = engine();
    let mut store = Store::open(dir.path()).unwrap();
    store.check_identity(&identity(&live)).unwrap();
    play(&mut live, &mut store, 0, 40);
    // Turn it back into what schema 1 wrote.
    store
        .db
        .batch(
            "BEGIN;
             CREATE TABLE feedback_v1 (
                 seq            INTEGER PRIMARY KEY REFERENCES rounds(seq),
                 labelled_order INTEGER NOT NULL UNIQUE,
                 rounds_before  INTEGER,
                 created_ms     INTEGER NOT NULL,
                 truth          BLOB NOT NULL,
                 outcome        TEXT NOT NULL
             );
             INSERT INTO feedback_v1 SELECT seq, labelled_order, rounds_before, created_ms,
                                            truth, outcome FROM feedback;
             DROP TABLE feedback;
             ALTER TABLE feedback_v1 RENAME TO feedback;
             UPDATE meta SET value = '1' WHERE key = 'schema_version';
             COMMIT;",
        )
        .unwrap();
    drop(store);
    let mut store = Store::open(dir.path()).unwrap();
    let v: String = store
        .db
        .query_one("SELECT value FROM meta WHERE key = 'schema_version'", &[])
        .and_then(|r| r.string(0))
        .unwrap();
    assert_eq!(v, "2");
    let fb = store.feedback(3).unwrap();
    assert_eq!(fb.len(), 1);
    assert_eq!(fb[0].source, "human");
    let mut rebuilt = engine();
    let rep = store.load_engine_full(&mut rebuilt).unwrap();
    assert_eq!(rep.labelled, 32);
    assert_eq!(rebuilt.reputations(), live.reputations());
    // And it takes a second feedback on a round now.
    let mut second = fb[0].clone();
    second.labelled_order = 32;
    second.truth = vec![vlmfuse_fusion::UNKNOWN; 14];
    second.truth[0] = 1;
    second.source = "kinematics".into();
    store.insert_feedback(&[second]).unwrap();
    assert_eq!(store.feedback(3).unwrap().len(), 2);
}

#[path = "pg_tests.rs"]
mod pg_tests;
