//! `vlmfuse label FILE|-`: the served labeler on the command line, with the evidence for each
//! label, so that a user can see why a label was chosen without starting the service.
//!
//! The labeler is built from the same configuration, by the same function, as the one
//! `vlmfuse serve` runs behind `/v1/infer` and `/v1/label` (`service::pipeline::load_labeler`),
//! and answers are labelled in rounds through `Labeler::label_batch`, as the service does.

use crate::config::{Config, ServeArgs};
use crate::wire::LabelOut;
use anyhow::{bail, Context};
use clap::Args;
use serde_json::Value;
use std::io::{IsTerminal, Read, Write};
use std::path::PathBuf;

/// Answers labelled per call: big enough that the encoder batches well, small enough that the
/// progress bar moves.
const CHUNK: usize = 16;

#[derive(Args, Debug, Clone)]
pub struct LabelArgs {
    /// The answer to label: a text file, or `-` for standard input. With `--jsonl`, one answer
    /// per line.
    pub input: PathBuf,
    /// One answer per line: a JSON string, or an object with a `"text"` field (its `"id"`, if
    /// any, is kept in the output). Blank lines are skipped.
    #[arg(long)]
    pub jsonl: bool,
    /// Print one JSON object per answer (the shape of `POST /v1/label`'s result) instead of a
    /// readable listing.
    #[arg(long)]
    pub json: bool,
    /// TOML configuration whose `[labeler]` and `[[ontology]]` are used, as `vlmfuse serve
    /// --config`; built-in defaults (config/default.toml) without it. The environment variables
    /// of `serve` (`VLMFUSE_ASSETS`, ...) apply too.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: Option<PathBuf>,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// A `--json` output line: the answer's id and line (when it has them), then `/v1/label`'s
/// result, serialised directly so that the scores stay in ontology order.
#[derive(serde::Serialize)]
struct JsonRow<'a> {
    #[serde(skip_serializing_if = "Option::is_none")]
    id: Option<&'a Value>,
    #[serde(skip_serializing_if = "Option::is_none")]
    line: Option<usize>,
    #[serde(flatten)]
    out: &'a LabelOut,
}

/// One answer read from the input.
struct Answer {
    /// 1-based line of the input (1 for a whole-file answer).
    line: usize,
    id: Option<Value>,
    text: String,
}

fn read_input(args: &LabelArgs) -> anyhow::Result<String> {
    if args.input.as_os_str() == "-" {
        let mut s = String::new();
        std::io::stdin()
            .read_to_string(&mut s)
            .context("reading standard input")?;
        Ok(s)
    } else {
        std::fs::read_to_string(&args.input)
            .with_context(|| format!("cannot read {}", args.input.display()))
    }
}

fn parse_answers(args: &LabelArgs, input: &str) -> anyhow::Result<Vec<Answer>> {
    let name = if args.input.as_os_str() == "-" {
        "<stdin>".to_string()
    } else {
        args.input.display().to_string()
    };
    if !args.jsonl {
        if input.trim().is_empty() {
            bail!("{name} is empty: there is no answer to label");
        }
        return Ok(vec![Answer {
            line: 1,
            id: None,
            text: input.to_string(),
        }]);
    }
    let mut out = Vec::new();
    for (i, l) in input.lines().enumerate() {
        if l.trim().is_empty() {
            continue;
        }
        let at = || format!("{name}:{}", i + 1);
        let v: Value = serde_json::from_str(l).with_context(|| format!("{}: not JSON", at()))?;
        let (id, text) = match v {
            Value::String(t) => (None, t),
            Value::Object(mut o) => match o.remove("text") {
                Some(Value::String(t)) => (o.remove("id"), t),
                Some(_) => bail!("{}: \"text\" is not a string", at()),
                None => bail!("{}: the object has no \"text\" field", at()),
            },
            _ => bail!(
                "{}: expected a JSON string or an object with \"text\"",
                at()
            ),
        };
        out.push(Answer {
            line: i + 1,
            id,
            text,
        });
    }
    if out.is_empty() {
        bail!("{name} has no answers (every line is blank)");
    }
    Ok(out)
}

/// The configuration `serve` would run with: the file (or defaults), then its variables.
fn config(args: &LabelArgs) -> anyhow::Result<Config> {
    let mut argv = vec!["serve".to_string()];
    if let Some(p) = &args.config {
        argv.push("--config".into());
        argv.push(p.display().to_string());
    }
    Config::load(&ServeArgs::try_parse_from(argv)?)
}

