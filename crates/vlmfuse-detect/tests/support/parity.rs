//! Comparison with the files `scripts/parity/yolo_detect.py` writes (ultralytics' own ONNX
//! predictor and trackers). Shared by `tests/parity.rs` (the committed tiny model) and
//! `examples/parity.rs` (any directory the script wrote, e.g. the real YOLO11n at 640).

#![allow(dead_code, clippy::needless_range_loop)]

use std::path::{Path, PathBuf};

use base64::Engine;
use serde_json::Value;
use vlmfuse_detect::decode::{non_max_suppression, output_layout, scale_boxes};
use vlmfuse_detect::letterbox::{to_chw, Letterbox};
use vlmfuse_detect::{Detection, Detector, NmsConfig, Tracker, TrackerConfig, TrackerKind};

pub fn committed() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/parity/detect")
}

pub fn json(dir: &Path, file: &str) -> Value {
    let p = dir.join(file);
    let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_str(&text).unwrap()
}

/// An RGB PNG as (width, height, rows).
pub fn png(path: &Path) -> (u32, u32, Vec<u8>) {
    let img = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8();
    (img.width(), img.height(), img.into_raw())
}

pub fn f32s(b64: &str) -> Vec<f32> {
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(b64)
        .unwrap();
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn shape(v: &Value) -> Vec<i64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_i64().unwrap())
        .collect()
}

fn nms_cfg(run: &Value) -> NmsConfig {
    NmsConfig {
        conf: run["conf"].as_f64().unwrap() as f32,
        iou: run["iou"].as_f64().unwrap(),
        max_det: run["max_det"].as_u64().unwrap() as usize,
        agnostic: false,
    }
}

fn expected_boxes(run: &Value) -> Vec<Detection> {
    run["boxes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| {
            let v: Vec<f64> = b
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            Detection {
                xyxy: [v[0] as f32, v[1] as f32, v[2] as f32, v[3] as f32],
                score: v[4] as f32,
                class: v[5] as usize,
            }
        })
        .collect()
}

/// What differed, over every frame (and setting) compared.
#[derive(Debug, Default, Clone)]
pub struct Report {
    pub frames: usize,
    /// Letterboxed pixels compared and the largest difference in grey levels.
    pub pixels: usize,
    pub max_grey_diff: u8,
    pub grey_mismatches: usize,
    pub max_tensor_diff: f32,
    /// Raw output values compared (ONNX Runtime runs only).
    pub raw_values: usize,
    pub max_raw_diff: f32,
    /// NMS results compared: (frame, setting) pairs, boxes in them, largest coordinate and
    /// score differences, and pairs whose kept set (count and classes in order) differs.
    pub settings: usize,
    pub boxes: usize,
    pub max_box_diff: f32,
    pub max_score_diff: f32,
    pub kept_set_mismatches: Vec<String>,
}

fn compare_boxes(r: &mut Report, what: &str, got: &[Detection], want: &[Detection]) {
    r.settings += 1;
    let same = got.len() == want.len() && got.iter().zip(want).all(|(g, w)| g.class == w.class);
    if !same {
        r.kept_set_mismatches.push(format!(
            "{what}: {} boxes {:?} vs ultralytics {} {:?}",
            got.len(),
            got.iter().map(|d| d.class).collect::<Vec<_>>(),
            want.len(),
            want.iter().map(|d| d.class).collect::<Vec<_>>()
        ));
        return;
    }
    for (g, w) in got.iter().zip(want) {
        r.boxes += 1;
        for k in 0..4 {
            r.max_box_diff = r.max_box_diff.max((g.xyxy[k] - w.xyxy[k]).abs());
        }
        r.max_score_diff = r.max_score_diff.max((g.score - w.score).abs());
    }
}

