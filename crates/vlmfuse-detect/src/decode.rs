//! From the model's raw output to boxes in the frame: ultralytics'
//! `non_max_suppression` (best class per anchor, confidence filter, class-aware NMS with
//! torchvision's semantics, `max_det`) and `scale_boxes` (undo the letterbox, clip).
//!
//! The YOLO family's ONNX export (v8, v11 and the other non-end-to-end heads) outputs one
//! tensor `[1, 4 + nc, anchors]`: per anchor a box `(cx, cy, w, h)` in input pixels and `nc`
//! class scores already through the sigmoid. Arithmetic stays in `f32` where ultralytics'
//! tensors are `f32` (box corners, the per-class offset, IoU), so the kept set is the same one
//! even for candidates at the IoU threshold.

use serde::{Deserialize, Serialize};

/// ultralytics' `max_wh`: boxes of different classes are moved this far apart before one
/// class-agnostic NMS, so they never overlap.
const MAX_WH: f32 = 7680.0;
/// ultralytics' `max_nms`: most candidates that enter NMS (by score).
const MAX_NMS: usize = 30_000;

/// Confidence filter and NMS settings (ultralytics' predict arguments `conf`, `iou`,
/// `max_det`, `agnostic_nms`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NmsConfig {
    /// A candidate needs a best-class score strictly above this.
    pub conf: f32,
    /// A box is suppressed by a higher-scored one of its class when their IoU is strictly above
    /// this.
    pub iou: f64,
    /// Most detections kept per frame (highest scores first).
    pub max_det: usize,
    /// One NMS over all classes instead of one per class.
    pub agnostic: bool,
}

impl Default for NmsConfig {
    /// ultralytics' predict defaults.
    fn default() -> Self {
        Self {
            conf: 0.25,
            iou: 0.7,
            max_det: 300,
            agnostic: false,
        }
    }
}

impl NmsConfig {
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=1.0).contains(&self.conf) {
            return Err(format!("conf must be in [0, 1], got {}", self.conf));
        }
        if !(0.0..=1.0).contains(&self.iou) {
            return Err(format!("iou must be in [0, 1], got {}", self.iou));
        }
        if self.max_det == 0 {
            return Err("max_det must be at least 1".into());
        }
        Ok(())
    }
}

/// One detection: a box `[x1, y1, x2, y2]` (pixels of the frame after [`scale_boxes`], of the
/// model input before), its score and class index.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Detection {
    pub xyxy: [f32; 4],
    pub score: f32,
    pub class: usize,
}

/// Why a raw output cannot be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("output shape {0:?} is not [1, 4 + classes, anchors]")]
    Shape(Vec<i64>),
    #[error("output has {got} values, its shape needs {want}")]
    Length { got: usize, want: usize },
}

/// The number of classes and anchors of a `[1, 4 + nc, anchors]` output.
pub fn output_layout(shape: &[i64], len: usize) -> Result<(usize, usize), DecodeError> {
    let [1, rows, anchors] = *shape else {
        return Err(DecodeError::Shape(shape.to_vec()));
    };
    if rows < 5 || anchors < 1 {
        return Err(DecodeError::Shape(shape.to_vec()));
    }
    let want = rows as usize * anchors as usize;
    if len != want {
        return Err(DecodeError::Length { got: len, want });
    }
    Ok((rows as usize - 4, anchors as usize))
}

/// Best class per anchor, confidence filter, class-aware NMS, `max_det`: ultralytics'
/// `non_max_suppression` for one image of a `[1, 4 + nc, anchors]` output (`raw`, row-major).
/// Boxes stay in model-input pixels; the result is in descending score order.
pub fn non_max_suppression(
    raw: &[f32],
    nc: usize,
    anchors: usize,
    cfg: &NmsConfig,
) -> Vec<Detection> {
    let at = |row: usize, a: usize| raw[row * anchors + a];
    let mut cand: Vec<Detection> = Vec::new();
    for a in 0..anchors {
        // torch's `max(1)`: the first class among equal maxima.
        let (mut best, mut class) = (at(4, a), 0);
        for k in 1..nc {
            let s = at(4 + k, a);
            if s > best {
                best = s;
                class = k;
            }
        }
        // Strictly above (a NaN score is never a candidate).
        if best.partial_cmp(&cfg.conf) != Some(std::cmp::Ordering::Greater) {
            continue;
        }
        let (cx, cy, hw, hh) = (at(0, a), at(1, a), at(2, a) / 2.0, at(3, a) / 2.0);
        cand.push(Detection {
            xyxy: [cx - hw, cy - hh, cx + hw, cy + hh],
            score: best,
            class,
        });
    }
    if cand.len() > MAX_NMS {
        cand.sort_by(|a, b| b.score.total_cmp(&a.score));
        cand.truncate(MAX_NMS);
    }
    let offset = |d: &Detection| {
        if cfg.agnostic {
            0.0
        } else {
            d.class as f32 * MAX_WH
        }
    };
    let boxes: Vec<[f32; 4]> = cand
        .iter()
        .map(|d| {
            let o = offset(d);
            [d.xyxy[0] + o, d.xyxy[1] + o, d.xyxy[2] + o, d.xyxy[3] + o]
        })
        .collect();
    let scores: Vec<f32> = cand.iter().map(|d| d.score).collect();
    nms(&boxes, &scores, cfg.iou)
        .into_iter()
        .take(cfg.max_det)
        .map(|i| cand[i])
        .collect()
}

