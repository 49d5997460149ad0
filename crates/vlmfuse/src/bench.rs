//! `vlmfuse bench`: the engine's speed, measured in one run so ratios compare like with like.
//! Numbers come from a release build (`cargo run --release -- bench`); a debug build is ~10x
//! slower and says nothing about production. The workloads and timed loops are the engine
//! crate's (`vlmfuse_fusion::bench`, also behind its criterion benches); this module prints.

use crate::eval::{self, EvalArgs};
use clap::Args;
use std::io::Write;
use std::time::Instant;
use vlmfuse_fusion::bench::{fuse_feedback, fuse_feedback_paired, knn, synthetic_records};
use vlmfuse_fusion::{FusionConfig, Method, Ontology};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Bank sizes for the fuse-then-feedback benchmark.
    #[arg(long, value_delimiter = ',', default_values_t = [1_000usize, 10_000, 100_000])]
    pub banks: Vec<usize>,
    /// Context dimension.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// Reporters per round.
    #[arg(long, default_value_t = 3)]
    pub reporters: usize,
    /// Timed rounds per bank size.
    #[arg(long, default_value_t = 300)]
    pub rounds: usize,
    /// Skip the eval end-to-end and batch-kNN parts.
    #[arg(long)]
    pub engine_only: bool,
    /// Instead of the engine tables: the state at scale. For each size, a generated rounds
    /// file (one round in ten labelled, `--dim`, `--reporters`) is imported into a fresh data
    /// directory (`vlmfuse import`'s code), then the restart is timed from the snapshot and by
    /// the full replay, and `--rounds` more live rounds (infer, store, observe; feedback for
    /// one in ten) are timed against the loaded state, with the process's RSS.
    #[arg(long, value_delimiter = ',')]
    pub scale: Vec<usize>,
    /// The fusion method of the scale run.
    #[arg(long, default_value = "adaptive", value_parser = parse_method)]
    pub method: Method,
    /// `[fusion.adaptive] pool_max` of the scale run (most unlabelled rounds kept; 0 = all).
    /// Without it, the default.
    #[arg(long)]
    pub pool_max: Option<usize>,
    /// `[fusion.adaptive] ann_min` of the scale run (0: exact kNN only). Without it, the
    /// default.
    #[arg(long)]
    pub ann_min: Option<usize>,
    /// `[fusion.adaptive] ann_probe` of the scale run. Without it, the default.
    #[arg(long)]
    pub ann_probe: Option<usize>,
    /// Contexts of the scale run: `scenes` (each scene type varies along a few directions of
    /// its own, as image embeddings do) or `isotropic` (a centre plus noise in every
    /// direction, where the exact neighbours are decided by noise).
    #[arg(long, default_value = "scenes", value_parser = ["scenes", "isotropic"])]
    pub contexts: String,
    /// Skip timing the restart by full replay (as long as the import itself at scale).
    #[arg(long)]
    pub no_full_replay: bool,
    /// With `--scale`: import the same file a second time with exact kNN only (`ann_min =
    /// 0`), and score both imports' decisions against the generated truth of every round
    /// (Hamming loss, micro-F1), over all rounds and over those the approximate index served:
    /// what approximate neighbours cost the fusion, at the pool sizes where they are used.
    /// The exact import is slow (its scan is linear in the pool).
    #[arg(long)]
    pub compare_exact: bool,
}

fn parse_method(s: &str) -> Result<Method, String> {
    match s {
        "paper" => Ok(Method::Paper),
        "adaptive" => Ok(Method::Adaptive),
        _ => Err(format!("unknown method {s:?}; expected paper or adaptive")),
    }
}

/// Resident set size of this process, in bytes (Linux; 0 elsewhere).
fn rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| s.split_whitespace().nth(1)?.parse::<u64>().ok())
        .map_or(0, |pages| pages * 4096)
}

