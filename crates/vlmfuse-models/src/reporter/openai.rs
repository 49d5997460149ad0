//! Reporter for any OpenAI-compatible `/v1/chat/completions` server (vLLM, SGLang, llama.cpp,
//! hosted APIs). The clip goes either as one `video_url` part (servers with native video input,
//! e.g. vLLM + Qwen-VL) or as sampled frames in `image_url` parts (image-only VLMs).

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use base64::Engine as _;
use futures::future::BoxFuture;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use vlmfuse_core::chat::{ChatClient, RetryPolicy};

use super::{ClipInput, Reporter, ReporterOutput, DEFAULT_PROMPT};
use crate::{Frame, ModelError};

/// How the clip is shown to the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OpenAiMode {
    /// One `video_url` part: a base64 `data:` URL of the file, or `video_url_template`.
    VideoUrl,
    /// One `image_url` part per sampled frame (base64 data URLs).
    Frames,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameFormat {
    Jpeg,
    Png,
}

/// Configuration of one remote reporter; every field has a default except `model` (and
/// `base_url` for anything but a local vLLM on port 8000).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OpenAiReporterConfig {
    /// Name in rounds/metrics; defaults to `model`.
    pub name: Option<String>,
    /// `http://host:port` or `http://host:port/v1`.
    pub base_url: String,
    pub model: String,
    /// Name of the environment variable holding the API key (never the key itself, so configs
    /// can be committed). Unset means no `Authorization` header.
    pub api_key_env: Option<String>,
    pub mode: OpenAiMode,
    /// For `video_url` mode: send this URL instead of inlining the file, with `{path}`
    /// (absolute path) and `{file_name}` substituted, e.g. `file://{path}` for a vLLM started
    /// with `--allowed-local-media-path`, or `http://media/{file_name}`. Inlining a large clip
    /// costs 4/3 of its size in request body.
    pub video_url_template: Option<String>,
    pub frame_format: FrameFormat,
    pub jpeg_quality: u8,
    /// In `frames` mode, frames are scaled (bicubic) so their shorter side is at most this
    /// many pixels before they are encoded (0: as decoded). The service decodes frames at the
    /// clip's own resolution so that in-process models get what their processors expect; a
    /// remote server gets a copy of bounded size.
    pub frame_short_side: u32,
    pub prompt: String,
    pub system_prompt: Option<String>,
    pub max_tokens: u32,
    pub temperature: f32,
    /// Per HTTP attempt.
    pub timeout_s: f64,
    /// Extra attempts after the first, on 408/429/5xx, connection errors and attempt timeouts
    /// (the shared client's policy, [`RetryPolicy`]).
    pub retries: u32,
    /// Backoff before retry k (1-based) is `backoff_initial_ms * 2^(k-1)`, capped at
    /// `backoff_max_ms`. A `Retry-After` (seconds) replaces it, capped the same way so one
    /// server cannot stall a round past its own timeout.
    pub backoff_initial_ms: u64,
    pub backoff_max_ms: u64,
    /// Merged into the request body top level (e.g. vLLM's `mm_processor_kwargs`).
    pub extra_body: Option<serde_json::Map<String, Value>>,
    /// Largest answer read from the server, in bytes; a larger one fails the reporter with a
    /// clear error instead of being read whole into memory.
    pub max_response_bytes: u64,
}

impl Default for OpenAiReporterConfig {
    fn default() -> Self {
        Self {
            name: None,
            base_url: "http://127.0.0.1:8000".into(),
            model: String::new(),
            api_key_env: None,
            mode: OpenAiMode::VideoUrl,
            video_url_template: None,
            frame_format: FrameFormat::Jpeg,
            jpeg_quality: 90,
            frame_short_side: 448,
            prompt: DEFAULT_PROMPT.into(),
            system_prompt: None,
            max_tokens: 512,
            temperature: 0.0,
            timeout_s: 120.0,
            retries: 2,
            backoff_initial_ms: 500,
            backoff_max_ms: 8_000,
            extra_body: None,
            max_response_bytes: vlmfuse_core::chat::DEFAULT_MAX_RESPONSE_BYTES as u64,
        }
    }
}

pub struct OpenAiReporter {
    name: String,
    cfg: OpenAiReporterConfig,
    client: ChatClient,
}

impl OpenAiReporterConfig {
    /// The transport retry policy these fields describe.
    pub fn retry_policy(&self) -> RetryPolicy {
        RetryPolicy {
            retries: self.retries,
            backoff_initial: Duration::from_millis(self.backoff_initial_ms),
            backoff_max: Duration::from_millis(self.backoff_max_ms),
        }
    }
}

