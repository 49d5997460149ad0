//! `vlmfuse eval`: the paper's protocol over a rounds file (PAPER-METHOD.md §9), with the metrics table of
//! docs/PAPER-METHOD.md §7 for the method, each requested ablation and the baselines; `--labelled N` hides the
//! truth of all but N history rounds, and `--curve` measures the learning curve of both methods.

use crate::plots;
use anyhow::{bail, Context};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Deserialize;
use serde_json::{json, Map, Value};
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;
use vlmfuse_fusion::curve::{dawid_skene, hide_labels, score_posteriors, ReviewPool};
use vlmfuse_fusion::metrics::Scores;
use vlmfuse_fusion::replay::{
    history_len, prepare, replay, score_baselines, score_method, ParsedRound, ReplayOptions,
    RoundOutcome,
};
use vlmfuse_fusion::{
    Ablations, Engine, FusionConfig, Label, Method, Ontology, RoundRecord, ThresholdMode,
};

/// The method `eval` runs when neither `--method` nor the config file names one.
pub const DEFAULT_METHOD: Method = Method::Adaptive;

/// EM iterations of the unsupervised Dawid–Skene baseline (it stops earlier once converged).
const DS_ITERS: usize = 200;
/// Pseudo-count added to each confusion cell of the Dawid–Skene baseline.
const DS_SMOOTHING: f64 = 0.01;

/// How many history rounds keep their truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Keep {
    N(usize),
    All,
}

impl Keep {
    pub fn limit(&self) -> Option<usize> {
        match self {
            Keep::N(n) => Some(*n),
            Keep::All => None,
        }
    }
}

impl std::fmt::Display for Keep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Keep::N(n) => write!(f, "{n}"),
            Keep::All => f.write_str("all"),
        }
    }
}

fn parse_keep(s: &str) -> Result<Keep, String> {
    if s.eq_ignore_ascii_case("all") {
        return Ok(Keep::All);
    }
    s.parse::<usize>()
        .map(Keep::N)
        .map_err(|_| format!("expected a number of labelled rounds or `all`, got {s:?}"))
}

fn parse_method(s: &str) -> Result<Method, String> {
    Method::from_name(s).ok_or_else(|| {
        format!(
            "unknown method {s:?}; expected one of {}",
            Method::NAMES.join(", ")
        )
    })
}

#[derive(Args, Debug, Clone)]
pub struct EvalArgs {
    /// Rounds file: JSON Lines, one docs/PAPER-METHOD.md §8 round a line.
    pub rounds: PathBuf,
    /// Share of rounds (from the start) that is history and not scored.
    #[arg(long, default_value_t = 0.7, value_parser = parse_split)]
    pub split: f64,
    /// Stop learning after the history.
    #[arg(long)]
    pub frozen: bool,
    /// Also run an ablation (repeatable): frozen-reputation, per-model-score, no-guardrail,
    /// no-context, or `all`.
    #[arg(long = "ablation", value_name = "NAME")]
    pub ablations: Vec<String>,
    /// Write one line per round of the full method (PAPER-METHOD.md §9 fields).
    #[arg(long, value_name = "OUT.jsonl")]
    pub emit_rounds: Option<PathBuf>,
    /// Write the table as JSON.
    #[arg(long, value_name = "OUT.json")]
    pub report: Option<PathBuf>,
    /// Write SVG charts here: reputations over rounds, reliability diagram, ablation bars.
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
    /// TOML config whose `[fusion]` table and `[[ontology]]` labels replace the defaults.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: Option<PathBuf>,
    /// Compute similarities one query at a time instead of batched GEMMs (for comparison).
    #[arg(long)]
    pub per_query_knn: bool,
    /// Fusion method: `adaptive` (docs/METHOD.md) or `paper` (PAPER-METHOD.md exactly). Without it,
    /// the config file's `[fusion] method`, else `adaptive`.
    #[arg(long, value_parser = parse_method)]
    pub method: Option<Method>,
    /// Keep the truth of only N history rounds (chosen by `--seed`) and hide the others'; `all`
    /// keeps every one. Test rounds keep theirs: they are scored on it.
    #[arg(long, value_parser = parse_keep, value_name = "N|all")]
    pub labelled: Option<Keep>,
    /// Seed of the `--labelled` / `--curve` choice of labelled rounds.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// How `--labelled` / `--curve` choose the history rounds that keep their truth: `random`
    /// (uniformly, by `--seed`) or `review` (the review queue of `GET /v1/review` over the
    /// history rounds: the rounds that best stand for the others in context, disputed rounds
    /// weighing more; no truth is used); with `--curve`, `compare` runs each N with both and
    /// `--plots` draws random picks dashed beside the queue's.
    #[arg(long, value_enum, default_value_t = Pick::Random)]
    pub pick: Pick,
    /// With `--pick review` or `compare`: the queue ranks only a `--seed`-chosen share of the
    /// history rounds (in (0, 1]; 1 = all, the default). The queue is deterministic, so one
    /// queue is one sample of N rounds; seeded pools give it a spread of outcomes to average over
    /// seeds, as random picks are (`scripts/queue-curve --pools`).
    #[arg(long, default_value_t = 1.0, value_parser = parse_pool, value_name = "SHARE",
          allow_negative_numbers = true)]
    pub review_pool: f64,
    /// Learning curve: for each N (e.g. `0,10,50,200,all`) and each method, one row of the
    /// table, plus majority vote, unsupervised Dawid–Skene and each reporter alone; with
    /// `--plots`, the curve and a reliability diagram per method.
    #[arg(long, value_delimiter = ',', value_parser = parse_keep, value_name = "N,...")]
    pub curve: Vec<Keep>,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// `--pick`: which history rounds keep their truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Pick {
    Random,
    Review,
    /// `--curve` only: each N twice, with the review queue's picks and with random ones.
    Compare,
}

