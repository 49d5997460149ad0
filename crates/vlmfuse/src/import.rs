//! `vlmfuse import`: a rounds file (the `eval` format, one JSON round per line, `truth`
//! optional) into a data directory, as if each round had come through `/v1/fuse` and, where it
//! has a truth, its `/v1/feedback` right after: inferred against the state as it stands,
//! stored, learned from. The service started on the directory afterwards continues from there
//! exactly (the same events a live writer would have stored, in the same order), and starts
//! from the snapshot the import leaves behind instead of replaying the file.
//!
//! The file is read twice at once: one thread checks every line (JSON, reporters, labels,
//! context dimension), running well ahead of the engine, while the rounds are imported in
//! chunks of one transaction each. A bad line stops the import, which rolls back and reports
//! every bad line with its number, storing nothing; so does any other failure (a full disk,
//! Ctrl-C or SIGTERM): a file either imports whole or not at all. (`kill -9` cannot be
//! caught: it leaves the chunks committed so far.)

use crate::config::{Config, ServeArgs};
use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use vlmfuse_fusion::{Engine, LabelledRound, RoundRecord};
use vlmfuse_store::{snapshot, Identity, NewRound, Store, StoredFeedback};

#[derive(clap::Args)]
pub struct ImportArgs {
    /// The rounds file (JSON lines: `context`, `reports`, optional `truth` and `id`).
    pub file: PathBuf,
    /// Rounds per transaction.
    #[arg(long, default_value_t = 2000)]
    pub chunk: usize,
    /// At most this many bad lines are listed (all are counted).
    #[arg(long, default_value_t = 20)]
    pub max_errors: usize,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// The service's configuration (`--config`, `--reporters`, `--data-dir`, every `serve`
    /// flag): the import writes where, and as, `vlmfuse serve` with these would.
    #[command(flatten)]
    pub serve: ServeArgs,
}

/// What an import did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Imported {
    pub rounds: u64,
    pub labelled: u64,
}

fn bar(quiet: bool, len: u64, what: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let b = ProgressBar::new(len);
    b.set_style(
        ProgressStyle::with_template(
            "{spinner} {msg:<10} [{bar:40}] {bytes}/{total_bytes} ({bytes_per_sec}, eta {eta})",
        )
        .expect("static template")
        .progress_chars("=> "),
    );
    b.set_message(what.to_string());
    b
}

/// The non-empty lines of the file with their 1-based numbers, and the bytes read so far.
fn lines(
    path: &Path,
) -> anyhow::Result<impl Iterator<Item = (usize, u64, std::io::Result<String>)>> {
    let f = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut read = 0u64;
    Ok(BufReader::with_capacity(1 << 20, f)
        .lines()
        .enumerate()
        .map(move |(i, l)| {
            if let Ok(s) = &l {
                read += s.len() as u64 + 1;
            }
            (i + 1, read, l)
        })
        .filter(|(_, _, l)| l.as_ref().map_or(true, |s| !s.trim().is_empty())))
}

/// Set by SIGINT or SIGTERM while an import runs; the import stops at the next round and rolls
/// back.
fn stop_flag() -> anyhow::Result<(Arc<AtomicBool>, Vec<signal_hook::SigId>)> {
    let flag = Arc::new(AtomicBool::new(false));
    let mut ids = Vec::new();
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        ids.push(signal_hook::flag::register(sig, flag.clone()).context("signal handler")?);
    }
    Ok((flag, ids))
}

pub fn run(args: ImportArgs) -> anyhow::Result<()> {
    let cfg = Config::load(&args.serve)?;
    let t = Instant::now();
    let (stop, ids) = stop_flag()?;
    let res = import(
        &cfg,
        &args.file,
        args.chunk,
        args.max_errors,
        args.quiet,
        &stop,
        &mut |_, _| {},
    );
    for id in ids {
        signal_hook::low_level::unregister(id);
    }
    let done = res?;
    let secs = t.elapsed().as_secs_f64();
    eprintln!(
        "imported {} rounds ({} labelled) from {} into {} in {secs:.1} s ({:.0} rounds/s)",
        done.rounds,
        done.labelled,
        args.file.display(),
        cfg.server.data_dir.display(),
        done.rounds as f64 / secs.max(1e-9)
    );
    Ok(())
}

