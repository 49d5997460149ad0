//! The store on a real PostgreSQL server (started per test on a loopback port): the same
//! engine as on SQLite, bit for bit, and the writer lease.

use super::*;
use vlmfuse_testkit::pg::PgServer;

fn server() -> PgServer {
    PgServer::start().unwrap_or_else(|e| panic!("PostgreSQL for the store tests: {e}"))
}

fn opts(url: &str, dir: &Path) -> pg::PgOptions {
    let mut o = pg::PgOptions::new(url, dir);
    o.lease_wait = Duration::ZERO;
    o
}

fn writer(url: &str, dir: &Path) -> Store {
    Store::open_at(&Location::Postgres(opts(url, dir)), Duration::ZERO).unwrap()
}

#[test]
fn a_postgres_store_rebuilds_what_sqlite_rebuilds_bit_for_bit() {
    use vlmfuse_fusion::Method::{Adaptive, Paper};
    let pg = server();
    for method in [Paper, Adaptive] {
        let url = pg.create_db(&format!("parity_{}", method.name())).unwrap();
        let (lite_dir, pg_tmp) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        // A replica's data directory need not exist yet.
        let pg_dir = pg_tmp.path().join("replica");
        let pg_dir = pg_dir.as_path();
        let (mut on_lite, mut on_pg) = (engine_with(method), engine_with(method));
        let mut lite = Store::open(lite_dir.path()).unwrap();
        let mut post = writer(&url, pg_dir);
        assert!(post.is_postgres() && post.alive());
        lite.check_identity(&identity(&on_lite)).unwrap();
        post.check_identity(&identity(&on_pg)).unwrap();
        // As a start does: the method is recorded with the (empty) load.
        lite.load_engine(&mut on_lite).unwrap();
        post.load_engine(&mut on_pg).unwrap();
        // A snapshot half-way on each side (each replica keeps its own, in its data directory).
        play(&mut on_lite, &mut lite, 0, 40);
        play(&mut on_pg, &mut post, 0, 40);
        let anchor = post.anchor().unwrap();
        assert_eq!(
            anchor,
            lite.anchor()
                .map(|mut a| {
                    // Feedback times are each store's own clock.
                    a.last_feedback = anchor.last_feedback;
                    a
                })
                .unwrap()
        );
        snapshot::write(&snapshot::dir_of(pg_dir), &on_pg, &anchor, 2).unwrap();
        play(&mut on_lite, &mut lite, 40, 90);
        play(&mut on_pg, &mut post, 40, 90);
        assert_eq!(
            bytes(&on_lite),
            bytes(&on_pg),
            "{method:?}: the live engines"
        );
        assert_eq!(post.counts().unwrap(), lite.counts().unwrap());
        for seq in [0, 17, 89] {
            let (a, b) = (
                lite.round(seq).unwrap().unwrap(),
                post.round(seq).unwrap().unwrap(),
            );
            assert_eq!((a.round, a.inference), (b.round, b.inference));
            let strip = |v: Vec<StoredFeedback>| {
                v.into_iter()
                    .map(|f| (f.truth, f.outcome))
                    .collect::<Vec<_>>()
            };
            assert_eq!(
                strip(lite.feedback(seq).unwrap()),
                strip(post.feedback(seq).unwrap())
            );
        }
        assert_eq!(
            lite.recent_rounds(None, 5)
                .unwrap()
                .iter()
                .map(|r| (r.seq, r.labelled))
                .collect::<Vec<_>>(),
            post.recent_rounds(None, 5)
                .unwrap()
                .iter()
                .map(|r| (r.seq, r.labelled))
                .collect::<Vec<_>>()
        );
        drop(post);

        // A restart on each: from the snapshot plus its tail, and by the full replay.
        let mut post = writer(&url, pg_dir);
        let (mut from_snap, mut full) = (engine_with(method), engine_with(method));
        let rep = post.load_engine(&mut from_snap).unwrap();
        assert!(
            rep.snapshot.is_some(),
            "{method:?}: the snapshot is used: {:?}",
            rep.skipped_snapshots
        );
        post.load_engine_full(&mut full).unwrap();
        let mut from_lite = engine_with(method);
        lite.load_engine_full(&mut from_lite).unwrap();
        for e in [&from_snap, &full] {
            assert_eq!(
                bytes(e),
                bytes(&from_lite),
                "{method:?}: rebuilt on PostgreSQL"
            );
        }
        let probe = on_lite.parse(&record(999)).unwrap().0;
        let (qa, qb) = (from_lite.infer(&probe).q, from_snap.infer(&probe).q);
        assert!(
            qa.iter().zip(&qb).all(|(a, b)| (a - b).abs() <= 1e-12),
            "{qa:?} {qb:?}"
        );

        // Idempotency keys and a roll-back behave alike.
        let key = IdempotencyRecord {
            key: "k1".into(),
            route: "/v1/fuse".into(),
            fingerprint: "f".into(),
            response: serde_json::json!({"round_id": "r-00000090"}),
            created_ms: 1_000,
        };
        let round = NewRound {
            round: probe.clone(),
            inference: from_snap.infer(&probe),
            request: serde_json::json!({"k": "v"}),
            created_ms: 5,
            thumbnails: vec![browse::Thumbnail {
                index: 0,
                t_s: 0.5,
                jpeg: vec![1, 2, 3],
            }],
        };
        let before = post.anchor().unwrap();
        post.insert_rounds_keyed(90, std::slice::from_ref(&round), std::slice::from_ref(&key))
            .unwrap();
        assert_eq!(post.idempotency("k1", 0).unwrap(), Some(key.clone()));
        assert_eq!(post.idempotency("k1", 2_000).unwrap(), None, "expired");
        assert_eq!(post.thumbnail(90, 0).unwrap(), Some(vec![1, 2, 3]));
        assert_eq!(post.thumbnail_index(90).unwrap(), vec![(0, 0.5)]);
        assert_eq!(
            post.round_request(90).unwrap(),
            Some(serde_json::json!({"k": "v"}))
        );
        // The same seq again is refused by the primary key, and nothing of it is kept.
        assert!(post
            .insert_rounds(90, std::slice::from_ref(&round))
            .is_err());
        assert_eq!(post.counts().unwrap().0, 91);
        post.roll_back_to(&before, from_snap.reputations()).unwrap();
        assert_eq!(post.counts().unwrap().0, 90);
        assert_eq!(post.prune_idempotency(2_000).unwrap(), 1);
        assert_eq!(post.idempotency_keys().unwrap(), 0);
    }
}