impl Pick {
    pub fn name(self) -> &'static str {
        match self {
            Pick::Random => "random",
            Pick::Review => "review",
            Pick::Compare => "compare",
        }
    }
}

/// The rounds with all but `keep` history truths hidden, chosen by `pick`; `pool.seed` (the
/// `--seed`) draws random picks as well as the review queue's pool.
fn choose_labels(
    rounds: &[ParsedRound],
    n_hist: usize,
    keep: Option<usize>,
    pick: Pick,
    pool: ReviewPool,
    (reporters, l): (usize, usize),
) -> (Vec<ParsedRound>, usize) {
    match pick {
        Pick::Random | Pick::Compare => hide_labels(rounds, n_hist, keep, pool.seed),
        Pick::Review => {
            let q = dawid_skene(rounds, reporters, l, DS_ITERS, DS_SMOOTHING);
            vlmfuse_fusion::curve::pick_review(rounds, n_hist, keep, &q, pool)
        }
    }
}

impl EvalArgs {
    /// `--review-pool` with the `--seed` that draws it.
    fn pool(&self) -> ReviewPool {
        ReviewPool {
            share: self.review_pool,
            seed: self.seed,
        }
    }
}

fn parse_pool(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if v > 0.0 && v <= 1.0 {
        Ok(v)
    } else {
        Err(format!("the review pool is a share in (0, 1], got {v}"))
    }
}

fn parse_split(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if (0.0..=1.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("split must lie in [0, 1], got {v}"))
    }
}

/// The parts of a config file that `eval` reads; the service's other sections are ignored.
#[derive(Deserialize, Default)]
struct EvalConfigFile {
    #[serde(default)]
    fusion: Option<FusionConfig>,
    #[serde(default)]
    ontology: Option<Vec<Label>>,
}

pub fn load_fusion_config(path: Option<&Path>) -> anyhow::Result<(FusionConfig, Ontology)> {
    let Some(path) = path else {
        return Ok((FusionConfig::default(), Ontology::paper()));
    };
    let at = || path.display().to_string();
    let text = std::fs::read_to_string(path).with_context(at)?;
    let file: EvalConfigFile = toml::from_str(&text).with_context(at)?;
    let ontology = match file.ontology {
        Some(labels) => Ontology::new(labels).with_context(at)?,
        None => Ontology::paper(),
    };
    let fusion = file.fusion.unwrap_or_default();
    fusion
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: [fusion] {e}", path.display()))?;
    Ok((fusion, ontology))
}