/// An end-to-end head's `[1, N, 6]` output (`x1, y1, x2, y2, score, class` per row, NMS done in
/// the model: YOLOv10, YOLO26): ultralytics' `end2end` branch, the rows with a score strictly
/// above `conf` in the model's order, at most `max_det`.
pub fn end_to_end(raw: &[f32], cfg: &NmsConfig) -> Vec<Detection> {
    raw.chunks_exact(6)
        .filter(|r| r[4].partial_cmp(&cfg.conf) == Some(std::cmp::Ordering::Greater))
        .take(cfg.max_det)
        .map(|r| Detection {
            xyxy: [r[0], r[1], r[2], r[3]],
            score: r[4],
            class: if r[5].is_finite() && r[5] > 0.0 {
                r[5] as usize
            } else {
                0
            },
        })
        .collect()
}

/// `torchvision.ops.nms` on the CPU: indices of the kept boxes, highest score first. Scores are
/// sorted stably (equal scores keep their input order), and a box is suppressed when its IoU
/// with a kept one is strictly above `iou` (computed in `f32`, compared in `f64` as
/// torchvision's kernel does).
pub fn nms(boxes: &[[f32; 4]], scores: &[f32], iou: f64) -> Vec<usize> {
    let n = boxes.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
    let area = |b: &[f32; 4]| (b[2] - b[0]) * (b[3] - b[1]);
    let areas: Vec<f32> = boxes.iter().map(area).collect();
    let mut suppressed = vec![false; n];
    let mut keep = Vec::new();
    for (oi, &i) in order.iter().enumerate() {
        if suppressed[i] {
            continue;
        }
        keep.push(i);
        let bi = &boxes[i];
        for &j in &order[oi + 1..] {
            if suppressed[j] {
                continue;
            }
            let bj = &boxes[j];
            let w = (bi[2].min(bj[2]) - bi[0].max(bj[0])).max(0.0);
            let h = (bi[3].min(bj[3]) - bi[1].max(bj[1])).max(0.0);
            let inter = w * h;
            let ovr = inter / (areas[i] + areas[j] - inter);
            if ovr as f64 > iou {
                suppressed[j] = true;
            }
        }
    }
    keep
}