impl OpenAiReporter {
    /// Reads the API key now, so a missing secret fails at startup rather than on the first clip.
    pub fn new(cfg: OpenAiReporterConfig) -> Result<Self, ModelError> {
        if cfg.model.trim().is_empty() {
            return Err(ModelError::BadConfig(
                "openai reporter: `model` is empty".into(),
            ));
        }
        if !(cfg.timeout_s.is_finite() && cfg.timeout_s > 0.0) {
            return Err(ModelError::BadConfig(format!(
                "openai reporter {}: timeout_s must be > 0",
                cfg.model
            )));
        }
        if cfg.max_response_bytes == 0 {
            return Err(ModelError::BadConfig(format!(
                "openai reporter {}: max_response_bytes must be at least 1",
                cfg.model
            )));
        }
        let api_key = match &cfg.api_key_env {
            None => None,
            Some(var) => match std::env::var(var) {
                Ok(k) if !k.trim().is_empty() => Some(k.trim().to_string()),
                _ => {
                    return Err(ModelError::BadConfig(format!(
                        "openai reporter {}: environment variable `{var}` (api_key_env) is not set",
                        cfg.model
                    )))
                }
            },
        };
        let client = ChatClient::new(
            &cfg.base_url,
            api_key,
            Duration::from_secs_f64(cfg.timeout_s),
            cfg.retry_policy(),
        )
        .with_max_response_bytes(usize::try_from(cfg.max_response_bytes).unwrap_or(usize::MAX));
        Ok(Self {
            name: cfg.name.clone().unwrap_or_else(|| cfg.model.clone()),
            client,
            cfg,
        })
    }

    pub fn endpoint(&self) -> &str {
        self.client.endpoint()
    }

    /// The readiness probe: `GET /v1/models` of the base URL (see [`ChatClient::probe`]).
    pub async fn probe(&self, timeout: Duration) -> Result<(), String> {
        self.client.probe(timeout).await
    }

    /// The JSON request for `clip`. Encoding (base64 of the video, JPEG/PNG of frames) runs on
    /// a blocking thread: it is tens of milliseconds of CPU per clip.
    pub async fn request_body(&self, clip: &ClipInput) -> Result<Value, ModelError> {
        let media_parts = match self.cfg.mode {
            OpenAiMode::VideoUrl => vec![json!({
                "type": "video_url",
                "video_url": { "url": self.video_url(&clip.path).await? }
            })],
            OpenAiMode::Frames => {
                if clip.frames.is_empty() {
                    return Err(ModelError::InvalidInput(
                        "frames mode needs sampled frames; the clip has none".into(),
                    ));
                }
                let frames = Arc::clone(&clip.frames);
                let (fmt, q) = (self.cfg.frame_format, self.cfg.jpeg_quality);
                let short = self.cfg.frame_short_side;
                let urls = tokio::task::spawn_blocking(move || {
                    frames
                        .iter()
                        .map(|f| frame_data_url(&*scaled(f, short)?, fmt, q))
                        .collect::<Result<Vec<_>, _>>()
                })
                .await
                .map_err(|e| ModelError::InvalidInput(format!("frame encoding task: {e}")))??;
                urls.into_iter()
                    .map(|u| json!({ "type": "image_url", "image_url": { "url": u } }))
                    .collect()
            }
        };
        let mut body = self.body_with_media(media_parts);
        if let (Some(extra), Some(obj)) = (&self.cfg.extra_body, body.as_object_mut()) {
            for (k, v) in extra {
                obj.insert(k.clone(), v.clone());
            }
        }
        Ok(body)
    }

    /// The chat request around the media parts: system prompt, the parts and the prompt.
    fn body_with_media(&self, media_parts: Vec<Value>) -> Value {
        let mut content = media_parts;
        content.push(json!({ "type": "text", "text": self.cfg.prompt }));
        let mut messages = Vec::new();
        if let Some(sys) = &self.cfg.system_prompt {
            messages.push(json!({ "role": "system", "content": sys }));
        }
        messages.push(json!({ "role": "user", "content": content }));
        json!({
            "model": self.cfg.model,
            "messages": messages,
            "max_tokens": self.cfg.max_tokens,
            "temperature": self.cfg.temperature,
            "stream": false,
        })
    }