/// The method `eval` runs: `--method`, else the config file's `[fusion] method` if it names one,
/// else [`DEFAULT_METHOD`].
pub fn resolve_method(args: &EvalArgs) -> anyhow::Result<Method> {
    if let Some(m) = args.method {
        return Ok(m);
    }
    if let Some(path) = &args.config {
        let at = || path.display().to_string();
        let text = std::fs::read_to_string(path).with_context(at)?;
        let v: toml::Value = toml::from_str(&text).with_context(at)?;
        if let Some(m) = v
            .get("fusion")
            .and_then(|f| f.get("method"))
            .and_then(|m| m.as_str())
        {
            return parse_method(m)
                .map_err(|e| anyhow::anyhow!("{}: [fusion] {e}", path.display()));
        }
    }
    Ok(DEFAULT_METHOD)
}

/// Reads a rounds file, naming the line of the first problem.
pub fn read_rounds(path: &Path) -> anyhow::Result<Vec<(usize, RoundRecord)>> {
    let f = File::open(path).with_context(|| path.display().to_string())?;
    let mut out = Vec::new();
    for (i, line) in BufReader::new(f).lines().enumerate() {
        let line_no = i + 1;
        let at = || format!("{}: line {line_no}", path.display());
        let line = line.with_context(at)?;
        if line.trim().is_empty() {
            continue;
        }
        let rec: RoundRecord = serde_json::from_str(&line).with_context(at)?;
        out.push((line_no, rec));
    }
    if out.is_empty() {
        bail!("{}: no rounds in the file", path.display());
    }
    Ok(out)
}

/// One row of the table.
pub struct Row {
    pub name: String,
    pub kind: &'static str,
    pub scores: Scores,
}

pub struct EvalRun {
    pub engine: Engine,
    pub rounds: Vec<ParsedRound>,
    pub outcomes: Vec<RoundOutcome>,
    pub rows: Vec<Row>,
    pub n_hist: usize,
    /// History rounds whose truth the method saw (all of them unless `--labelled`).
    pub labelled: usize,
    /// History rounds with truth in the file.
    pub available: usize,
    pub seed: u64,
    pub pick: Pick,
    /// `--review-pool`: the share of history rounds the queue ranked.
    pub review_pool: f64,
}

fn ablation_list(names: &[String]) -> anyhow::Result<Vec<String>> {
    let mut out: Vec<String> = Vec::new();
    for n in names {
        let expanded: Vec<String> = if n == "all" {
            Ablations::NAMES.iter().map(|s| s.to_string()).collect()
        } else if Ablations::from_name(n).is_some() {
            vec![n.clone()]
        } else {
            bail!(
                "unknown ablation {n:?}; expected one of {} or all",
                Ablations::NAMES.join(", ")
            );
        };
        for e in expanded {
            if !out.contains(&e) {
                out.push(e);
            }
        }
    }
    Ok(out)
}

/// The whole protocol in memory: the method, each ablation, the baselines.
pub fn evaluate(
    cfg: &FusionConfig,
    ontology: &Ontology,
    records: &[(usize, RoundRecord)],
    args: &EvalArgs,
) -> anyhow::Result<EvalRun> {
    let ablations = ablation_list(&args.ablations)?;
    let (engine, all_rounds) = prepare(cfg, ontology, records)?;
    let n_hist = history_len(all_rounds.len(), args.split);
    if args.pick == Pick::Compare {
        anyhow::bail!("--pick compare draws two curves: use it with --curve, not --labelled");
    }
    let (rounds, labelled) = choose_labels(
        &all_rounds,
        n_hist,
        args.labelled.and_then(|k| k.limit()),
        args.pick,
        args.pool(),
        (engine.reporters().len(), ontology.len()),
    );
    let opts = ReplayOptions {
        split: args.split,
        frozen: args.frozen,
        batch_knn: !args.per_query_knn,
    };
    let total = rounds.len() as u64 * (1 + ablations.len() as u64);
    let bar = if args.quiet || total < 2000 {
        ProgressBar::hidden()
    } else {
        let b = ProgressBar::new(total);
        b.set_style(
            ProgressStyle::with_template(
                "{spinner} {msg:<24} [{bar:40}] {pos}/{len} rounds ({per_sec}, eta {eta})",
            )
            .expect("static template")
            .progress_chars("=> "),
        );
        b
    };
    let l = ontology.len();
    let eps = cfg.eps;
    let mut done = 0u64;
    bar.set_message(format!("fusion ({})", cfg.method));
    let (engine, outcomes) = replay(engine, &rounds, &opts, &mut |_| {
        done += 1;
        if done.is_multiple_of(64) {
            bar.set_position(done);
        }
    })?;
    let mut rows = vec![Row {
        name: "fusion (full method)".into(),
        kind: "method",
        scores: score_method(&rounds, &outcomes, l, eps),
    }];
    for name in &ablations {
        bar.set_message(name.clone());
        let mut c = cfg.clone();
        c.ablations = Ablations::from_name(name).expect("checked above");
        let mut fresh = Engine::new(c, ontology.clone(), engine.reporters().to_vec())?;
        if let Some(d) = engine.dim() {
            fresh.fix_dim(d)?;
        }
        let (_, outs) = replay(fresh, &rounds, &opts, &mut |_| {
            done += 1;
            if done.is_multiple_of(64) {
                bar.set_position(done);
            }
        })?;
        rows.push(Row {
            name: format!("ablation: {name}"),
            kind: "ablation",
            scores: score_method(&rounds, &outs, l, eps),
        });
    }
    bar.finish_and_clear();
    rows.extend(baseline_rows(&rounds, n_hist, engine.reporters(), l, eps));
    Ok(EvalRun {
        engine,
        rounds,
        outcomes,
        rows,
        n_hist,
        labelled,
        available: all_rounds[..n_hist]
            .iter()
            .filter(|r| r.truth.is_some())
            .count(),
        seed: args.seed,
        pick: args.pick,
        review_pool: args.review_pool,
    })
}