pub fn run(args: LabelArgs) -> anyhow::Result<()> {
    let answers = parse_answers(&args, &read_input(&args)?)?;
    let cfg = config(&args)?;
    let t0 = std::time::Instant::now();
    let labeler = crate::service::pipeline::load_labeler(&cfg).context("loading the labeler")?;
    if !args.quiet {
        eprintln!(
            "labeler {} loaded in {:.1}s",
            labeler.name(),
            t0.elapsed().as_secs_f64()
        );
    }
    let rt = tokio::runtime::Runtime::new().context("starting the runtime")?;
    let bar =
        (!args.quiet && answers.len() > CHUNK && std::io::stderr().is_terminal()).then(|| {
            let b = indicatif::ProgressBar::new(answers.len() as u64);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{bar:40} {pos}/{len} answers, {per_sec}, eta {eta}",
                )
                .expect("valid template"),
            );
            b
        });
    let mut stdout = std::io::stdout().lock();
    for chunk in answers.chunks(CHUNK) {
        let texts: Vec<&str> = chunk.iter().map(|a| a.text.as_str()).collect();
        let outs = rt
            .block_on(labeler.label_batch(&texts))
            .with_context(|| format!("labelling the answers from line {}", chunk[0].line))?;
        for (a, o) in chunk.iter().zip(outs) {
            let out = LabelOut::from(o);
            if args.json {
                let row = JsonRow {
                    id: a.id.as_ref(),
                    line: args.jsonl.then_some(a.line),
                    out: &out,
                };
                writeln!(stdout, "{}", serde_json::to_string(&row)?)?;
            } else {
                write_readable(&mut stdout, a, &out, args.jsonl)?;
            }
        }
        if let Some(b) = &bar {
            b.inc(chunk.len() as u64);
        }
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    Ok(())
}

fn write_readable(
    w: &mut impl Write,
    a: &Answer,
    out: &LabelOut,
    numbered: bool,
) -> std::io::Result<()> {
    let head = match (&a.id, numbered) {
        (Some(Value::String(id)), _) => format!("{id}: "),
        (Some(id), _) => format!("{id}: "),
        (None, true) => format!("line {}: ", a.line),
        (None, false) => String::new(),
    };
    let labels = if out.labels.is_empty() {
        "(none)".to_string()
    } else {
        out.labels.join(", ")
    };
    writeln!(w, "{head}{labels}")?;
    write_evidence(w, out)
}

/// One line per evidence item: on or discounted, label, how, source, score, clause.
pub(crate) fn write_evidence(w: &mut impl Write, out: &LabelOut) -> std::io::Result<()> {
    for e in &out.evidence {
        let how = match (e.accepted, e.negated, e.hedged) {
            (true, _, _) => "on",
            (false, true, _) => "negated",
            (false, _, true) => "hedged",
            (false, false, false) => "not counted",
        };
        let source = serde_json::to_value(e.source)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default();
        let clause = if e.clause.is_empty() {
            "(the whole answer)".to_string()
        } else {
            format!("{:?}", e.clause)
        };
        writeln!(
            w,
            "  {} {:<28} {:<11} {:<9} {:.2}  {clause}",
            if e.accepted { "+" } else { "-" },
            e.label,
            how,
            source,
            e.score
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn args(jsonl: bool) -> LabelArgs {
        LabelArgs {
            input: "answers.jsonl".into(),
            jsonl,
            json: false,
            config: None,
            quiet: true,
        }
    }

    #[test]
    fn jsonl_lines_are_strings_or_objects_and_mistakes_name_their_line() {
        let a = parse_answers(
            &args(true),
            "\"Brake.\"\n\n{\"id\": \"a-7\", \"text\": \"Stop.\"}\n",
        )
        .unwrap();
        assert_eq!(a.len(), 2);
        assert_eq!((a[0].line, a[0].text.as_str()), (1, "Brake."));
        assert_eq!((a[1].line, a[1].id.clone()), (3, Some(json!("a-7"))));
        for (bad, want) in [
            (
                "\"ok\"\n{\"txt\": \"x\"}",
                "answers.jsonl:2: the object has no \"text\"",
            ),
            ("{\"text\": 3}", "answers.jsonl:1: \"text\" is not a string"),
            ("[1]", "answers.jsonl:1: expected a JSON string"),
            ("{oops", "answers.jsonl:1: not JSON"),
            ("\n  \n", "has no answers"),
        ] {
            let e = format!("{:#}", parse_answers(&args(true), bad).err().unwrap());
            assert!(e.contains(want), "{bad:?}: {e}");
        }
    }

    #[test]
    fn a_whole_file_is_one_answer_and_an_empty_one_is_refused() {
        let a = parse_answers(&args(false), "1. Scene: x\n2. Brake.\n").unwrap();
        assert_eq!(a.len(), 1);
        assert!(a[0].text.contains("Brake."));
        let e = parse_answers(&args(false), " \n").err().unwrap();
        assert!(e.to_string().contains("empty"), "{e}");
    }
}