/// ultralytics' `scale_boxes` + `clip_boxes`: boxes from a centred letterbox of `input`
/// (height, width) back to the `frame` (height, width), clipped to it.
///
/// The letterbox is recomputed from the two shapes the way ultralytics does it (Python `round`
/// of each side, the `-0.1` padding rule), not taken from the preprocessing, so that a frame
/// preprocessed elsewhere maps back the same way.
pub fn scale_boxes(dets: &mut [Detection], input: (u32, u32), frame: (u32, u32)) {
    let (ih, iw) = (input.0 as f64, input.1 as f64);
    let (fh, fw) = (frame.0 as f64, frame.1 as f64);
    let gain = (ih / fh).min(iw / fw);
    let new_h = (fh * gain).round_ties_even().max(1.0);
    let new_w = (fw * gain).round_ties_even().max(1.0);
    let (gain_y, gain_x) = ((new_h / fh) as f32, (new_w / fw) as f32);
    let pad_x = ((iw - new_w) / 2.0 - 0.1).round_ties_even() as f32;
    let pad_y = ((ih - new_h) / 2.0 - 0.1).round_ties_even() as f32;
    let (w, h) = (fw as f32, fh as f32);
    for d in dets {
        let b = &mut d.xyxy;
        b[0] = ((b[0] - pad_x) / gain_x).clamp(0.0, w);
        b[1] = ((b[1] - pad_y) / gain_y).clamp(0.0, h);
        b[2] = ((b[2] - pad_x) / gain_x).clamp(0.0, w);
        b[3] = ((b[3] - pad_y) / gain_y).clamp(0.0, h);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `[1, 4 + nc, n]` output from per-anchor `(cx, cy, w, h, scores...)`.
    fn raw(anchors: &[(f32, f32, f32, f32, &[f32])]) -> (Vec<f32>, usize, usize) {
        let nc = anchors[0].4.len();
        let n = anchors.len();
        let mut out = vec![0.0; (4 + nc) * n];
        for (a, (cx, cy, w, h, s)) in anchors.iter().enumerate() {
            for (r, v) in [*cx, *cy, *w, *h]
                .into_iter()
                .chain(s.iter().copied())
                .enumerate()
            {
                out[r * n + a] = v;
            }
        }
        (out, nc, n)
    }

    #[test]
    fn overlapping_boxes_of_one_class_keep_the_best_and_other_classes_survive() {
        let (r, nc, n) = raw(&[
            (50.0, 50.0, 20.0, 20.0, &[0.9, 0.1]),
            (52.0, 50.0, 20.0, 20.0, &[0.8, 0.1]), // IoU 0.82 with the first: suppressed
            (52.0, 50.0, 20.0, 20.0, &[0.1, 0.7]), // same place, other class: kept
            (90.0, 90.0, 10.0, 10.0, &[0.3, 0.2]),
            (10.0, 10.0, 10.0, 10.0, &[0.25, 0.0]), // not strictly above conf
        ]);
        let d = non_max_suppression(&r, nc, n, &NmsConfig::default());
        let got: Vec<(usize, f32)> = d.iter().map(|d| (d.class, d.score)).collect();
        assert_eq!(got, [(0, 0.9), (1, 0.7), (0, 0.3)]);
        assert_eq!(d[0].xyxy, [40.0, 40.0, 60.0, 60.0]);
        // Agnostic: the other-class box is suppressed too; max_det truncates.
        let cfg = NmsConfig {
            agnostic: true,
            max_det: 1,
            ..Default::default()
        };
        assert_eq!(non_max_suppression(&r, nc, n, &cfg).len(), 1);
        let cfg = NmsConfig {
            agnostic: true,
            ..Default::default()
        };
        assert_eq!(non_max_suppression(&r, nc, n, &cfg).len(), 2);
    }

    #[test]
    fn iou_exactly_at_the_threshold_is_kept_and_ties_keep_input_order() {
        // Two 10x10 boxes overlapping by half their width: IoU = 50 / 150 = 1/3.
        let boxes = [
            [0.0, 0.0, 10.0, 10.0],
            [5.0, 0.0, 15.0, 10.0],
            [100.0, 0.0, 110.0, 10.0],
        ];
        assert_eq!(nms(&boxes, &[0.5, 0.5, 0.5], 0.5), [0, 1, 2]);
        assert_eq!(nms(&boxes, &[0.5, 0.6, 0.5], 0.3), [1, 2]);
        assert_eq!(
            nms(&boxes, &[0.5, 0.6, 0.5], (1.0f32 / 3.0) as f64),
            [1, 0, 2]
        );
    }

    #[test]
    fn boxes_map_back_through_the_letterbox_and_are_clipped() {
        // A 320x180 frame in a 160x160 input: gain 0.5, 35 px of padding on top.
        let mut d = [Detection {
            xyxy: [10.0, 35.0, 170.0, 60.0],
            score: 1.0,
            class: 0,
        }];
        scale_boxes(&mut d, (160, 160), (180, 320));
        assert_eq!(d[0].xyxy, [20.0, 0.0, 320.0, 50.0]);
    }

    #[test]
    fn an_end_to_end_output_is_filtered_in_its_own_order() {
        let raw = [
            1.0, 2.0, 3.0, 4.0, 0.9, 2.0, //
            5.0, 6.0, 7.0, 8.0, 0.2, 1.0, // below conf
            9.0, 9.0, 9.5, 9.5, 0.3, 0.0, //
            0.0, 0.0, 1.0, 1.0, 0.8, 3.0,
        ];
        let d = end_to_end(&raw, &NmsConfig::default());
        let got: Vec<(usize, f32)> = d.iter().map(|d| (d.class, d.score)).collect();
        assert_eq!(got, [(2, 0.9), (0, 0.3), (3, 0.8)]);
        assert_eq!(d[0].xyxy, [1.0, 2.0, 3.0, 4.0]);
        let cfg = NmsConfig {
            max_det: 2,
            ..Default::default()
        };
        assert_eq!(end_to_end(&raw, &cfg).len(), 2);
    }

    #[test]
    fn a_wrong_shape_is_an_error() {
        assert!(output_layout(&[1, 84, 8400], 84 * 8400).is_ok());
        assert!(output_layout(&[2, 84, 8400], 2 * 84 * 8400).is_err());
        assert!(output_layout(&[1, 4, 10], 40).is_err());
        assert!(output_layout(&[1, 84, 10], 5).is_err());
    }
}