fn synth_for(args: &BenchArgs, seed: u64) -> vlmfuse_fusion::bench::Synth {
    use vlmfuse_fusion::bench::Synth;
    let l = Ontology::paper().len();
    if args.contexts == "isotropic" {
        Synth::new(seed, args.dim, args.reporters, l)
    } else {
        Synth::scenes(seed, args.dim, args.reporters, l)
    }
}

fn scale_bench(args: &BenchArgs) -> anyhow::Result<()> {
    use vlmfuse_fusion::bench::reporter_names;
    use vlmfuse_fusion::{Engine, LabelledRound, RoundRecord};
    use vlmfuse_store::{NewRound, Store, StoredFeedback};
    let ontology = Ontology::paper();
    let l = ontology.len();
    let names = reporter_names(args.reporters);
    let defaults = vlmfuse_fusion::AdaptiveConfig::default();
    println!(
        "state at scale, method {}, {} contexts, d = {}, n = {}, pool_max = {}, ann_min = {}, ann_probe = {}, one round in ten labelled; restart = open + rebuild of the engine (the service's start before it listens)",
        args.method.name(),
        args.contexts,
        args.dim,
        args.reporters,
        args.pool_max.unwrap_or(defaults.pool_max),
        args.ann_min.unwrap_or(defaults.ann_min),
        args.ann_probe.unwrap_or(defaults.ann_probe),
    );
    for &n in &args.scale {
        let tmp = tempfile::tempdir()?;
        let file = tmp.path().join("rounds.jsonl");
        // Every round's truth (the file keeps one in ten), for `--compare-exact`.
        let mut truths: Vec<Vec<u8>> = Vec::new();
        {
            let mut synth = synth_for(args, 7);
            let mut w = std::io::BufWriter::new(std::fs::File::create(&file)?);
            for t in 0..n {
                let s = synth.round();
                let reports = names
                    .iter()
                    .enumerate()
                    .map(|(i, name)| {
                        (
                            name.clone(),
                            ontology.decode(&s.round.reports[i * l..(i + 1) * l]),
                        )
                    })
                    .collect();
                let rec = RoundRecord {
                    id: None,
                    context: s.round.context,
                    reports,
                    truth: (t % 10 == 0).then(|| ontology.decode(&s.truth)),
                };
                if args.compare_exact {
                    truths.push(s.truth.clone());
                }
                serde_json::to_writer(&mut w, &rec)?;
                w.write_all(b"\n")?;
            }
        }
        let data = tmp.path().join("data");
        let mut cfg = crate::Config {
            reporters: names.clone(),
            ..Default::default()
        };
        cfg.fusion.method = args.method;
        if let Some(m) = args.pool_max {
            cfg.fusion.adaptive.pool_max = m;
        }
        if let Some(m) = args.ann_min {
            cfg.fusion.adaptive.ann_min = m;
        }
        if let Some(p) = args.ann_probe {
            cfg.fusion.adaptive.ann_probe = p;
        }
        cfg.server.data_dir = data.clone();
        let t = Instant::now();
        let mut preds: Vec<Vec<u8>> = Vec::new();
        let mut served_from: Option<u64> = None;
        let done = {
            let mut keep = |i: u64, inf: &vlmfuse_fusion::Inference| {
                if args.compare_exact {
                    preds.push(inf.pred.clone());
                    if served_from.is_none() && inf.scan.as_ref().is_some_and(|s| s.cell.is_some())
                    {
                        served_from = Some(i);
                    }
                }
            };
            crate::import::import(
                &cfg,
                &file,
                2000,
                20,
                false,
                &std::sync::atomic::AtomicBool::new(false),
                &mut keep,
            )?
        };
        let import_s = t.elapsed().as_secs_f64();
        if args.compare_exact {
            compare_exact(&cfg, &file, tmp.path(), &truths, &preds, served_from)?;
        }
        let snap_bytes: u64 =
            vlmfuse_store::snapshot::list(&vlmfuse_store::snapshot::dir_of(&data))
                .iter()
                .filter_map(|p| std::fs::metadata(p).ok())
                .map(|m| m.len())
                .sum();
        let fresh = || Engine::new(cfg.fusion.clone(), cfg.ontology.clone(), names.clone());
        let t = Instant::now();
        let mut store = Store::open(&data)?;
        let mut engine = fresh()?;
        let rep = store.load_engine(&mut engine)?;
        let from_snapshot_s = t.elapsed().as_secs_f64();
        anyhow::ensure!(
            rep.snapshot.is_some(),
            "the import left no usable snapshot: {:?}",
            rep.skipped_snapshots
        );
        let full_s = if args.no_full_replay {
            f64::NAN
        } else {
            let t = Instant::now();
            let mut full = fresh()?;
            store.load_engine_full(&mut full)?;
            t.elapsed().as_secs_f64()
        };
        // Live rounds against the loaded state, as the writer runs them.
        // More rounds of the same scene types as the imported ones.
        let mut synth = synth_for(args, 7).reseeded(8);
        let mut lat = Vec::with_capacity(args.rounds);
        let mut eng = Vec::with_capacity(args.rounds);
        for (t, seq) in (0..args.rounds).zip(rep.next_seq..) {
            let s = synth.round();
            let t0 = Instant::now();
            let mut in_store = std::time::Duration::ZERO;
            let inf = engine.infer(&s.round);
            let mut stored = inf.clone();
            stored.scan = None;
            let ts = Instant::now();
            store.insert_rounds(
                seq,
                &[NewRound {
                    round: s.round.clone(),
                    inference: stored,
                    request: serde_json::json!({}),
                    created_ms: vlmfuse_store::timestamp_ms(),
                    thumbnails: Vec::new(),
                }],
            )?;
            in_store += ts.elapsed();
            engine.observe(seq, &s.round, &inf)?;
            if t % 10 == 0 {
                let o = engine.credit(&inf.signals, &inf.w_used, &s.truth, seq);
                let ts = Instant::now();
                store.insert_feedback(&[StoredFeedback {
                    seq,
                    labelled_order: engine.labelled(),
                    rounds_before: seq + 1,
                    truth: s.truth.clone(),
                    outcome: o.clone(),
                    source: "human".into(),
                }])?;
                in_store += ts.elapsed();
                engine.apply(
                    &LabelledRound {
                        seq,
                        round: s.round,
                        truth: s.truth,
                        q: inf.q,
                    },
                    Some(&o),
                )?;
            }
            let total = t0.elapsed();
            lat.push(total.as_secs_f64() * 1e3);
            eng.push((total - in_store).as_secs_f64() * 1e3);
        }
        lat.sort_by(f64::total_cmp);
        eng.sort_by(f64::total_cmp);
        let queries: Vec<Vec<f64>> = (0..200).map(|_| synth.round().round.context).collect();
        let recall = match engine.neighbour_recall(&queries) {
            Some((true, r)) => format!("approximate kNN, recall {r:.3} of the exact neighbours"),
            Some((false, _)) => "exact kNN".to_string(),
            None => "the paper method's exact kNN".to_string(),
        };
        let pct = |p: f64| vlmfuse_fusion::bench::percentile(&lat, p);
        let epct = |p: f64| vlmfuse_fusion::bench::percentile(&eng, p);
        println!(
            "{n:>9} rounds ({} labelled): import {import_s:.1} s ({:.0} rounds/s); snapshot {:.0} MB; \
             restart from the snapshot {from_snapshot_s:.2} s, by full replay {full_s:.2} s \
             ({:.0}x); per live round: engine p50 {:.2} ms, p99 {:.2} ms; with its commits (an \
             fsync each) p50 {:.2} ms, p99 {:.2} ms; RSS {:.0} MB; {recall}",
            done.labelled,
            done.rounds as f64 / import_s,
            snap_bytes as f64 / 1e6,
            full_s / from_snapshot_s.max(1e-9),
            epct(0.5),
            epct(0.99),
            pct(0.5),
            pct(0.99),
            rss_bytes() as f64 / 1e6
        );
        let _ = std::io::stdout().flush();
        drop(store);
        ui_cost(
            &data,
            &cfg,
            done.labelled,
            rep.next_seq + args.rounds as u64,
        )?;
    }
    Ok(())
}