#[test]
fn the_lease_admits_one_writer_and_passes_when_its_session_ends() {
    let pg = server();
    let url = pg.create_db("lease").unwrap();
    let (d1, d2) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let mut live = engine();
    let mut first = writer(&url, d1.path());
    first.check_identity(&identity(&live)).unwrap();
    first.load_engine(&mut live).unwrap();
    play(&mut live, &mut first, 0, 20);

    // A second writer is refused while the first holds the lease, and the message names it.
    let mut o = opts(&url, d2.path());
    o.name = "replica-2".into();
    o.lease_wait = Duration::from_millis(300);
    let err = Store::open_at(&Location::Postgres(o.clone()), Duration::ZERO)
        .err()
        .expect("a second writer is refused");
    match &err {
        StoreError::Leased { holder, url: u } => {
            assert!(
                holder.contains(&format!(":{}", std::process::id())),
                "{holder}"
            );
            assert!(u.contains("/lease"), "{u}");
        }
        e => panic!("expected Leased, got {e}"),
    }
    // A reader is not a writer: it opens beside the first and cannot write.
    let reader = Store::open_read_only_at(&Location::Postgres(o.clone())).unwrap();
    assert_eq!(reader.counts().unwrap(), first.counts().unwrap());
    assert!(reader.db.exec("DELETE FROM idempotency", &[]).is_err());

    // The writer's session is cut (what a partition or a dead host comes to): the lease goes
    // with it, the old writer can no longer commit anything, and the standby takes over.
    let killed = pg
        .sql(
            "lease",
            "SELECT count(*) FROM (SELECT pg_terminate_backend(pid) FROM pg_stat_activity \
             WHERE application_name = 'vlmfuse-writer') t",
        )
        .unwrap();
    assert_eq!(killed, "1");
    o.lease_wait = Duration::from_secs(10);
    let t = Instant::now();
    let mut second = Store::open_at(&Location::Postgres(o), Duration::ZERO).unwrap();
    assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
    assert!(!first.alive());
    let (r, _) = second.counts().unwrap();
    let late = NewRound {
        round: live.parse(&record(20)).unwrap().0,
        inference: live.infer(&live.parse(&record(20)).unwrap().0),
        request: serde_json::json!({}),
        created_ms: 0,
        thumbnails: Vec::new(),
    };
    assert!(
        first.insert_rounds(r, std::slice::from_ref(&late)).is_err(),
        "fenced"
    );
    assert_eq!(
        second.counts().unwrap().0,
        r,
        "nothing of the old writer's landed"
    );
    let mut rebuilt = engine();
    second.check_identity(&identity(&live)).unwrap();
    second.load_engine(&mut rebuilt).unwrap();
    assert_eq!(bytes(&rebuilt), bytes(&live));
    second
        .insert_rounds(r, std::slice::from_ref(&late))
        .unwrap();
    let holder = pg.sql("lease", "SELECT holder FROM lease").unwrap();
    assert_eq!(holder, "replica-2");
}

#[test]
fn an_unreachable_server_is_named_without_its_password() {
    let dir = tempfile::tempdir().unwrap();
    // A port nothing listens on.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut o = pg::PgOptions::new(
        format!("postgres://vlm:hunter2@127.0.0.1:{port}/x"),
        dir.path(),
    );
    o.lease_timeout = Duration::from_secs(3);
    let err = Store::open_at(&Location::Postgres(o), Duration::ZERO)
        .err()
        .unwrap();
    let msg = err.to_string();
    assert!(matches!(err, StoreError::Connect { .. }), "{msg}");
    assert!(
        msg.contains(&format!("127.0.0.1:{port}")) && !msg.contains("hunter2"),
        "{msg}"
    );
}