/// Preprocessing and decoding + NMS from the stored raw outputs: no ONNX Runtime.
pub fn check_pure(dir: &Path) -> Report {
    let d = json(dir, "detect.json");
    let mut r = Report::default();
    for f in d["frames"].as_array().unwrap() {
        r.frames += 1;
        let name = f["file"].as_str().unwrap();
        let (w, h, rgb) = png(&dir.join(name));
        let in_shape = shape(&f["input_shape"]);
        let (ih, iw) = (in_shape[2] as u32, in_shape[3] as u32);
        let (lb, g) = Letterbox::new(ih, iw)
            .apply(vlmfuse_core::FrameRef {
                width: w,
                height: h,
                rgb: &rgb,
            })
            .unwrap();
        let (ew, eh, want) = png(&dir.join(f["letterbox"].as_str().unwrap()));
        assert_eq!((g.out_w(), g.out_h()), (ew, eh), "{name}: letterbox size");
        r.pixels += want.len();
        for (a, b) in lb.iter().zip(&want) {
            let dlt = a.abs_diff(*b);
            r.max_grey_diff = r.max_grey_diff.max(dlt);
            r.grey_mismatches += (dlt > 0) as usize;
        }
        let (mut x, mut y) = (vec![0f32; want.len()], vec![0f32; want.len()]);
        to_chw(&lb, eh as usize, ew as usize, &mut x);
        to_chw(&want, eh as usize, ew as usize, &mut y);
        for (a, b) in x.iter().zip(&y) {
            r.max_tensor_diff = r.max_tensor_diff.max((a - b).abs());
        }

        let raw = f32s(f["raw_f32_le"].as_str().unwrap());
        let (nc, anchors) = output_layout(&shape(&f["raw_shape"]), raw.len()).unwrap();
        for run in f["runs"].as_array().unwrap() {
            let cfg = nms_cfg(run);
            let mut got = non_max_suppression(&raw, nc, anchors, &cfg);
            scale_boxes(&mut got, (ih, iw), (h, w));
            let what = format!(
                "{name} conf {} iou {} max_det {}",
                cfg.conf, cfg.iou, cfg.max_det
            );
            compare_boxes(&mut r, &what, &got, &expected_boxes(run));
        }
    }
    r
}

/// The whole detector on ONNX Runtime: input tensor, raw output, final boxes.
pub fn check_onnx(dir: &Path) -> Report {
    let d = json(dir, "detect.json");
    let mut r = Report::default();
    let mut detectors: Vec<(NmsConfig, Detector)> = Vec::new();
    for f in d["frames"].as_array().unwrap() {
        r.frames += 1;
        let name = f["file"].as_str().unwrap();
        let (w, h, rgb) = png(&dir.join(name));
        let frame = vlmfuse_core::FrameRef {
            width: w,
            height: h,
            rgb: &rgb,
        };
        for run in f["runs"].as_array().unwrap() {
            let cfg = nms_cfg(run);
            let det = match detectors.iter().position(|(c, _)| *c == cfg) {
                Some(i) => &detectors[i].1,
                None => {
                    let det = Detector::load(&vlmfuse_detect::DetectorConfig {
                        model: dir.join("model.onnx"),
                        nms: cfg,
                        session: vlmfuse_ort::SessionOptions::with_threads(1),
                    })
                    .unwrap();
                    detectors.push((cfg, det));
                    &detectors.last().unwrap().1
                }
            };
            let (x, _) = det.preprocess(frame).unwrap();
            let (_, _, want) = png(&dir.join(f["letterbox"].as_str().unwrap()));
            let (lh, lw) = det.input_size();
            let mut y = vec![0f32; want.len()];
            to_chw(&want, lh as usize, lw as usize, &mut y);
            for (a, b) in x.iter().zip(&y) {
                r.max_tensor_diff = r.max_tensor_diff.max((a - b).abs());
            }
            let (raw, shp) = det.run(&x).unwrap();
            assert_eq!(shp, shape(&f["raw_shape"]), "{name}: output shape");
            let want_raw = f32s(f["raw_f32_le"].as_str().unwrap());
            r.raw_values += raw.len();
            for (a, b) in raw.iter().zip(&want_raw) {
                r.max_raw_diff = r.max_raw_diff.max((a - b).abs());
            }
            let got = det.detect(frame).unwrap();
            let what = format!(
                "{name} conf {} iou {} max_det {}",
                cfg.conf, cfg.iou, cfg.max_det
            );
            compare_boxes(&mut r, &what, &got, &expected_boxes(run));
        }
    }
    r
}

/// Tracker outputs per frame: ids (by detection index), boxes, for each stored run.
#[derive(Debug, Default, Clone)]
pub struct TrackReport {
    pub runs: usize,
    pub frames: usize,
    pub tracks_compared: usize,
    pub ids: usize,
    pub max_box_diff: f32,
    pub mismatches: Vec<String>,
}