/// `--compare-exact`: the same file imported with exact kNN only, and both imports' decisions
/// scored against every round's generated truth.
fn compare_exact(
    cfg: &crate::Config,
    file: &std::path::Path,
    tmp: &std::path::Path,
    truths: &[Vec<u8>],
    approx: &[Vec<u8>],
    served_from: Option<u64>,
) -> anyhow::Result<()> {
    let mut exact_cfg = cfg.clone();
    exact_cfg.fusion.adaptive.ann_min = 0;
    exact_cfg.server.data_dir = tmp.join("data-exact");
    let t = Instant::now();
    let mut exact: Vec<Vec<u8>> = Vec::with_capacity(truths.len());
    crate::import::import(
        &exact_cfg,
        file,
        2000,
        20,
        false,
        &std::sync::atomic::AtomicBool::new(false),
        &mut |_, inf| exact.push(inf.pred.clone()),
    )?;
    let exact_s = t.elapsed().as_secs_f64();
    let score = |preds: &[Vec<u8>], from: usize| {
        let (mut err, mut cells, mut tp, mut fp, mut fn_) = (0u64, 0u64, 0u64, 0u64, 0u64);
        for (p, y) in preds[from..].iter().zip(&truths[from..]) {
            for (&a, &b) in p.iter().zip(y) {
                cells += 1;
                err += (a != b) as u64;
                tp += (a == 1 && b == 1) as u64;
                fp += (a == 1 && b == 0) as u64;
                fn_ += (a == 0 && b == 1) as u64;
            }
        }
        let f1 = 2.0 * tp as f64 / (2 * tp + fp + fn_).max(1) as f64;
        (err as f64 / cells.max(1) as f64, f1)
    };
    let differ = |from: usize| {
        let (mut d, mut c) = (0u64, 0u64);
        for (a, b) in approx[from..].iter().zip(&exact[from..]) {
            for (x, y) in a.iter().zip(b) {
                c += 1;
                d += (x != y) as u64;
            }
        }
        d as f64 / c.max(1) as f64
    };
    let from = served_from.map_or(approx.len(), |s| s as usize);
    println!(
        "          exact kNN import {exact_s:.1} s; decisions against the generated truth (Hamming loss, micro-F1), approximate | exact | difference:"
    );
    for (what, start) in [("all rounds", 0usize), ("rounds the index served", from)] {
        if start >= approx.len() {
            println!("            {what}: none");
            continue;
        }
        let (ha, fa) = score(approx, start);
        let (he, fe) = score(&exact, start);
        println!(
            "            {what} ({}): Hamming {ha:.4} | {he:.4} | {:+.4}; micro-F1 {fa:.4} | {fe:.4} | {:+.4}; decisions that differ {:.4}",
            approx.len() - start,
            ha - he,
            fa - fe,
            differ(start)
        );
    }
    Ok(())
}

