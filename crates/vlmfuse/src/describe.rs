//! `vlmfuse describe CLIP --config FILE --reporter NAME [--dump DIR]`: one reporter on one clip,
//! as `/v1/infer` would run it (the config's `[media]` sampling, the reporter's settings, the
//! configured labeler), printing the answer and its labels. Users need it to check a checkpoint
//! before serving it; `--dump` writes the in-process model's inputs and first logits so anyone
//! can compare them with the reference implementation (`scripts/parity/check_dump.py`).

use crate::config::{Config, ReporterBackend, ServeArgs};
use crate::wire::LabelOut;
use anyhow::{bail, Context};
use clap::Args;
use serde_json::json;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;
use vlmfuse_models::reporter::Trace;
use vlmfuse_models::{CandleVlmReporter, ClipInput, ClipMeta, Frame, Reporter};

#[derive(Args, Debug, Clone)]
pub struct DescribeArgs {
    /// The clip (any container and codec the service accepts).
    pub clip: PathBuf,
    /// TOML configuration with the `[[reporter]]`, `[media]`, `[labeler]` and `[[ontology]]`
    /// to use, as `vlmfuse serve --config`.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: PathBuf,
    /// The `name` of the `[[reporter]]` to run.
    #[arg(long)]
    pub reporter: String,
    /// Also write the in-process model's inputs and outputs here: `input_ids.json`,
    /// `pixel_values.npy`, `grid.json`, `first_token_logits.npy`, `generated_ids.json`,
    /// `step_logits.npy` (`[tokens, vocab]`: the logits each generated token, the stop token
    /// included, was chosen from), `generated_steps.json` (each token's logit and
    /// log-probability), `frames.json` and `meta.json` (created if missing). Only for
    /// `kind = "candle"` reporters.
    #[arg(long)]
    pub dump: Option<PathBuf>,
    /// Print one JSON object instead of the readable report.
    #[arg(long)]
    pub json: bool,
    /// Do not label the answer (no labeler is loaded).
    #[arg(long)]
    pub no_labels: bool,
    /// No progress lines on standard error.
    #[arg(long)]
    pub quiet: bool,
}

/// What the reporter produced, whatever its kind.
struct Answer {
    text: String,
    model: String,
    /// In-process reporters: the trace of the generation.
    trace: Option<Trace>,
    ms: f64,
}

fn config(path: &Path) -> anyhow::Result<Config> {
    let argv = [
        "serve".to_string(),
        "--config".into(),
        path.display().to_string(),
    ];
    Config::load(&ServeArgs::try_parse_from(argv)?)
}

/// A spinner on standard error while a long step runs (loading a 7B checkpoint, generating on
/// the CPU), when it is a terminal; nothing otherwise.
fn spinner(quiet: bool, msg: String) -> Option<indicatif::ProgressBar> {
    use std::io::IsTerminal;
    if quiet || !std::io::stderr().is_terminal() {
        return None;
    }
    let b = indicatif::ProgressBar::new_spinner();
    b.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} {elapsed}").expect("template"),
    );
    b.set_message(msg);
    b.enable_steady_tick(std::time::Duration::from_millis(120));
    Some(b)
}

