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
    let (mut pre, mut run, mut post, mut n_det) = (0.0, 0.0, 0.0, 0);
    let all = Instant::now();
    for _ in 0..runs {
        let t = Instant::now();
        let (x, _) = d.preprocess(frame).unwrap();
        pre += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (raw, shape) = d.run(&x).unwrap();
        run += t.elapsed().as_secs_f64();
        let t = Instant::now();
        n_det = d.postprocess(&raw, &shape, h, w).unwrap().len();
        post += t.elapsed().as_secs_f64();
    }
    let ms = |s: f64| s / runs as f64 * 1e3;
    let (ih, iw) = d.input_size();
    println!(
        "vlmfuse-detect {model} {w}x{h} -> {iw}x{ih}: {:.2} ms/frame (letterbox {:.2}, onnxruntime {:.2}, \
         nms {:.2}; {n_det} boxes; intra threads {}; {runs} runs)",
        ms(all.elapsed().as_secs_f64()),
        ms(pre),
        ms(run),
        ms(post),
        threads.map_or("default".to_string(), |t| t.to_string()),
    );
}