    async fn video_url(&self, path: &Path) -> Result<String, ModelError> {
        if let Some(t) = &self.cfg.video_url_template {
            let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
            let file_name = path
                .file_name()
                .map(|f| f.to_string_lossy())
                .unwrap_or_default();
            return Ok(t
                .replace("{path}", &abs.to_string_lossy())
                .replace("{file_name}", &file_name));
        }
        let bytes = tokio::fs::read(path)
            .await
            .map_err(|source| ModelError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        let mime = video_mime(path);
        tokio::task::spawn_blocking(move || {
            format!(
                "data:{mime};base64,{}",
                base64::engine::general_purpose::STANDARD.encode(bytes)
            )
        })
        .await
        .map_err(|e| ModelError::InvalidInput(format!("video encoding task: {e}")))
    }

    /// Whether the request inlines the clip file (`video_url` mode without a template).
    fn inlines_file(&self) -> bool {
        self.cfg.mode == OpenAiMode::VideoUrl && self.cfg.video_url_template.is_none()
    }

    /// The serialised request for `clip`, built once and shared by every attempt.
    ///
    /// An inline clip is base64-encoded straight from the file into the one request buffer,
    /// sized exactly up front: the body is the only copy (4/3 of the clip). Building a JSON
    /// value with the data URL and serialising it held the file, the base64 string, the value
    /// and the bytes at once: about four copies, 32 MiB for a 6 MiB clip.
    pub async fn request_bytes(&self, clip: &ClipInput) -> Result<bytes::Bytes, ModelError> {
        if !self.inlines_file() {
            let body = self.request_body(clip).await?;
            return serde_json::to_vec(&body)
                .map(bytes::Bytes::from)
                .map_err(|e| ModelError::InvalidInput(format!("request serialisation: {e}")));
        }
        // The body with a marker where the data URL goes, serialised; the URL is written
        // between its two halves.
        let mut body = self.body_with_media(vec![json!({
            "type": "video_url",
            "video_url": { "url": INLINE_MARKER }
        })]);
        if let (Some(extra), Some(obj)) = (&self.cfg.extra_body, body.as_object_mut()) {
            for (k, v) in extra {
                obj.insert(k.clone(), v.clone());
            }
        }
        let text = serde_json::to_vec(&body)
            .map_err(|e| ModelError::InvalidInput(format!("request serialisation: {e}")))?;
        let at = text
            .windows(INLINE_MARKER.len())
            .position(|w| w == INLINE_MARKER.as_bytes())
            .ok_or_else(|| ModelError::InvalidInput("request template lost its marker".into()))?;
        let (prefix, suffix) = (&text[..at], &text[at + INLINE_MARKER.len()..]);
        let head = format!("data:{};base64,", video_mime(&clip.path));
        let path = clip.path.clone();
        let (prefix, suffix) = (prefix.to_vec(), suffix.to_vec());
        tokio::task::spawn_blocking(move || -> Result<bytes::Bytes, ModelError> {
            let io = |source| ModelError::Io {
                path: path.clone(),
                source,
            };
            let mut file = std::fs::File::open(&path).map_err(io)?;
            let len = file.metadata().map_err(io)?.len() as usize;
            let b64 = len.div_ceil(3) * 4;
            let mut out = Vec::with_capacity(prefix.len() + head.len() + b64 + suffix.len());
            out.extend_from_slice(&prefix);
            out.extend_from_slice(head.as_bytes());
            {
                let mut enc = base64::write::EncoderWriter::new(
                    &mut out,
                    &base64::engine::general_purpose::STANDARD,
                );
                std::io::copy(&mut file, &mut enc).map_err(io)?;
                enc.finish().map_err(io)?;
            }
            out.extend_from_slice(&suffix);
            Ok(bytes::Bytes::from(out))
        })
        .await
        .map_err(|e| ModelError::InvalidInput(format!("video encoding task: {e}")))?
    }

    async fn run_inner(&self, clip: &ClipInput) -> Result<ReporterOutput, ModelError> {
        let started = Instant::now();
        let body = self.request_bytes(clip).await?;
        let reply = self.client.complete_bytes(body).await?;
        Ok(ReporterOutput {
            text: reply.text,
            latency_ms: started.elapsed().as_secs_f64() * 1e3,
            model: reply.model.unwrap_or_else(|| self.cfg.model.clone()),
        })
    }
}

/// Stands for the inline data URL in the serialised request template (plain ASCII, so JSON
/// writes it verbatim; nothing else in a request contains it).
const INLINE_MARKER: &str = "vlmfuse-inline-video-0b9e41c7d2f35a86";

impl Reporter for OpenAiReporter {
    fn name(&self) -> &str {
        &self.name
    }

    fn run<'a>(&'a self, clip: &'a ClipInput) -> BoxFuture<'a, Result<ReporterOutput, ModelError>> {
        Box::pin(self.run_inner(clip))
    }
}

fn video_mime(path: &Path) -> &'static str {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .as_deref()
    {
        Some("webm") => "video/webm",
        Some("mov") => "video/quicktime",
        Some("mkv") => "video/x-matroska",
        Some("avi") => "video/x-msvideo",
        _ => "video/mp4",
    }
}

