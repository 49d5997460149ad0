//! `vlmfuse eval`: the paper's protocol over a rounds file (SPEC §9), with the metrics table of
//! SPEC §7 for the method, each requested ablation and the baselines.

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
use vlmfuse_fusion::metrics::Scores;
use vlmfuse_fusion::replay::{
    history_len, prepare, replay, score_baselines, score_method, ParsedRound, ReplayOptions,
    RoundOutcome,
};
use vlmfuse_fusion::{
    Ablations, Engine, FusionConfig, Label, Ontology, RoundRecord, ThresholdMode,
};

#[derive(Args, Debug, Clone)]
pub struct EvalArgs {
    /// Rounds file: JSON Lines, one SPEC §8 round a line.
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
    /// Write one line per round of the full method (SPEC §9 fields).
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
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
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
    Ok((file.fusion.unwrap_or_default(), ontology))
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
    let (engine, rounds) = prepare(cfg, ontology, records)?;
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
    let n_hist = history_len(rounds.len(), args.split);
    let mut done = 0u64;
    bar.set_message("fusion");
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
    for (name, scores) in score_baselines(&rounds, n_hist, engine.reporters(), l, eps) {
        rows.push(Row {
            name: format!("baseline: {name}"),
            kind: "baseline",
            scores,
        });
    }
    Ok(EvalRun {
        engine,
        rounds,
        outcomes,
        rows,
        n_hist,
    })
}

pub fn format_table(run: &EvalRun) -> String {
    let mut s = String::new();
    let scored = run.rows.first().map(|r| r.scores.rounds).unwrap_or(0);
    s.push_str(&format!(
        "{} rounds: {} history, {} scored (test rounds with truth)\n\n",
        run.rounds.len(),
        run.n_hist,
        scored
    ));
    s.push_str(&format!(
        "{:<34} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9}\n",
        "model", "Hamming", "microF1", "macroF1", "Jaccard", "Brier", "LogLoss", "ECE", "lat(us)"
    ));
    s.push_str(&format!("{}\n", "-".repeat(34 + 9 * 8)));
    for r in &run.rows {
        let c = &r.scores;
        let lat = c
            .latency_us
            .map(|v| format!("{v:9.1}"))
            .unwrap_or_else(|| format!("{:>9}", "-"));
        s.push_str(&format!(
            "{:<34} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {}\n",
            r.name, c.hamming, c.micro_f1, c.macro_f1, c.jaccard, c.brier, c.log_loss, c.ece, lat
        ));
    }
    s.push_str(
        "\nHamming: mean per-round share of wrong labels (lower is better). Macro-F1 averages all \
         labels; a label with no true and no predicted positive scores F1 = 1.\nBaselines are hard \
         0/1 predictions; their Brier, log loss and ECE score them as probabilities clipped to eps. \
         A reporter missing from a round counts as an empty label set in its own baseline.\n",
    );
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

/// One SPEC §9 `--emit-rounds` line.
pub fn emit_line(engine: &Engine, o: &RoundOutcome) -> Value {
    let ont = engine.ontology();
    let labels: Vec<String> = ont.labels().iter().map(|l| l.id.clone()).collect();
    let reporters = engine.reporters();
    let threshold = match engine.config().threshold_mode {
        ThresholdMode::Global => json!(o.thresholds[0]),
        ThresholdMode::PerLabel => map_of(&labels, &o.thresholds),
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
        "rounds": run.rounds.len(),
        "history": run.n_hist,
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

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let (cfg, ontology) = load_fusion_config(args.config.as_deref())?;
    let records = read_rounds(&args.rounds)?;
    let run = evaluate(&cfg, &ontology, &records, &args)
        .with_context(|| args.rounds.display().to_string())?;
    print!("{}", format_table(&run));
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