pub fn run(args: DescribeArgs) -> anyhow::Result<()> {
    let say = |m: String| {
        if !args.quiet {
            eprintln!("{m}");
        }
    };
    let done = |b: Option<indicatif::ProgressBar>| {
        if let Some(b) = b {
            b.finish_and_clear();
        }
    };
    let cfg = config(&args.config)?;
    let entry = cfg
        .reporter
        .iter()
        .find(|r| r.name() == args.reporter)
        .cloned()
        .ok_or_else(|| {
            let names: Vec<String> = cfg.reporter.iter().map(|r| r.name()).collect();
            if names.is_empty() {
                anyhow::anyhow!(
                    "no reporter `{}`: {} configures no [[reporter]]",
                    args.reporter,
                    args.config.display()
                )
            } else {
                anyhow::anyhow!(
                    "no reporter `{}` in {}; configured: {}",
                    args.reporter,
                    args.config.display(),
                    names.join(", ")
                )
            }
        })?;
    let candle = match &entry.backend {
        ReporterBackend::Candle(c) => Some(c.clone()),
        ReporterBackend::Openai(_) => None,
    };
    if args.dump.is_some() && candle.is_none() {
        bail!(
            "--dump needs an in-process reporter (kind = \"candle\"); `{}` is kind = \"openai\", \
             whose inputs are built by its server",
            args.reporter
        );
    }
    if !args.clip.is_file() {
        bail!(
            "clip {} does not exist (or is not a file)",
            args.clip.display()
        );
    }

    // Decode first: a bad clip should fail before minutes of model loading.
    let t0 = Instant::now();
    let decoded =
        vlmfuse_media::sample_frames(&args.clip, &cfg.media.sample_options(), &cfg.media.limits())
            .with_context(|| format!("decoding {}", args.clip.display()))?;
    let info = decoded.info.clone();
    let times = decoded.timestamps();
    let frames: Arc<[Frame]> = decoded.frames.into_iter().map(|f| f.frame).collect();
    say(format!(
        "clip {}: {} {}x{}, {:.2} s at {:.2} fps; {} frames sampled at {:?} s ({:.0} ms)",
        args.clip.display(),
        info.codec,
        info.width,
        info.height,
        info.duration_s,
        info.fps,
        frames.len(),
        times
            .iter()
            .map(|t| (t * 100.0).round() / 100.0)
            .collect::<Vec<_>>(),
        t0.elapsed().as_secs_f64() * 1e3
    ));

    let labeler = if args.no_labels {
        None
    } else {
        let t = Instant::now();
        let l = crate::service::pipeline::load_labeler(&cfg).context("loading the labeler")?;
        say(format!(
            "labeler {} loaded in {:.1} s",
            l.name(),
            t.elapsed().as_secs_f64()
        ));
        Some(l)
    };

    let rt = tokio::runtime::Runtime::new().context("starting the runtime")?;
    // The frames the in-process model took, and whether its own sampler chose them.
    let mut frames_used: Option<(bool, Arc<[Frame]>)> = None;
    // The in-process model's end-of-sequence ids and prompt, for `--dump`.
    let mut model_meta = serde_json::Value::Null;
    let answer = match candle {
        Some(c) => {
            let t = Instant::now();
            say(format!(
                "loading `{}` from {} on {} ...",
                c.name,
                c.weights.describe(),
                c.device
            ));
            let bar = spinner(args.quiet, "loading".into());
            let r = CandleVlmReporter::load(c);
            done(bar);
            let r = r.with_context(|| format!("loading reporter `{}`", args.reporter))?;
            say(format!(
                "loaded {} ({:?} on {}) in {:.1} s; generating up to {} tokens ...",
                r.family().model_type(),
                r.family().dtype(),
                r.config().device,
                t.elapsed().as_secs_f64(),
                r.config().max_new_tokens
            ));
            // The checkpoint's own sampler, when it has one in force, as the service does.
            let own =
                match vlmfuse_models::LocalReporter::frame_times(&r, info.duration_s, info.fps) {
                    Some(times) => {
                        let size = match vlmfuse_models::LocalReporter::frame_size(&r) {
                            Some((width, height)) => {
                                vlmfuse_media::FrameSize::Exact { width, height }
                            }
                            None => vlmfuse_media::FrameSize::Native,
                        };
                        let d = vlmfuse_media::sample_frames_at(
                            &args.clip,
                            &times,
                            size,
                            &cfg.media.limits(),
                            &vlmfuse_media::Interrupt::new(),
                        )
                        .with_context(|| format!("decoding {}", args.clip.display()))?;
                        let f: Arc<[Frame]> = d.frames.into_iter().map(|f| f.frame).collect();
                        say(format!(
                            "the checkpoint's sampler takes {} frames at {:?} s",
                            f.len(),
                            f.iter()
                                .map(|f| (f.pts_s * 100.0).round() / 100.0)
                                .collect::<Vec<_>>()
                        ));
                        Some(f)
                    }
                    None => None,
                };
            let used = own.clone().unwrap_or_else(|| frames.clone());
            frames_used = Some((own.is_some(), used.clone()));
            model_meta = json!({"eos_ids": r.family().eos_ids(), "prompt": r.config().prompt});
            let t = Instant::now();
            let bar = spinner(args.quiet, "generating".into());
            let trace = r.trace(&used, &AtomicBool::new(false));
            done(bar);
            let trace = trace.with_context(|| format!("running reporter `{}`", args.reporter))?;
            Answer {
                text: trace.generation.text.clone(),
                model: format!("{} ({})", r.config().name, trace.model_type),
                trace: Some(trace),
                ms: t.elapsed().as_secs_f64() * 1e3,
            }
        }
        None => {
            let ReporterBackend::Openai(mut c) = entry.backend.clone() else {
                unreachable!("matched above")
            };
            c.name = Some(entry.name());
            let r = vlmfuse_models::OpenAiReporter::new(c)
                .with_context(|| format!("reporter `{}`", args.reporter))?;
            let clip = ClipInput {
                path: args.clip.clone(),
                frames: frames.clone(),
                meta: ClipMeta {
                    clip_id: args.clip.file_name().map(|n| n.to_string_lossy().into()),
                    duration_s: Some(info.duration_s),
                    fps: Some(info.fps),
                    width: Some(info.width),
                    height: Some(info.height),
                    ..ClipMeta::default()
                },
            };
            say(format!("asking `{}` ...", args.reporter));
            let t = Instant::now();
            let bar = spinner(args.quiet, "waiting for the server".into());
            let out = rt.block_on(r.run(&clip));
            done(bar);
            let out = out.with_context(|| format!("running reporter `{}`", args.reporter))?;
            Answer {
                text: out.text,
                model: out.model,
                trace: None,
                ms: t.elapsed().as_secs_f64() * 1e3,
            }
        }
    };

    let labels = match &labeler {
        Some(l) => Some(LabelOut::from(
            rt.block_on(l.label(&answer.text))
                .context("labelling the answer")?,
        )),
        None => None,
    };

    if let (Some(dir), Some(trace)) = (&args.dump, &answer.trace) {
        let (own, used) = frames_used.clone().unwrap_or((false, frames.clone()));
        let sampled = json!({
            "sampler": if own { "checkpoint" } else { "media" },
            "clip_fps": info.fps,
            "clip_duration_s": info.duration_s,
            "timestamps_s": used.iter().map(|f| f.pts_s).collect::<Vec<_>>(),
            // The frame numbers, from the timestamps at the clip's average rate.
            "indices": used.iter().map(|f| (f.pts_s * info.fps).round() as i64).collect::<Vec<_>>(),
            "sizes": used.iter().map(|f| [f.width, f.height]).collect::<Vec<_>>(),
            // SHA-256 of each frame's RGB24 bytes, to check a reference decoded the same pixels.
            "sha256": used.iter().map(|f| {
                use sha2::Digest;
                format!("{:x}", sha2::Sha256::digest(&f.rgb))
            }).collect::<Vec<_>>(),
            "media": {"frames": cfg.media.frames, "frame_short_side": cfg.media.frame_short_side},
        });
        let files = write_dump(dir, trace, &args, &cfg, sampled, model_meta.clone())?;
        say(format!("wrote {} files to {}", files.len(), dir.display()));
    }

    let mut out = std::io::stdout().lock();
    if args.json {
        let mut v = json!({
            "clip": args.clip.display().to_string(),
            "reporter": args.reporter,
            "model": answer.model,
            "answer": answer.text,
            "frames": frames.len(),
            "timestamps_s": times,
            "reporter_ms": answer.ms,
        });
        if let Some(l) = &labels {
            v["labels"] = json!(l.labels);
            v["evidence"] = serde_json::to_value(&l.evidence)?;
        }
        if let Some(t) = &answer.trace {
            let g = &t.generation;
            v["model_type"] = json!(t.model_type);
            v["generated_ids"] = json!(g.tokens);
            v["prompt_tokens"] = json!(g.prompt_tokens);
            v["visual_tokens"] = json!(g.visual_tokens);
            v["prefill_ms"] = json!(g.prefill_ms);
            v["decode_ms"] = json!(g.decode_ms);
            v["tokens_per_s"] = json!(g.tokens_per_s());
        }
        writeln!(out, "{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    writeln!(out, "reporter: {} ({:.0} ms)", answer.model, answer.ms)?;
    if let Some(t) = &answer.trace {
        let g = &t.generation;
        writeln!(
            out,
            "prompt: {} tokens ({} visual); generated {} tokens; prefill {:.0} ms, {:.1} tokens/s",
            g.prompt_tokens,
            g.visual_tokens,
            g.tokens.len(),
            g.prefill_ms,
            g.tokens_per_s()
        )?;
    }
    writeln!(out, "answer:")?;
    for line in answer.text.lines() {
        writeln!(out, "  {line}")?;
    }
    if answer.text.trim().is_empty() {
        writeln!(out, "  (empty)")?;
    }
    if let Some(l) = &labels {
        let names = if l.labels.is_empty() {
            "(none)".to_string()
        } else {
            l.labels.join(", ")
        };
        writeln!(out, "labels: {names}")?;
        crate::label::write_evidence(&mut out, l)?;
    }
    Ok(())
}

/// Writes the trace as the reference scripts read it. Every array is f32 (`.npy`) or a JSON
/// list of ints, row-major, in the layouts the model's vision tower and text model take.
fn write_dump(
    dir: &Path,
    t: &Trace,
    args: &DescribeArgs,
    cfg: &Config,
    frames: serde_json::Value,
    model: serde_json::Value,
) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = Vec::new();
    let mut json_file = |name: &str, v: serde_json::Value| -> anyhow::Result<()> {
        let p = dir.join(name);
        std::fs::write(&p, serde_json::to_string_pretty(&v)? + "\n")
            .with_context(|| format!("writing {}", p.display()))?;
        written.push(p);
        Ok(())
    };
    json_file("input_ids.json", json!(t.input_ids))?;
    json_file("frames.json", frames)?;
    json_file("grid.json", t.grid.clone())?;
    json_file("generated_ids.json", json!(t.generation.tokens))?;
    let weights = cfg.reporter.iter().find_map(|r| match &r.backend {
        ReporterBackend::Candle(c) if c.name == args.reporter => Some(c.clone()),
        _ => None,
    });
    json_file(
        "meta.json",
        json!({
            "model_type": t.model_type,
            "reporter": args.reporter,
            "clip": args.clip.display().to_string(),
            "weights": weights.as_ref().and_then(|c| c.weights.resolve("config.json").ok())
                .and_then(|p| p.parent().map(|d| d.display().to_string())),
            "adapter": weights.as_ref().and_then(|c| c.adapter.as_ref()).map(|a| a.describe()),
            "dtype": weights.as_ref().and_then(|c| c.dtype.clone()),
            "max_new_tokens": weights.as_ref().map(|c| c.max_new_tokens),
            "vocab": t.first_token_logits.len(),
            "eos_ids": model["eos_ids"],
            "prompt": model["prompt"],
        }),
    )?;
    let npy = |name: &str, tensor: &candle_core::Tensor| -> anyhow::Result<PathBuf> {
        let p = dir.join(name);
        tensor
            .write_npy(&p)
            .with_context(|| format!("writing {}", p.display()))?;
        Ok(p)
    };
    if let Some(px) = &t.pixel_values {
        written.push(npy("pixel_values.npy", px)?);
    }
    let logits = candle_core::Tensor::from_slice(
        &t.first_token_logits,
        t.first_token_logits.len(),
        &candle_core::Device::Cpu,
    )?;
    written.push(npy("first_token_logits.npy", &logits)?);
    if !t.step_logits.is_empty() {
        // One row per generated token (the stop token's too): the distribution it was picked
        // from, and the picked token's logit and log-probability in generated_steps.json.
        let vocab = t.step_logits[0].len();
        let flat: Vec<f32> = t.step_logits.iter().flatten().copied().collect();
        let steps = candle_core::Tensor::from_vec(
            flat,
            (t.step_logits.len(), vocab),
            &candle_core::Device::Cpu,
        )?;
        written.push(npy("step_logits.npy", &steps)?);
        let mut ids = t.generation.tokens.clone();
        ids.extend(t.stop);
        let rows: Vec<serde_json::Value> = t
            .step_logits
            .iter()
            .zip(&ids)
            .enumerate()
            .map(|(i, (row, &id))| {
                let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let lse = max as f64
                    + row
                        .iter()
                        .map(|&x| ((x - max) as f64).exp())
                        .sum::<f64>()
                        .ln();
                let logit = row.get(id as usize).copied().unwrap_or(f32::NAN);
                json!({"step": i, "id": id, "logit": logit, "logprob": logit as f64 - lse})
            })
            .collect();
        let p = dir.join("generated_steps.json");
        std::fs::write(&p, serde_json::to_string_pretty(&json!(rows))? + "\n")
            .with_context(|| format!("writing {}", p.display()))?;
        written.push(p);
    }
    Ok(written)
}
