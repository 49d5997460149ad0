//! Per-frame latency of the detector: letterbox, ONNX Runtime, NMS + box scaling, on one image
//! (`scripts/bench/detect.sh` runs it beside ultralytics' own ONNX path on the same frame).
//!
//!     cargo run --release -p vlmfuse-detect --example bench -- MODEL.onnx IMAGE.png [RUNS] [THREADS]

use std::time::Instant;

use vlmfuse_detect::{Detector, DetectorConfig, NmsConfig};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, model, image, rest @ ..] = args.as_slice() else {
        eprintln!("usage: bench MODEL.onnx IMAGE.png [RUNS] [THREADS]");
        std::process::exit(2);
    };
    let runs: usize = rest.first().map_or(30, |s| s.parse().expect("RUNS"));
    let threads: Option<usize> = rest.get(1).map(|s| s.parse().expect("THREADS"));
    let img = image::open(image).expect("image").to_rgb8();
    let (w, h) = (img.width(), img.height());
    let rgb = img.into_raw();
    let frame = vlmfuse_core::FrameRef {
        width: w,
        height: h,
        rgb: &rgb,
    };
    let d = Detector::load(&DetectorConfig {
        model: model.into(),
        nms: NmsConfig::default(),
        session: vlmfuse_ort::SessionOptions {
            threads,
            library: None,
        },
    })
    .expect("detector");
    d.detect(frame).expect("warm-up");
    // `detect` as the service calls it, end to end.
    let t = Instant::now();
    for _ in 0..runs {
        d.detect(frame).unwrap();
    }
    let whole = t.elapsed().as_secs_f64();
    // Its three steps, each timed alone (the input buffer reused, as `detect` does).
    let mut x = Vec::new();
    let t = Instant::now();
    for _ in 0..runs {
        d.preprocess_into(frame, &mut x).unwrap();
    }
    let pre = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut out = (Vec::new(), Vec::new());
    for _ in 0..runs {
        out = d.run(&x).unwrap();
    }
    let run = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut n_det = 0;
    for _ in 0..runs {
        n_det = d.postprocess(&out.0, &out.1, h, w).unwrap().len();
    }
    let post = t.elapsed().as_secs_f64();
    let ms = |s: f64| s / runs as f64 * 1e3;
    let (ih, iw) = d.input_size();
    println!(
        "vlmfuse-detect {model} {w}x{h} -> {iw}x{ih}: detect() {:.2} ms/frame (alone: letterbox {:.2}, \
         onnxruntime {:.2}, nms {:.2}; {n_det} boxes; intra threads {}; {runs} runs)",
        ms(whole),
        ms(pre),
        ms(run),
        ms(post),
        threads.map_or("default".to_string(), |t| t.to_string()),
    );
}
