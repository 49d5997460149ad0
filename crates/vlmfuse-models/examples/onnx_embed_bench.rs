//! The context embedder on ONNX Runtime against candle, on the same frames of a real clip:
//! median time to embed N frames (preprocess + forward), the cores kept busy meanwhile
//! (process CPU time / wall time, from getrusage), and how far apart the embeddings are.
//!
//! `scripts/bench-encoders.sh` runs this next to the Python references (onnxruntime and torch,
//! `scripts/onnx/bench_reference.py`) and prints the ratios; on its own:
//!
//! ```sh
//! cargo run --release -p vlmfuse-models \
//!     --example onnx_embed_bench -- --model DIR --clip clip.mp4 --threads 2 --out ort.json
//! ```
//!
//! DIR is a CLIP directory with both `model.safetensors` (candle) and `onnx/vision_model.onnx`
//! (ONNX Runtime), as `scripts/onnx/make_bench_model.py` writes it. `--dump-frames F` writes the
//! decoded frames (raw RGB24, `F.json` beside it) so the references embed exactly the same ones.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use candle_core::Device;
use clap::Parser;
use serde_json::json;
use vlmfuse_models::{
    ClipEmbedder, ContextEmbedder, FrameRef, OnnxClipConfig, OnnxClipEmbedder, WeightSource,
};
use vlmfuse_ort::SessionOptions;

#[derive(Parser)]
struct Args {
    /// CLIP directory (safetensors for candle, onnx/vision_model.onnx for ONNX Runtime).
    #[arg(long)]
    model: PathBuf,
    /// The clip to sample frames from.
    #[arg(long)]
    clip: PathBuf,
    #[arg(long, default_value_t = 8)]
    frames: usize,
    /// Shorter side of the decoded frames (0: the clip's own size, 720 for a 720p clip).
    #[arg(long, default_value_t = 0)]
    short_side: u32,
    /// Threads of each engine's pool (ONNX Runtime intra-op; candle's rayon pool through
    /// RAYON_NUM_THREADS, which must be set before start: this program re-reads it).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Timed repetitions per engine (after two warm-up runs).
    #[arg(long, default_value_t = 10)]
    reps: usize,
    /// Engines to run, comma-separated: ort, candle.
    #[arg(long, default_value = "ort,candle")]
    engines: String,
    /// Results as JSON (timings and embeddings).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the decoded frames for the reference scripts.
    #[arg(long)]
    dump_frames: Option<PathBuf>,
}

fn cpu_time() -> Duration {
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage only writes into the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

struct Timing {
    walls: Vec<f64>,
    cores: f64,
}

impl Timing {
    fn median(&self) -> f64 {
        let mut v = self.walls.clone();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    }
    fn pct(&self, p: f64) -> f64 {
        let mut v = self.walls.clone();
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * p).round() as usize]
    }
}

