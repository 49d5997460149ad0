//! The detector on ONNX Runtime: an ultralytics YOLO export (`model.export(format="onnx")`),
//! one frame per run.
//!
//! What is read from the file: the input `[1, 3, H, W]` (its static size, else the metadata's
//! `imgsz`, else 640), the output `[1, 4 + nc, anchors]` (or an end-to-end head's
//! `[1, N, 6]`), and the class names from the metadata's `names` (ultralytics writes them; a
//! model without them gets `"0"`, `"1"`, ... and a warning, so a class mapping can still name
//! them by index). The session comes from `vlmfuse-ort` (library lookup, threads).
//!
//! Threads: [`Detector::detect`] runs on the calling thread, which ONNX Runtime makes the first
//! worker of the session's pool; call it from a blocking thread, never an async worker.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use vlmfuse_core::FrameRef;
use vlmfuse_ort::ort::session::Session;
use vlmfuse_ort::ort::value::{TensorElementType, TensorRef};
use vlmfuse_ort::{describe_outlets, OrtError, SessionOptions};

use crate::decode::{
    end_to_end, non_max_suppression, output_layout, scale_boxes, Detection, NmsConfig,
};
use crate::letterbox::{to_chw, Geometry, Letterbox};
use crate::names::parse_names;
use crate::rules::FrameDetections;
use crate::DetectError;

/// How the detector loads and filters.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectorConfig {
    pub model: PathBuf,
    pub nms: NmsConfig,
    pub session: SessionOptions,
}

/// The output's layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Head {
    /// `[1, 4 + nc, anchors]`: NMS needed.
    Anchors { nc: usize },
    /// `[1, N, 6]` (`x1, y1, x2, y2, score, class`), NMS inside the model (YOLOv10, YOLO26).
    EndToEnd,
}

pub struct Detector {
    path: PathBuf,
    input: String,
    output: String,
    /// Model input (height, width).
    size: (u32, u32),
    head: Head,
    names: Vec<String>,
    nms: NmsConfig,
    /// `Session::run` needs `&mut`, and one run at a time is what the thread budget assumes;
    /// the input buffer is kept with it (a fresh 5 MB tensor per frame costs more in page
    /// faults than the letterbox itself).
    session: Mutex<(Session, Vec<f32>)>,
}

impl std::fmt::Debug for Detector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Detector")
            .field("model", &self.path)
            .field("size", &self.size)
            .field("classes", &self.names.len())
            .finish()
    }
}