/// What the operator page (`/ui`) costs over a data directory of this size: the start's
/// seeding of its aggregates, one summary's panels, and the store reads of the rounds pages
/// (newest, and from the middle of the history) and of one round's page. Each should stay flat
/// as the store grows: bounded windows and key ranges, never a scan.
fn ui_cost(
    data: &std::path::Path,
    cfg: &crate::Config,
    labelled: u64,
    rounds: u64,
) -> anyhow::Result<()> {
    use crate::service::dashboard::Dashboard;
    let reader = vlmfuse_store::Store::open_read_only(data)?;
    let mut dash = Dashboard::new(
        cfg.ui.clone(),
        cfg.reporters.len(),
        cfg.ontology.labels().len(),
    );
    let t = Instant::now();
    dash.seed(&reader, labelled)?;
    let seed_ms = t.elapsed().as_secs_f64() * 1e3;
    let time = |f: &mut dyn FnMut() -> anyhow::Result<()>| -> anyhow::Result<f64> {
        let mut v = Vec::with_capacity(20);
        for _ in 0..20 {
            let t = Instant::now();
            f()?;
            v.push(t.elapsed().as_secs_f64() * 1e3);
        }
        v.sort_by(f64::total_cmp);
        Ok(v[v.len() / 2])
    };
    let summary_ms = time(&mut || {
        std::hint::black_box(dash.panels(&cfg.reporters));
        Ok(())
    })?;
    let newest_ms = time(&mut || {
        std::hint::black_box(reader.recent_rounds(None, 20)?);
        Ok(())
    })?;
    let middle_ms = time(&mut || {
        std::hint::black_box(reader.recent_rounds(Some(rounds / 2), 20)?);
        Ok(())
    })?;
    let round_ms = time(&mut || {
        let seq = rounds / 3;
        std::hint::black_box((
            reader.round_row(seq)?,
            reader.feedback(seq)?,
            reader.thumbnail_index(seq)?,
        ));
        Ok(())
    })?;
    println!(
        "{rounds:>9} rounds, operator page: start-up seeding {seed_ms:.0} ms; per request (median of 20): \
         summary panels {summary_ms:.2} ms, rounds page newest {newest_ms:.2} ms, from the middle \
         {middle_ms:.2} ms, a round's page {round_ms:.2} ms"
    );
    Ok(())
}