/// Each reporter alone, majority vote and unsupervised Dawid–Skene: none of them uses a label,
/// so they are the same whatever `--labelled` hides.
fn baseline_rows(
    rounds: &[ParsedRound],
    n_hist: usize,
    reporters: &[String],
    l: usize,
    eps: f64,
) -> Vec<Row> {
    let mut rows: Vec<Row> = score_baselines(rounds, n_hist, reporters, l, eps)
        .into_iter()
        .map(|(name, scores)| Row {
            name: format!("baseline: {name}"),
            kind: "baseline",
            scores,
        })
        .collect();
    let post = dawid_skene(rounds, reporters.len(), l, DS_ITERS, DS_SMOOTHING);
    rows.push(Row {
        name: "baseline: Dawid-Skene (unsupervised)".into(),
        kind: "baseline",
        scores: score_posteriors(rounds, &post, n_hist, l, eps),
    });
    rows
}

const TABLE_NOTE: &str = "\nHamming: mean per-round share of wrong labels (lower is better). \
    Macro-F1 averages all labels; a label with no true and no predicted positive scores F1 = 1.\n\
    Baselines use no label; reporters and majority vote are hard 0/1 predictions, their Brier, \
    log loss and ECE score them as probabilities clipped to eps. A reporter missing from a round \
    counts as an empty label set in its own baseline. Dawid-Skene is fitted without truth on \
    every round of the file and predicts a label when its posterior exceeds 1/2.\n";

fn header(first: &str, width: usize) -> String {
    let mut s = format!(
        "{:<width$} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9}\n",
        first, "Hamming", "microF1", "macroF1", "Jaccard", "Brier", "LogLoss", "ECE", "lat(us)"
    );
    s.push_str(&format!("{}\n", "-".repeat(width + 9 * 8)));
    s
}

fn score_line(name: &str, c: &Scores, width: usize) -> String {
    let lat = c
        .latency_us
        .map(|v| format!("{v:9.1}"))
        .unwrap_or_else(|| format!("{:>9}", "-"));
    format!(
        "{:<width$} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {}\n",
        name, c.hamming, c.micro_f1, c.macro_f1, c.jaccard, c.brier, c.log_loss, c.ece, lat
    )
}