/// Imports `file` into `cfg.server.data_dir` (see the module docs). It gives up, storing
/// nothing, once `stop` is set; `on_round` sees each round's inference as it is made, with
/// the round's 0-based place among the file's rounds (what `vlmfuse bench --scale
/// --compare-exact` scores).
pub fn import(
    cfg: &Config,
    file: &Path,
    chunk: usize,
    max_errors: usize,
    quiet: bool,
    stop: &AtomicBool,
    on_round: &mut dyn FnMut(u64, &vlmfuse_fusion::Inference),
) -> anyhow::Result<Imported> {
    if chunk == 0 {
        bail!("--chunk must be at least 1");
    }
    let total = std::fs::metadata(file)
        .with_context(|| format!("cannot read {}", file.display()))?
        .len();
    let mut engine = Engine::new(
        cfg.fusion.clone(),
        cfg.ontology.clone(),
        cfg.reporters.clone(),
    )
    .context("fusion engine")?;
    let mut store = Store::open_at(
        &cfg.store.location(&cfg.server.data_dir),
        std::time::Duration::ZERO,
    )?;
    store.check_identity(&Identity {
        reporters: cfg.reporters.clone(),
        labels: cfg.ontology.ids().map(str::to_string).collect(),
    })?;
    store
        .load_engine(&mut engine)
        .with_context(|| format!("rebuilding the engine from {}", store.path().display()))?;

    // A parse-only engine (configuration, ontology, reporters and context dimension; no state)
    // for the threads that check and parse lines beside the engine.
    let parser = {
        let mut p = Engine::new(
            cfg.fusion.clone(),
            cfg.ontology.clone(),
            cfg.reporters.clone(),
        )
        .context("fusion engine")?;
        if let Some(d) = engine.dim() {
            p.fix_dim(d)?;
        }
        p
    };

    // Pass 2: the events, in chunks of one transaction.
    let start = store.anchor()?;
    let start_w = engine.reputations().to_vec();
    let res = ingest(
        &mut store,
        &mut engine,
        &parser,
        start.rounds,
        file,
        (chunk, max_errors),
        quiet,
        total,
        stop,
        on_round,
    );
    match res {
        Ok(done) => {
            let anchor = store.anchor()?;
            let dir = snapshot::dir_of(store.dir());
            let keep = cfg.server.snapshot_keep;
            drop(store);
            if let Err(e) = snapshot::write(&dir, &engine, &anchor, keep) {
                eprintln!("warning: the import is stored, but its snapshot failed ({e}); the next start replays every event");
            }
            Ok(done)
        }
        Err(e) => {
            store.roll_back_to(&start, &start_w).with_context(|| {
                format!(
                    "the import failed ({e:#}) and rolling back failed too: the data directory \
                     holds part of the file"
                )
            })?;
            Err(e.context("the import failed; the data directory is as it was before"))
        }
    }
}

/// One line as the engine takes it: the record, its round and its truth. `p` is a parse-only
/// engine; the first line fixes its context dimension when the store has none yet (as the
/// service's first stored round does).
fn parse_line(
    p: &mut Engine,
    text: &str,
) -> anyhow::Result<(RoundRecord, vlmfuse_fusion::Round, Option<Vec<u8>>)> {
    let rec = serde_json::from_str::<RoundRecord>(text)?;
    if p.dim().is_none() {
        p.fix_dim(rec.context.len())?;
    }
    let (round, truth) = p.parse(&rec)?;
    Ok((rec, round, truth))
}

/// What the checking thread found: good lines, bad lines (counted), the first `max_errors`
/// of them with their numbers.
#[derive(Default)]
struct Checked {
    good: u64,
    nbad: usize,
    bad: Vec<String>,
}