fn eval_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let records = synthetic_records(2000, 103, args.reporters, 5);
    let dir = std::env::temp_dir().join(format!("vlmfuse-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("rounds-2000-d103.jsonl");
    {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&path)?);
        for (_, r) in &records {
            serde_json::to_writer(&mut f, r)?;
            f.write_all(b"\n")?;
        }
    }
    let eargs = EvalArgs {
        rounds: path.clone(),
        split: 0.7,
        frozen: false,
        ablations: vec![],
        emit_rounds: None,
        report: None,
        plots: None,
        config: None,
        per_query_knn: false,
        method: None,
        labelled: None,
        seed: 0,
        pick: eval::Pick::Random,
        review_pool: 1.0,
        curve: vec![],
        quiet: true,
    };
    let start = Instant::now();
    let recs = eval::read_rounds(&path)?;
    let read = start.elapsed().as_secs_f64();
    let run = eval::evaluate(&FusionConfig::default(), &Ontology::paper(), &recs, &eargs)?;
    let table = eval::format_table(&run);
    std::hint::black_box(table);
    let total = start.elapsed().as_secs_f64();
    println!(
        "\neval end to end, 2,000 rounds, d = 103, n = {} (read + parse {:.0} ms, total {:.0} ms; \
         target < 500 ms)",
        args.reporters,
        read * 1e3,
        total * 1e3
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Fuse-then-feedback per round under both methods at each bank size, in one run, with the
/// adaptive/paper ratio of the means (issue 9's speed target: at most 1.5x at bank 10k, d 512).
/// `VLMFUSE_BENCH_PARTS=1` adds each step's mean.
fn engine_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let l = Ontology::paper().len();
    println!(
        "fuse-then-feedback per round (infer [+ observe] + Shapley credit + reputation update + \
         bank, window and threshold refit), then as many rounds that are never labelled (infer + \
         observe), d = {}, n = {}, L = {l}, one core",
        args.dim, args.reporters
    );
    println!(
        "{:>9} {:>9} {:>12} {:>12} {:>12} {:>14} {:>10} {:>9} {:>16} {:>9}",
        "bank",
        "method",
        "mean (us)",
        "p50 (us)",
        "p95 (us)",
        "top-50 (us)",
        "fill (s)",
        "ratio",
        "unlabelled (us)",
        "ratio"
    );
    let parts = std::env::var_os("VLMFUSE_BENCH_PARTS").is_some();
    for &bank in &args.banks {
        let mut paper_mean = f64::NAN;
        let mut paper_unlabelled = f64::NAN;
        for method in [Method::Paper, Method::Adaptive] {
            let t = fuse_feedback(method, bank, args.dim, args.reporters, args.rounds)?;
            let mean = t.mean_us();
            let unlabelled = t.unlabelled_mean_us();
            if method == Method::Paper {
                paper_mean = mean;
                paper_unlabelled = unlabelled;
            }
            println!(
                "{:>9} {:>9} {:>12.1} {:>12.1} {:>12.1} {:>14.1} {:>10.2} {:>8.2}x {:>16.1} {:>8.2}x",
                bank,
                method.name(),
                mean,
                t.percentile_us(0.5),
                t.percentile_us(0.95),
                t.top50_us,
                t.fill_s,
                mean / paper_mean,
                unlabelled,
                unlabelled / paper_unlabelled
            );
            if parts {
                let p = t.mean_parts;
                println!(
                    "{:>19} infer {:?}, observe {:?}, credit {:?}, apply {:?}",
                    "", p.infer, p.observe, p.credit, p.apply
                );
            }
            let _ = std::io::stdout().flush();
        }
    }
    // The same workload with the two methods interleaved block by block (see
    // `fuse_feedback_paired`): the ratio that a busy machine cannot skew.
    println!(
        "interleaved, blocks of {PAIRED_BLOCK} rounds run by paper then adaptive; median of the \
         per-block ratios"
    );
    println!(
        "{:>9} {:>16} {:>19} {:>9} {:>18} {:>21} {:>9}",
        "bank",
        "paper lab. (us)",
        "adaptive lab. (us)",
        "ratio",
        "paper unlab. (us)",
        "adaptive unlab. (us)",
        "ratio"
    );
    for &bank in &args.banks {
        let p = fuse_feedback_paired(bank, args.dim, args.reporters, args.rounds, PAIRED_BLOCK)?;
        println!(
            "{:>9} {:>16.1} {:>19.1} {:>8.2}x {:>18.1} {:>21.1} {:>8.2}x",
            bank,
            p.paper_labelled_us,
            p.adaptive_labelled_us,
            p.labelled_ratio,
            p.paper_unlabelled_us,
            p.adaptive_unlabelled_us,
            p.unlabelled_ratio
        );
        let _ = std::io::stdout().flush();
    }
    Ok(())
}