/// Times `f` `reps` times after two warm-up calls; cores busy = CPU time / wall time over the
/// timed calls.
fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> (Timing, T) {
    let _ = f();
    let mut out = f();
    let mut walls = Vec::with_capacity(reps);
    let (c0, w0) = (cpu_time(), Instant::now());
    for _ in 0..reps {
        let t = Instant::now();
        out = f();
        walls.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cores = (cpu_time() - c0).as_secs_f64() / w0.elapsed().as_secs_f64();
    (Timing { walls, cores }, out)
}

fn cosine(a: &[f32], b: &[f32]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let n = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    dot / (n(a) * n(b))
}

fn main() {
    let args = Args::parse();
    let limits = vlmfuse_media::MediaLimits::default();
    let opts = vlmfuse_media::SampleOptions {
        frames: args.frames,
        size: if args.short_side == 0 {
            vlmfuse_media::FrameSize::Native
        } else {
            vlmfuse_media::FrameSize::ShortSide(args.short_side)
        },
    };
    let t = Instant::now();
    let clip = vlmfuse_media::sample_frames(&args.clip, &opts, &limits).expect("decode the clip");
    let decode_ms = t.elapsed().as_secs_f64() * 1e3;
    let frames: Vec<FrameRef> = clip
        .frames
        .iter()
        .map(|f| FrameRef {
            width: f.width,
            height: f.height,
            rgb: &f.rgb,
        })
        .collect();
    let (w, h) = (frames[0].width, frames[0].height);
    eprintln!(
        "{} frames of {w}x{h} from {} ({:.1} s clip), decoded in {decode_ms:.0} ms",
        frames.len(),
        args.clip.display(),
        clip.info.duration_s
    );
    if let Some(p) = &args.dump_frames {
        dump(p, &frames);
    }

    let engines: Vec<&str> = args.engines.split(',').map(str::trim).collect();
    let mut results = serde_json::Map::new();
    let mut embeddings: Vec<(String, Vec<f32>)> = Vec::new();
    for engine in &engines {
        eprint!("{engine}: loading ... ");
        let (embedder, extra): (Box<dyn ContextEmbedder>, serde_json::Value) = match *engine {
            "ort" => {
                let cfg = OnnxClipConfig {
                    session: SessionOptions::with_threads(args.threads),
                    ..OnnxClipConfig::new(WeightSource::local(&args.model))
                };
                let e = OnnxClipEmbedder::load(&cfg).expect("load the ONNX embedder");
                // The two halves on their own, to show which one dominates.
                let threads = std::num::NonZeroUsize::new(args.threads).unwrap();
                let (pre, (px, _)) = time(args.reps, || {
                    e.processor().process_batch(&frames, threads).unwrap()
                });
                let (fwd, _) = time(args.reps, || e.pixel_embeddings(&px, frames.len()).unwrap());
                let extra = json!({
                    "preprocess_ms": pre.median(), "forward_ms": fwd.median(),
                    "preprocess_cores": pre.cores, "forward_cores": fwd.cores,
                    "processor": format!("{:?}", e.processor()),
                });
                (Box::new(e), extra)
            }
            "candle" => {
                let e = ClipEmbedder::load(&WeightSource::local(&args.model), &Device::Cpu)
                    .expect("load the candle embedder");
                // The candle backend's own preprocessing, timed alone.
                let p =
                    vlmfuse_models::imaging::ImageProcessor::clip(e.settings().image_size as u32);
                let (pre, _) = time(args.reps, || {
                    p.process_batch(&frames, std::num::NonZeroUsize::MIN)
                        .unwrap();
                });
                (
                    Box::new(e),
                    json!({ "preprocess_ms": pre.median(), "preprocess_cores": pre.cores }),
                )
            }
            other => panic!("unknown engine {other} (ort, candle)"),
        };
        eprint!("embedding x{} ... ", args.reps);
        let (timing, emb) = time(args.reps, || embedder.embed(&frames).unwrap());
        eprintln!(
            "median {:.1} ms (p10 {:.1}, p90 {:.1}), {:.2} cores busy",
            timing.median(),
            timing.pct(0.1),
            timing.pct(0.9),
            timing.cores
        );
        let mut r = json!({
            "median_ms": timing.median(), "p10_ms": timing.pct(0.1), "p90_ms": timing.pct(0.9),
            "walls_ms": timing.walls, "cores_busy": timing.cores, "embedding": emb,
        });
        r.as_object_mut()
            .unwrap()
            .extend(extra.as_object().unwrap().clone());
        results.insert(engine.to_string(), r);
        embeddings.push((engine.to_string(), emb));
    }
    if embeddings.len() == 2 {
        let c = cosine(&embeddings[0].1, &embeddings[1].1);
        eprintln!("cosine {} vs {}: {c:.8}", embeddings[0].0, embeddings[1].0);
    }
    let report = json!({
        "frames": frames.len(), "width": w, "height": h, "threads": args.threads,
        "decode_ms": decode_ms, "reps": args.reps, "engines": results,
    });
    if let Some(p) = &args.out {
        std::fs::write(p, serde_json::to_string_pretty(&report).unwrap()).expect("write --out");
    }
}

fn dump(path: &Path, frames: &[FrameRef]) {
    let mut raw = Vec::new();
    for f in frames {
        raw.extend_from_slice(f.rgb);
    }
    std::fs::write(path, raw).expect("write frames");
    let meta = json!({"n": frames.len(), "width": frames[0].width, "height": frames[0].height});
    std::fs::write(path.with_extension("json"), meta.to_string()).expect("write frames meta");
}