pub fn tracker_config(kind: &str, overrides: &Value) -> TrackerConfig {
    let mut c = TrackerConfig {
        kind: match kind {
            "botsort" => TrackerKind::Botsort,
            "bytetrack" => TrackerKind::Bytetrack,
            other => panic!("tracker {other}"),
        },
        ..Default::default()
    };
    for (k, v) in overrides.as_object().unwrap() {
        match k.as_str() {
            "gmc_method" => assert_eq!(v, "none"),
            "with_reid" => assert_eq!(v, false),
            "track_buffer" => c.track_buffer = v.as_u64().unwrap() as u32,
            "fuse_score" => c.fuse_score = v.as_bool().unwrap(),
            "match_thresh" => c.match_thresh = v.as_f64().unwrap(),
            "new_track_thresh" => c.new_track_thresh = v.as_f64().unwrap() as f32,
            "track_high_thresh" => c.track_high_thresh = v.as_f64().unwrap() as f32,
            "track_low_thresh" => c.track_low_thresh = v.as_f64().unwrap() as f32,
            other => panic!("override {other}"),
        }
    }
    c
}

pub fn detections(frame: &Value) -> Vec<Detection> {
    frame
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            let v: Vec<f64> = d
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            Detection {
                xyxy: [v[0] as f32, v[1] as f32, v[2] as f32, v[3] as f32],
                score: v[4] as f32,
                class: v[5] as usize,
            }
        })
        .collect()
}

pub fn check_tracker(dir: &Path) -> TrackReport {
    let t = json(dir, "tracker.json");
    let seq: Vec<Vec<Detection>> = t["detections"]
        .as_array()
        .unwrap()
        .iter()
        .map(detections)
        .collect();
    let mut r = TrackReport::default();
    for run in t["runs"].as_array().unwrap() {
        r.runs += 1;
        let kind = run["tracker"].as_str().unwrap();
        let mut tracker = Tracker::new(tracker_config(kind, &run["overrides"]));
        let mut ids = std::collections::BTreeSet::new();
        for (fi, (dets, want)) in seq
            .iter()
            .zip(run["frames"].as_array().unwrap())
            .enumerate()
        {
            r.frames += 1;
            let mut got: Vec<_> = tracker.update(dets);
            got.sort_by_key(|o| o.idx);
            let mut want: Vec<Vec<f64>> = want
                .as_array()
                .unwrap()
                .iter()
                .map(|row| {
                    row.as_array()
                        .unwrap()
                        .iter()
                        .map(|x| x.as_f64().unwrap())
                        .collect()
                })
                .collect();
            want.sort_by_key(|w| w[7] as usize);
            let g: Vec<(usize, u64)> = got.iter().map(|o| (o.idx, o.track_id)).collect();
            let w: Vec<(usize, u64)> = want.iter().map(|w| (w[7] as usize, w[4] as u64)).collect();
            if g != w {
                r.mismatches.push(format!(
                    "{kind} {} frame {fi}: (idx, id) {g:?} vs ultralytics {w:?}",
                    run["overrides"]
                ));
                continue;
            }
            for (o, w) in got.iter().zip(&want) {
                r.tracks_compared += 1;
                ids.insert(o.track_id);
                for k in 0..4 {
                    r.max_box_diff = r.max_box_diff.max((o.xyxy[k] - w[k] as f32).abs());
                }
                if o.class != w[6] as usize || (o.score - w[5] as f32).abs() > 1e-6 {
                    r.mismatches.push(format!(
                        "{kind} frame {fi}: class/score of track {}",
                        o.track_id
                    ));
                }
            }
        }
        r.ids += ids.len();
    }
    r
}

/// `linear_assignment` against `lap.lapjv(cost, extend_cost=True, cost_limit=thresh)` on the
/// stored random matrices: (matrices compared, those whose row -> column answer differs).
pub fn check_assignments(dir: &Path) -> (usize, Vec<String>) {
    let t = json(dir, "tracker.json");
    let mut bad = Vec::new();
    let cases = t["assignments"].as_array().unwrap();
    for (k, c) in cases.iter().enumerate() {
        let rows = c["rows"].as_u64().unwrap() as usize;
        let cols = c["cols"].as_u64().unwrap() as usize;
        let cost: Vec<f32> = c["cost"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap() as f32)
            .collect();
        let (matches, _, _) = vlmfuse_detect::track::linear_assignment(
            &cost,
            rows,
            cols,
            c["thresh"].as_f64().unwrap(),
        );
        let mut x = vec![-1i64; rows];
        for (r, col) in matches {
            x[r] = col as i64;
        }
        let want: Vec<i64> = c["x"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_i64().unwrap())
            .collect();
        if x != want {
            bad.push(format!("case {k} ({rows}x{cols}): {x:?} vs lap {want:?}"));
        }
    }
    (cases.len(), bad)
}