/// Rounds per block of the interleaved benchmark: long enough to time (about 10 ms at bank
/// 1k), short enough that a slow second of the machine spoils only a few blocks.
const PAIRED_BLOCK: usize = 25;

fn knn_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let t = knn(args.dim, args.reporters)?;
    println!(
        "\nsimilarities, {} queries x {} bank x d {}: per-query dots {:.1} ms, one GEMM {:.1} ms \
         -> GEMM {:.2}x faster",
        t.queries,
        t.bank,
        t.dim,
        t.per_query_s * 1e3,
        t.gemm_s * 1e3,
        t.per_query_s / t.gemm_s
    );
    println!(
        "replay of {} rounds at d = {}: per-query kNN {:.1} ms, batched GEMM kNN {:.1} ms -> {:.2}x",
        t.replay_rounds,
        t.dim,
        t.replay_per_query_s * 1e3,
        t.replay_batched_s * 1e3,
        t.replay_per_query_s / t.replay_batched_s
    );
    Ok(())
}

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    if cfg!(debug_assertions) {
        eprintln!("warning: a debug build; run `cargo run --release -- bench` for real numbers");
    }
    if !args.scale.is_empty() {
        return scale_bench(&args);
    }
    engine_bench(&args)?;
    if !args.engine_only {
        knn_bench(&args)?;
        eval_bench(&args)?;
    }
    Ok(())
}