/// Checks every line of the file (JSON, reporters, labels, context dimension) against a
/// parse-only engine, until the end or until `quit`. On the first bad line `failed` is set, so
/// that the engine side stops and the import rolls back.
fn check_lines(
    parser: &Engine,
    file: &Path,
    max_errors: usize,
    failed: &AtomicBool,
    quit: &AtomicBool,
) -> anyhow::Result<Checked> {
    let mut check = parser.clone();
    let mut out = Checked::default();
    for (line, _, text) in lines(file)? {
        if quit.load(Ordering::Relaxed) {
            break;
        }
        let text = text.with_context(|| format!("{}: line {line}", file.display()))?;
        match parse_line(&mut check, &text) {
            Ok(_) => out.good += 1,
            Err(e) => {
                failed.store(true, Ordering::Relaxed);
                out.nbad += 1;
                if out.bad.len() < max_errors {
                    out.bad.push(format!("line {line}: {e}"));
                }
            }
        }
    }
    Ok(out)
}

/// A line made ready for the engine on the parsing thread: the round, its truth, and the
/// request JSON stored with it.
struct Parsed {
    line: usize,
    read: u64,
    round: vlmfuse_fusion::Round,
    truth: Option<Vec<u8>>,
    request: serde_json::Value,
}

/// The file's rounds as events from `seq` `first` on, in chunks of one transaction. Four
/// threads: one checks every line (the whole file, so that every bad line is reported, and
/// well ahead of the engine, so that a bad file stops the import early); one reads and parses
/// the lines for the engine; the engine takes the rounds one by one, in order, on this thread
/// (its work is sequential: each round is inferred against the state the previous ones left);
/// one commits the chunks. The engine's thread does nothing but the engine's work.
#[allow(clippy::too_many_arguments)]
fn ingest(
    store: &mut Store,
    engine: &mut Engine,
    parser: &Engine,
    mut first: u64,
    file: &Path,
    (chunk, max_errors): (usize, usize),
    quiet: bool,
    total: u64,
    stop: &AtomicBool,
    on_round: &mut dyn FnMut(u64, &vlmfuse_fusion::Inference),
) -> anyhow::Result<Imported> {
    let b = bar(quiet, total, "importing");
    let mut seq = first;
    let mut rounds: Vec<NewRound> = Vec::with_capacity(chunk);
    let mut fbs: Vec<StoredFeedback> = Vec::new();
    let mut done = Imported {
        rounds: 0,
        labelled: 0,
    };
    let name = file.display().to_string();
    let lines = lines(file)?;
    let failed = AtomicBool::new(false);
    let quit = AtomicBool::new(false);
    std::thread::scope(|scope| -> anyhow::Result<Imported> {
        let (failed, quit) = (&failed, &quit);
        let checker = scope.spawn(move || {
            let r = check_lines(parser, file, max_errors, failed, quit);
            if r.is_err() {
                failed.store(true, Ordering::Relaxed);
            }
            r
        });
        let (tx, rx) = std::sync::mpsc::sync_channel::<anyhow::Result<Parsed>>(256);
        let reader_name = name.clone();
        let mut parse = parser.clone();
        scope.spawn(move || {
            for (line, read, text) in lines {
                if quit.load(Ordering::Relaxed) {
                    return;
                }
                let parsed = text
                    .with_context(|| format!("{reader_name}: line {line}"))
                    .and_then(|t| {
                        let (rec, round, truth) = parse_line(&mut parse, &t)
                            .with_context(|| format!("{reader_name}: line {line}"))?;
                        let request = serde_json::json!({
                            "import": { "file": reader_name, "line": line, "id": rec.id },
                            "reports": rec.reports,
                        });
                        Ok(Parsed {
                            line,
                            read,
                            round,
                            truth,
                            request,
                        })
                    });
                let bad = parsed.is_err();
                if tx.send(parsed).is_err() || bad {
                    return;
                }
            }
        });
        // Chunks are committed on their own thread, while the engine goes on with the next.
        let (wtx, wrx) =
            std::sync::mpsc::sync_channel::<(u64, Vec<NewRound>, Vec<StoredFeedback>)>(1);
        let writer = scope.spawn(move || -> anyhow::Result<()> {
            for (first, rounds, fbs) in wrx {
                store.insert_batch(first, &rounds, &fbs)?;
            }
            Ok(())
        });
        let commit = |first: u64, rounds: Vec<NewRound>, fbs: Vec<StoredFeedback>| {
            // A closed queue means the writer failed: its error is the one to report.
            wtx.send((first, rounds, fbs)).is_ok()
        };
        // Set when the engine side stopped on a line the reader could not parse: the checker
        // then runs to the end of the file, so that every bad line is listed.
        let mut bad_line = false;
        let engine_side = (|| -> anyhow::Result<bool> {
            // Peeked: the next round's context lets the engine search its neighbours on a
            // second thread while this round's EM work runs (`Engine::observe_ahead`).
            let mut rx = rx.iter().peekable();
            let beside = vlmfuse_fusion::Beside::new();
            while let Some(parsed) = rx.next() {
                bad_line = parsed.is_err();
                let Parsed {
                    line,
                    read,
                    round,
                    truth,
                    request,
                } = parsed?;
                if stop.load(Ordering::Relaxed) {
                    bail!("interrupted at line {line}");
                }
                if failed.load(Ordering::Relaxed) {
                    bail!("a bad line in the file");
                }
                if engine.dim().is_none() {
                    engine.fix_dim(round.context.len())?;
                }
                let inf = engine.infer(&round);
                on_round(done.rounds, &inf);
                let next = match rx.peek() {
                    Some(Ok(p)) => Some((p.round.context.as_slice(), &beside)),
                    _ => None,
                };
                engine.observe_ahead(seq, &round, &inf, next)?;
                if let Some(truth) = truth {
                    let outcome = engine.credit(&inf.signals, &inf.w_used, &truth, seq);
                    fbs.push(StoredFeedback {
                        seq,
                        labelled_order: engine.labelled(),
                        rounds_before: seq + 1,
                        truth: truth.clone(),
                        outcome: outcome.clone(),
                        source: "human".into(),
                    });
                    engine.apply(
                        &LabelledRound {
                            seq,
                            round: round.clone(),
                            truth,
                            q: inf.q.clone(),
                        },
                        Some(&outcome),
                    )?;
                    done.labelled += 1;
                }
                let mut stored = inf;
                stored.scan = None;
                rounds.push(NewRound {
                    round,
                    inference: stored,
                    request,
                    created_ms: vlmfuse_store::timestamp_ms(),
                    thumbnails: Vec::new(),
                });
                seq += 1;
                done.rounds += 1;
                if rounds.len() >= chunk {
                    let full = std::mem::replace(&mut rounds, Vec::with_capacity(chunk));
                    if !commit(first, full, std::mem::take(&mut fbs)) {
                        return Ok(false);
                    }
                    first = seq;
                    b.set_position(read);
                }
            }
            Ok(rounds.is_empty()
                || commit(first, std::mem::take(&mut rounds), std::mem::take(&mut fbs)))
        })();
        drop(wtx);
        // Anything but a bad line (an interrupt, a refused commit, the end) needs no full check.
        if !failed.load(Ordering::Relaxed) && !bad_line {
            quit.store(true, Ordering::Relaxed);
        }
        let written = writer
            .join()
            .map_err(|_| anyhow::anyhow!("the import's writer thread panicked"))?;
        let checked = checker
            .join()
            .map_err(|_| anyhow::anyhow!("the import's checking thread panicked"))??;
        quit.store(true, Ordering::Relaxed);
        b.finish_and_clear();
        // Bad lines first: they are why the engine side stopped, and every one is listed.
        if checked.nbad > 0 {
            let more = if checked.nbad > checked.bad.len() {
                format!("\n  ... and {} more", checked.nbad - checked.bad.len())
            } else {
                String::new()
            };
            bail!(
                "{name}: {} bad line(s); nothing was imported:\n  {}{more}",
                checked.nbad,
                checked.bad.join("\n  ")
            );
        }
        // Then the writer's: a refused commit is why the engine side stopped.
        written?;
        engine_side?;
        if done.rounds == 0 {
            bail!("{name}: no rounds in the file; nothing was imported");
        }
        Ok(done)
    })
}