/// `f` with its shorter side scaled down to `short` (0, or already that small: unchanged).
fn scaled(f: &Frame, short: u32) -> Result<std::borrow::Cow<'_, Frame>, ModelError> {
    let s = f.width.min(f.height);
    if short == 0 || s <= short {
        return Ok(std::borrow::Cow::Borrowed(f));
    }
    let r = short as f64 / s as f64;
    let (w, h) = (
        ((f.width as f64 * r).round() as u32).max(1),
        ((f.height as f64 * r).round() as u32).max(1),
    );
    let rgb = crate::imaging::resize_rgb8(
        crate::FrameRef {
            width: f.width,
            height: f.height,
            rgb: &f.rgb,
        },
        w as usize,
        h as usize,
        crate::imaging::Resample::Bicubic,
        crate::imaging::Arith::Pil,
    )?;
    Ok(std::borrow::Cow::Owned(Frame {
        width: w,
        height: h,
        rgb,
        pts_s: f.pts_s,
    }))
}

fn frame_data_url(f: &Frame, fmt: FrameFormat, jpeg_quality: u8) -> Result<String, ModelError> {
    use image::ImageEncoder as _;
    f.as_ref().validate()?;
    let mut buf = Vec::new();
    let (mime, res) = match fmt {
        FrameFormat::Jpeg => (
            "image/jpeg",
            image::codecs::jpeg::JpegEncoder::new_with_quality(
                &mut buf,
                jpeg_quality.clamp(1, 100),
            )
            .write_image(&f.rgb, f.width, f.height, image::ExtendedColorType::Rgb8),
        ),
        FrameFormat::Png => (
            "image/png",
            image::codecs::png::PngEncoder::new(&mut buf).write_image(
                &f.rgb,
                f.width,
                f.height,
                image::ExtendedColorType::Rgb8,
            ),
        ),
    };
    res.map_err(|e| ModelError::InvalidInput(format!("frame encoding: {e}")))?;
    Ok(format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(buf)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Remote servers get frames of bounded size (the shorter side at most `frame_short_side`),
    /// smaller frames and `0` pass as decoded.
    #[test]
    fn frames_for_a_server_are_scaled_to_the_short_side() {
        let f = |w: u32, h: u32| Frame {
            width: w,
            height: h,
            rgb: (0..w * h * 3).map(|i| (i % 251) as u8).collect(),
            pts_s: 1.5,
        };
        let big = f(640, 480);
        let s = scaled(&big, 448).unwrap();
        assert_eq!((s.width, s.height, s.rgb.len()), (597, 448, 597 * 448 * 3));
        assert_eq!(s.pts_s, 1.5);
        let tall_frame = f(480, 1000);
        let tall = scaled(&tall_frame, 448).unwrap();
        assert_eq!((tall.width, tall.height), (448, 933));
        let small = f(300, 200);
        assert!(matches!(
            scaled(&small, 448).unwrap(),
            std::borrow::Cow::Borrowed(_)
        ));
        assert!(matches!(
            scaled(&big, 0).unwrap(),
            std::borrow::Cow::Borrowed(_)
        ));
    }

    #[test]
    fn config_errors_are_clear() {
        let e = OpenAiReporter::new(OpenAiReporterConfig::default())
            .err()
            .unwrap();
        assert!(e.to_string().contains("model"), "{e}");
        let e = OpenAiReporter::new(OpenAiReporterConfig {
            model: "m".into(),
            api_key_env: Some("VLMFUSE_TEST_SURELY_UNSET_KEY".into()),
            ..Default::default()
        })
        .err()
        .unwrap();
        assert!(
            e.to_string().contains("VLMFUSE_TEST_SURELY_UNSET_KEY"),
            "{e}"
        );
    }

    #[test]
    fn frames_encode_to_decodable_images() {
        let f = Frame {
            width: 4,
            height: 2,
            rgb: (0..24).map(|i| (i * 10) as u8).collect(),
            pts_s: 0.0,
        };
        let png = frame_data_url(&f, FrameFormat::Png, 90).unwrap();
        let b64 = png.strip_prefix("data:image/png;base64,").unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(b64)
            .unwrap();
        let img = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert_eq!(img.into_raw(), f.rgb, "PNG must be lossless");
        let jpg = frame_data_url(&f, FrameFormat::Jpeg, 90).unwrap();
        let b64 = jpg.strip_prefix("data:image/jpeg;base64,").unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(b64)
            .unwrap();
        assert_eq!(&bytes[..2], &[0xFF, 0xD8], "JPEG SOI marker");
    }
}