impl Detector {
    /// Opens the model, checks its signature and reads its metadata, then runs one grey frame
    /// so that a model that cannot run fails at start-up, not on the first clip.
    pub fn load(cfg: &DetectorConfig) -> Result<Self, DetectError> {
        cfg.nms.validate().map_err(DetectError::Config)?;
        let path = cfg.model.clone();
        let session = vlmfuse_ort::session_from_file(&path, &cfg.session)?;
        let sig = |reason: String| {
            DetectError::Ort(OrtError::Signature {
                path: path.clone(),
                reason,
            })
        };
        let [inp] = session.inputs() else {
            return Err(sig(format!(
                "a YOLO export has one image input, this has: {}",
                describe_outlets(session.inputs())
            )));
        };
        let in_shape: Vec<i64> = inp
            .dtype()
            .tensor_shape()
            .map(|s| s.iter().copied().collect())
            .unwrap_or_default();
        if inp.dtype().tensor_type() != Some(TensorElementType::Float32)
            || in_shape.len() != 4
            || !matches!(in_shape[1], 3 | -1)
        {
            return Err(sig(format!(
                "input `{}: {}` is not float32 [batch, 3, H, W] (fp16 exports are not supported)",
                inp.name(),
                inp.dtype()
            )));
        }
        let Some(out) = session.outputs().first() else {
            return Err(sig("no outputs".into()));
        };
        let out_shape: Vec<i64> = out
            .dtype()
            .tensor_shape()
            .map(|s| s.iter().copied().collect())
            .unwrap_or_default();
        let (input, output) = (inp.name().to_string(), out.name().to_string());

        // Owned copies: the metadata borrows the session, which moves into the detector.
        let (meta_imgsz, meta_names, meta_task) = {
            let meta = session.metadata().ok();
            let custom = |k: &str| meta.as_ref().and_then(|m| m.custom(k));
            (custom("imgsz"), custom("names"), custom("task"))
        };
        let size = match (in_shape[2], in_shape[3]) {
            (h, w) if h > 0 && w > 0 => (h as u32, w as u32),
            _ => meta_imgsz
                .as_deref()
                .and_then(parse_imgsz)
                .unwrap_or((640, 640)),
        };
        let head = match out_shape.as_slice() {
            [_, rows, _] if *rows > 4 && out_shape[2] != 6 => Head::Anchors {
                nc: *rows as usize - 4,
            },
            [_, _, 6] => Head::EndToEnd,
            _ => {
                return Err(sig(format!(
                    "output `{}` has shape {out_shape:?}; a YOLO detect export gives \
                     [1, 4 + classes, anchors] or [1, N, 6]",
                    out.name()
                )))
            }
        };
        let names = match meta_names {
            Some(s) => {
                parse_names(&s).map_err(|e| sig(format!("metadata `names` ({s:.80}): {e}")))?
            }
            None => {
                tracing::warn!(model = %path.display(),
                    "no class names in the model's metadata; classes are named by index");
                Vec::new()
            }
        };
        let names = match head {
            Head::Anchors { nc } if names.is_empty() => (0..nc).map(|i| i.to_string()).collect(),
            Head::Anchors { nc } if names.len() != nc => {
                return Err(sig(format!(
                    "metadata names {} classes, the output has {nc}",
                    names.len()
                )))
            }
            _ => names,
        };
        if let Some(task) = meta_task.filter(|t| t != "detect") {
            return Err(sig(format!("metadata task is `{task}`, not `detect`")));
        }
        let d = Self {
            path,
            input,
            output,
            size,
            head,
            names,
            nms: cfg.nms,
            session: Mutex::new((session, Vec::new())),
        };
        let grey = vec![114u8; 64 * 48 * 3];
        d.detect(FrameRef {
            width: 64,
            height: 48,
            rgb: &grey,
        })?;
        tracing::info!(model = %d.path.display(), size = ?d.size, classes = d.names.len(),
            "detector ready");
        Ok(d)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Class names by index.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Model input (height, width).
    pub fn input_size(&self) -> (u32, u32) {
        self.size
    }

    /// The predictor's letterbox for this model.
    pub fn letterbox(&self) -> Letterbox {
        Letterbox::new(self.size.0, self.size.1)
    }

    /// The model input for a frame (`[3, H, W]` in `[0, 1]`) and where the frame went.
    pub fn preprocess(&self, frame: FrameRef<'_>) -> Result<(Vec<f32>, Geometry), DetectError> {
        let mut x = Vec::new();
        let g = self.preprocess_into(frame, &mut x)?;
        Ok((x, g))
    }

    /// [`Detector::preprocess`] into a buffer the caller keeps (resized to fit).
    pub fn preprocess_into(
        &self,
        frame: FrameRef<'_>,
        x: &mut Vec<f32>,
    ) -> Result<Geometry, DetectError> {
        let (img, g) = self.letterbox().apply(frame)?;
        let (h, w) = (g.out_h() as usize, g.out_w() as usize);
        x.resize(3 * h * w, 0.0);
        to_chw(&img, h, w, x);
        Ok(g)
    }

    /// One forward pass: the raw output and its shape.
    pub fn run(&self, input: &[f32]) -> Result<(Vec<f32>, Vec<i64>), DetectError> {
        let mut guard = self.session.lock().unwrap_or_else(|p| p.into_inner());
        self.run_on(&mut guard.0, input)
    }

    fn run_on(
        &self,
        session: &mut Session,
        input: &[f32],
    ) -> Result<(Vec<f32>, Vec<i64>), DetectError> {
        let (h, w) = (self.size.0 as usize, self.size.1 as usize);
        if input.len() != 3 * h * w {
            return Err(DetectError::Config(format!(
                "input has {} values, the model takes 3x{h}x{w}",
                input.len()
            )));
        }
        let run_err = |e: vlmfuse_ort::ort::Error| DetectError::Ort(OrtError::Run(e.to_string()));
        let t = TensorRef::from_array_view(([1usize, 3, h, w], input)).map_err(run_err)?;
        let outputs = session
            .run(vlmfuse_ort::ort::inputs![self.input.as_str() => t])
            .map_err(run_err)?;
        let value = outputs.get(self.output.as_str()).ok_or_else(|| {
            DetectError::Ort(OrtError::Run(format!(
                "no `{}` in the outputs",
                self.output
            )))
        })?;
        let (shape, data) = value.try_extract_tensor::<f32>().map_err(run_err)?;
        Ok((data.to_vec(), shape.iter().copied().collect()))
    }

    /// Raw output to boxes in a `frame_h x frame_w` frame (NMS, `max_det`, `scale_boxes`).
    pub fn postprocess(
        &self,
        raw: &[f32],
        shape: &[i64],
        frame_h: u32,
        frame_w: u32,
    ) -> Result<Vec<Detection>, DetectError> {
        let mut dets = match self.head {
            Head::Anchors { .. } => {
                let (nc, anchors) = output_layout(shape, raw.len())?;
                non_max_suppression(raw, nc, anchors, &self.nms)
            }
            Head::EndToEnd => end_to_end(raw, &self.nms),
        };
        scale_boxes(&mut dets, self.size, (frame_h, frame_w));
        Ok(dets)
    }

    /// Detections in one frame (boxes in its pixels), highest score first.
    pub fn detect(&self, frame: FrameRef<'_>) -> Result<Vec<Detection>, DetectError> {
        let (raw, shape) = {
            let mut guard = self.session.lock().unwrap_or_else(|p| p.into_inner());
            let (session, x) = &mut *guard;
            self.preprocess_into(frame, x)?;
            self.run_on(session, x)?
        };
        self.postprocess(&raw, &shape, frame.height, frame.width)
    }

    /// Every frame of a clip, in order.
    pub fn detect_frames(
        &self,
        frames: &[vlmfuse_core::Frame],
    ) -> Result<Vec<FrameDetections>, DetectError> {
        frames
            .iter()
            .map(|f| {
                Ok(FrameDetections {
                    t_s: f.pts_s,
                    width: f.width,
                    height: f.height,
                    detections: self.detect(f.as_ref())?,
                })
            })
            .collect()
    }
}

/// ultralytics' `imgsz` metadata: `[640, 640]` or `640`.
fn parse_imgsz(s: &str) -> Option<(u32, u32)> {
    let v: Vec<u32> = s
        .trim_matches(|c: char| c == '[' || c == ']' || c == '(' || c == ')' || c.is_whitespace())
        .split(',')
        .map(|p| p.trim().parse().ok())
        .collect::<Option<_>>()?;
    match v.as_slice() {
        [n] => Some((*n, *n)),
        [h, w] => Some((*h, *w)),
        _ => None,
    }
    .filter(|(h, w)| *h > 0 && *w > 0)
}

#[cfg(test)]
mod tests {
    #[test]
    fn imgsz_metadata_forms() {
        assert_eq!(super::parse_imgsz("[640, 640]"), Some((640, 640)));
        assert_eq!(super::parse_imgsz("[384, 640]"), Some((384, 640)));
        assert_eq!(super::parse_imgsz("320"), Some((320, 320)));
        assert_eq!(super::parse_imgsz("[0, 1]"), None);
        assert_eq!(super::parse_imgsz("x"), None);
    }
}