pub fn format_table(run: &EvalRun) -> String {
    let mut s = String::new();
    let scored = run.rows.first().map(|r| r.scores.rounds).unwrap_or(0);
    s.push_str(&format!(
        "{} rounds: {} history ({} labelled{}), {} scored (test rounds with truth); \
         method: {}\n\n",
        run.rounds.len(),
        run.n_hist,
        run.labelled,
        if run.labelled < run.available {
            format!(
                " of {}, {}",
                run.available,
                chosen_by(run.pick, run.seed, run.review_pool)
            )
        } else {
            String::new()
        },
        scored,
        run.engine.method()
    ));
    s.push_str(&header("model", 38));
    for r in &run.rows {
        s.push_str(&score_line(&r.name, &r.scores, 38));
    }
    s.push_str(TABLE_NOTE);
    let names = run.engine.reporters();
    let w = run.engine.reputations();
    s.push_str("Final reputations: ");
    s.push_str(
        &names
            .iter()
            .zip(w)
            .map(|(n, w)| format!("{n} {w:.4}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    s.push('\n');
    s
}

fn map_of(names: &[String], v: &[f64]) -> Value {
    Value::Object(
        names
            .iter()
            .zip(v)
            .map(|(n, x)| (n.clone(), json!(x)))
            .collect::<Map<_, _>>(),
    )
}

/// One docs/PAPER-METHOD.md §9 `--emit-rounds` line.
pub fn emit_line(engine: &Engine, o: &RoundOutcome) -> Value {
    let ont = engine.ontology();
    let labels: Vec<String> = ont.labels().iter().map(|l| l.id.clone()).collect();
    let reporters = engine.reporters();
    // One number when every label shares it; `adaptive`'s calibration maps a global threshold
    // per label (monotonically, like the posteriors), so those rounds carry the map.
    let uniform = o.thresholds.iter().all(|&t| t == o.thresholds[0]);
    let threshold = match engine.config().threshold_mode {
        ThresholdMode::Global if uniform => json!(o.thresholds[0]),
        _ => map_of(&labels, &o.thresholds),
    };
    let mut line = json!({
        "id": o.id,
        "q": map_of(&labels, &o.q),
        "threshold": threshold,
        "pred": ont.decode(&o.pred),
        "w_used": map_of(reporters, &o.w_used),
        "phi": o.phi.as_ref().map(|p| map_of(reporters, p)),
        "w_after": map_of(reporters, &o.w_after),
    });
    if let Some(se) = &o.shapley_std_error {
        line["phi_std_error"] = map_of(reporters, se);
    }
    line
}

fn report_json(run: &EvalRun, args: &EvalArgs) -> Value {
    json!({
        "file": args.rounds.display().to_string(),
        "method": run.engine.method().name(),
        "rounds": run.rounds.len(),
        "history": run.n_hist,
        "labelled_history": run.labelled,
        "seed": run.seed,
        "review_pool": run.review_pool,
        "split": args.split,
        "frozen": args.frozen,
        "reporters": run.engine.reporters(),
        "final_reputations": map_of(run.engine.reporters(), run.engine.reputations()),
        "macro_f1_note": "a label with no true and no predicted positive scores F1 = 1",
        "rows": run.rows.iter().map(|r| json!({
            "name": r.name,
            "kind": r.kind,
            "scores": r.scores,
        })).collect::<Vec<_>>(),
    })
}

/// Writes the table to stdout, ending its last line, and flushes it: what follows on stderr
/// (`wrote ...`, `eval took ...`) then starts a line of its own wherever the two streams meet.
fn print_report(text: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())?;
    if !text.ends_with('\n') {
        out.write_all(b"\n")?;
    }
    out.flush()?;
    Ok(())
}

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let (mut cfg, ontology) = load_fusion_config(args.config.as_deref())?;
    cfg.method = resolve_method(&args)?;
    let records = read_rounds(&args.rounds)?;
    if !args.curve.is_empty() {
        return run_curve(&cfg, &ontology, &records, &args, started);
    }
    let run = evaluate(&cfg, &ontology, &records, &args)
        .with_context(|| args.rounds.display().to_string())?;
    print_report(&format_table(&run))?;
    if let Some(path) = &args.emit_rounds {
        let at = || path.display().to_string();
        let f = File::create(path).with_context(at)?;
        let mut w = BufWriter::new(f);
        for o in &run.outcomes {
            serde_json::to_writer(&mut w, &emit_line(&run.engine, o)).with_context(at)?;
            w.write_all(b"\n").with_context(at)?;
        }
        w.flush().with_context(at)?;
    }
    if let Some(path) = &args.report {
        let text = serde_json::to_string_pretty(&report_json(&run, &args))?;
        std::fs::write(path, text).with_context(|| path.display().to_string())?;
    }
    if let Some(dir) = &args.plots {
        let files = plots::write_all(dir, &run)?;
        for f in files {
            eprintln!("wrote {}", f.display());
        }
    }
    eprintln!("eval took {:.3} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// One point of the learning curve: a method run with `labelled` history labels.
pub struct CurvePoint {
    pub keep: Keep,
    pub labelled: usize,
    /// How the labelled rounds were chosen (`random` or `review`).
    pub pick: Pick,
    pub method: Method,
    pub scores: Scores,
    pub final_w: Vec<f64>,
}

pub struct CurveRun {
    pub points: Vec<CurvePoint>,
    /// Reporters alone, majority vote, unsupervised Dawid–Skene (independent of N).
    pub baselines: Vec<Row>,
    pub reporters: Vec<String>,
    pub rounds: usize,
    pub n_hist: usize,
    pub available: usize,
    pub seed: u64,
    /// `--review-pool`: the share of history rounds the queue ranked.
    pub review_pool: f64,
    pub frozen: bool,
    /// Whether each N was run with both picks (`--pick compare`).
    pub compare: bool,
}

/// The methods a curve compares, in table order.
pub const CURVE_METHODS: [Method; 2] = [Method::Paper, Method::Adaptive];

/// Runs every method at every N of `--curve` on the same rounds (the same labelled subset for
/// both methods at a given N and seed).
pub fn evaluate_curve(
    cfg: &FusionConfig,
    ontology: &Ontology,
    records: &[(usize, RoundRecord)],
    args: &EvalArgs,
) -> anyhow::Result<CurveRun> {
    if !args.ablations.is_empty() || args.emit_rounds.is_some() {
        bail!(
            "--curve does not combine with --ablation or --emit-rounds; run those with \
             --labelled N instead"
        );
    }
    let (engine, all_rounds) = prepare(cfg, ontology, records)?;
    let n_hist = history_len(all_rounds.len(), args.split);
    let available = all_rounds[..n_hist]
        .iter()
        .filter(|r| r.truth.is_some())
        .count();
    let opts = ReplayOptions {
        split: args.split,
        frozen: args.frozen,
        batch_knn: !args.per_query_knn,
    };
    let picks: &[Pick] = match args.pick {
        Pick::Compare => &[Pick::Review, Pick::Random],
        Pick::Review => &[Pick::Review],
        Pick::Random => &[Pick::Random],
    };
    let total = (all_rounds.len() * args.curve.len() * CURVE_METHODS.len() * picks.len()) as u64;
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        let b = ProgressBar::new(total);
        b.set_style(
            ProgressStyle::with_template(
                "{spinner} {msg:<30} [{bar:40}] {pos}/{len} rounds ({per_sec}, eta {eta})",
            )
            .expect("static template")
            .progress_chars("=> "),
        );
        b
    };
    let l = ontology.len();
    let mut points = Vec::new();
    let mut done = 0u64;
    for &keep in &args.curve {
        for &pick in picks {
            let (rounds, labelled) = choose_labels(
                &all_rounds,
                n_hist,
                keep.limit(),
                pick,
                args.pool(),
                (engine.reporters().len(), l),
            );
            for method in CURVE_METHODS {
                bar.set_message(if picks.len() > 1 {
                    format!("{method}, N = {keep}, {}", pick.name())
                } else {
                    format!("{method}, N = {keep}")
                });
                let c = FusionConfig {
                    method,
                    ..cfg.clone()
                };
                let mut fresh = Engine::new(c, ontology.clone(), engine.reporters().to_vec())?;
                if let Some(d) = engine.dim() {
                    fresh.fix_dim(d)?;
                }
                let (end, outs) = replay(fresh, &rounds, &opts, &mut |_| {
                    done += 1;
                    if done.is_multiple_of(64) {
                        bar.set_position(done);
                    }
                })?;
                points.push(CurvePoint {
                    keep,
                    labelled,
                    pick,
                    method,
                    scores: score_method(&rounds, &outs, l, cfg.eps),
                    final_w: end.reputations().to_vec(),
                });
            }
        }
    }
    bar.finish_and_clear();
    Ok(CurveRun {
        points,
        baselines: baseline_rows(&all_rounds, n_hist, engine.reporters(), l, cfg.eps),
        reporters: engine.reporters().to_vec(),
        rounds: all_rounds.len(),
        n_hist,
        available,
        seed: args.seed,
        review_pool: args.review_pool,
        frozen: args.frozen,
        compare: picks.len() > 1,
    })
}

/// How the labelled history rounds were chosen, in words.
fn chosen_by(pick: Pick, seed: u64, pool: f64) -> String {
    let queue = if pool < 1.0 {
        format!("the review queue over a share {pool} of the history chosen by seed {seed}")
    } else {
        "the review queue".into()
    };
    match pick {
        Pick::Random => format!("chosen by seed {seed}"),
        Pick::Review => format!("chosen by {queue}"),
        Pick::Compare => format!("chosen by {queue} and, for comparison, by seed {seed}"),
    }
}

pub fn format_curve(c: &CurveRun) -> String {
    let mut s = format!(
        "learning curve: {} rounds, {} history ({} with truth), {} scored; labelled rounds \
         {}{}\n\n",
        c.rounds,
        c.n_hist,
        c.available,
        c.baselines.first().map(|b| b.scores.rounds).unwrap_or(0),
        chosen_by(
            if c.compare {
                Pick::Compare
            } else {
                c.points.first().map_or(Pick::Random, |p| p.pick)
            },
            c.seed,
            c.review_pool
        ),
        if c.frozen {
            "; frozen after the history"
        } else {
            "; learning continues on the scored rounds"
        }
    );
    s.push_str(&header("labelled  method", 38));
    for p in &c.points {
        let name = if c.compare {
            format!("{:<9} {} ({})", p.labelled, p.method, p.pick.name())
        } else {
            format!("{:<9} {}", p.labelled, p.method)
        };
        s.push_str(&score_line(&name, &p.scores, 38));
    }
    s.push('\n');
    s.push_str(&header("baseline (no labels used)", 38));
    for b in &c.baselines {
        let name = b.name.trim_start_matches("baseline: ");
        s.push_str(&score_line(name, &b.scores, 38));
    }
    s.push_str(TABLE_NOTE);
    s.push_str("Final reputations:\n");
    for p in &c.points {
        s.push_str(&format!(
            "  {:<9} {:<9} {}{}\n",
            p.labelled,
            p.method.name(),
            if c.compare {
                format!("({}) ", p.pick.name())
            } else {
                String::new()
            },
            c.reporters
                .iter()
                .zip(&p.final_w)
                .map(|(n, w)| format!("{n} {w:.4}"))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    s
}

fn curve_json(c: &CurveRun, args: &EvalArgs) -> Value {
    json!({
        "file": args.rounds.display().to_string(),
        "rounds": c.rounds,
        "history": c.n_hist,
        "history_with_truth": c.available,
        "seed": c.seed,
        "review_pool": c.review_pool,
        "split": args.split,
        "frozen": c.frozen,
        "reporters": c.reporters,
        "macro_f1_note": "a label with no true and no predicted positive scores F1 = 1",
        "points": c.points.iter().map(|p| json!({
            "requested": p.keep.to_string(),
            "labelled": p.labelled,
            "pick": p.pick.name(),
            "method": p.method.name(),
            "scores": p.scores,
            "final_reputations": map_of(&c.reporters, &p.final_w),
        })).collect::<Vec<_>>(),
        "baselines": c.baselines.iter().map(|r| json!({
            "name": r.name,
            "scores": r.scores,
        })).collect::<Vec<_>>(),
    })
}

fn run_curve(
    cfg: &FusionConfig,
    ontology: &Ontology,
    records: &[(usize, RoundRecord)],
    args: &EvalArgs,
    started: Instant,
) -> anyhow::Result<()> {
    let c = evaluate_curve(cfg, ontology, records, args)
        .with_context(|| args.rounds.display().to_string())?;
    print_report(&format_curve(&c))?;
    if let Some(path) = &args.report {
        let text = serde_json::to_string_pretty(&curve_json(&c, args))?;
        std::fs::write(path, text).with_context(|| path.display().to_string())?;
    }
    if let Some(dir) = &args.plots {
        for f in plots::write_curve(dir, &c)? {
            eprintln!("wrote {}", f.display());
        }
    }
    eprintln!("eval took {:.3} s", started.elapsed().as_secs_f64());
    Ok(())
}
