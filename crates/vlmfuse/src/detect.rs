//! `vlmfuse detect IMAGE|CLIP`: the object detector on one image or on a clip's sampled frames,
//! with the tracker and the label rules of `[detect]` (the same path as `/v1/infer`): every
//! detection, then the labels with their evidence. `--bench N` times the detector per frame
//! (letterbox, ONNX Runtime, NMS) instead.

use crate::config::{Config, ServeArgs};
use anyhow::{bail, Context};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use vlmfuse_detect::{Detector, FrameDetections};
use vlmfuse_models::Frame;

#[derive(Args, Debug, Clone)]
pub struct DetectArgs {
    /// A PNG or JPEG image, or a video clip (its frames are sampled as the service samples
    /// them).
    pub input: PathBuf,
    /// The YOLO ONNX export (default: `[detect] model` of the configuration).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Frames sampled from a clip (default: `[detect] frames`, else `[media] frames`).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Print the detections and the annotation as JSON (`detected` of `/v1/infer`'s answer).
    #[arg(long)]
    pub json: bool,
    /// Time the detector over this many runs on each frame and print milliseconds per frame.
    #[arg(long)]
    pub bench: Option<usize>,
    /// Intra-op threads of the session (default: `[detect] threads`, else one per core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// TOML configuration whose `[detect]` and `[media]` are used, as `vlmfuse serve --config`.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: Option<PathBuf>,
}

fn is_image(p: &std::path::Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
}

fn frames_of(args: &DetectArgs, cfg: &Config) -> anyhow::Result<Vec<Frame>> {
    if is_image(&args.input) {
        let img = image::open(&args.input)
            .with_context(|| format!("cannot read image {}", args.input.display()))?
            .to_rgb8();
        return Ok(vec![Frame {
            width: img.width(),
            height: img.height(),
            rgb: img.into_raw(),
            pts_s: 0.0,
        }]);
    }
    let n = args
        .frames
        .or((cfg.detect.frames > 0).then_some(cfg.detect.frames))
        .unwrap_or(cfg.media.frames);
    let opts = vlmfuse_media::SampleOptions {
        frames: n,
        ..cfg.media.sample_options()
    };
    let decoded = vlmfuse_media::sample_frames(&args.input, &opts, &cfg.media.limits())
        .with_context(|| format!("cannot sample frames of {}", args.input.display()))?;
    Ok(decoded.frames.into_iter().map(|f| f.frame).collect())
}

pub fn run(args: DetectArgs) -> anyhow::Result<()> {
    let mut argv = vec!["serve".to_string()];
    if let Some(p) = &args.config {
        argv.push("--config".into());
        argv.push(p.display().to_string());
    }
    let cfg = Config::load(&ServeArgs::try_parse_from(argv)?)?;
    let mut dc = match (&args.model, cfg.detect.detector_config()) {
        (Some(m), Some(dc)) => vlmfuse_detect::DetectorConfig {
            model: m.clone(),
            ..dc
        },
        (Some(m), None) => vlmfuse_detect::DetectorConfig {
            model: m.clone(),
            nms: cfg.detect.nms(),
            session: vlmfuse_ort::SessionOptions {
                threads: cfg.detect.threads,
                library: cfg.detect.onnx_library.clone(),
            },
        },
        (None, Some(dc)) => dc,
        (None, None) => bail!("no detector: pass --model or set [detect] model"),
    };
    if args.threads.is_some() {
        dc.session.threads = args.threads;
    }
    if dc.session.library.is_none() && std::env::var_os(vlmfuse_ort::DYLIB_ENV).is_none() {
        dc.session.library = Some(cfg.assets().onnxruntime);
    }
    let detector = Detector::load(&dc)?;
    let frames = frames_of(&args, &cfg)?;
    if let Some(n) = args.bench {
        return bench(&detector, &frames, n.max(1));
    }
    let dets = detector.detect_frames(&frames)?;
    let a = vlmfuse_detect::derive(
        &dets,
        detector.names(),
        &cfg.detect.tracker_config(),
        &cfg.detect.rules,
    );
    if args.json {
        let frames: Vec<serde_json::Value> = dets
            .iter()
            .map(|f| {
                serde_json::json!({
                    "t_s": f.t_s,
                    "width": f.width,
                    "height": f.height,
                    "detections": f.detections.iter().map(|d| serde_json::json!({
                        "class": d.class,
                        "name": detector.names().get(d.class),
                        "score": d.score,
                        "box": d.xyxy,
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        let out = serde_json::json!({"frames": frames, "detected": a});
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    print_human(&detector, &dets, &a);
    Ok(())
}

fn print_human(d: &Detector, frames: &[FrameDetections], a: &vlmfuse_detect::DetectAnnotation) {
    let name = |c: usize| d.names().get(c).cloned().unwrap_or_else(|| c.to_string());
    for f in frames {
        println!(
            "t = {:.2} s ({}x{}): {} detection(s)",
            f.t_s,
            f.width,
            f.height,
            f.detections.len()
        );
        for det in &f.detections {
            let b = det.xyxy;
            println!(
                "  {:<14} {:.2}  [{:.0}, {:.0}, {:.0}, {:.0}]",
                name(det.class),
                det.score,
                b[0],
                b[1],
                b[2],
                b[3]
            );
        }
    }
    println!("{} frame(s), {} track(s)", a.frames, a.tracks);
    for l in &a.labels {
        println!(
            "{:<26} {} ({:.2})",
            l.label,
            if l.value { "yes" } else { "no" },
            l.confidence
        );
        for e in &l.evidence {
            println!("    {}", e.note);
        }
    }
    for u in &a.undecided {
        println!("{:<26} unknown: {}", u.label, u.reason);
    }
}

fn bench(d: &Detector, frames: &[Frame], n: usize) -> anyhow::Result<()> {
    for f in frames {
        d.detect(f.as_ref())?; // warm-up
        let (mut pre, mut run, mut post) = (0.0, 0.0, 0.0);
        let t_all = Instant::now();
        for _ in 0..n {
            let t = Instant::now();
            let (x, _) = d.preprocess(f.as_ref())?;
            pre += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let (raw, shape) = d.run(&x)?;
            run += t.elapsed().as_secs_f64();
            let t = Instant::now();
            d.postprocess(&raw, &shape, f.height, f.width)?;
            post += t.elapsed().as_secs_f64();
        }
        let ms = |s: f64| s / n as f64 * 1e3;
        let (h, w) = d.input_size();
        println!(
            "{} {}x{} frame -> {w}x{h}: {:.2} ms/frame (letterbox {:.2}, onnxruntime {:.2}, nms {:.2}; {n} runs)",
            d.path().display(),
            f.width,
            f.height,
            ms(t_all.elapsed().as_secs_f64()),
            ms(pre),
            ms(run),
            ms(post)
        );
    }
    Ok(())
}
