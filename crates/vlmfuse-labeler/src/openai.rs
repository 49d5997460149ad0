//! Labeler backed by an LLM behind an OpenAI-compatible `/v1/chat/completions` endpoint.
//!
//! An LLM's answer is untrusted: it may invent labels or wrap JSON in prose. The answer is parsed
//! strictly against the ontology; a bad answer gets one corrective retry, then the labeler fails,
//! so that the engine counts this reporter as absent rather than fusing garbage. The prompt and the
//! validator are the ones the in-process GGUF labeler uses (`llm::prompt`).

use crate::llm::prompt::{parse_labels, system_prompt, user_prompt};
use crate::{Evidence, EvidenceSource, Labeler, LabelerError, LabelerOutput, Ontology};
use futures::future::BoxFuture;
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, Clone)]
pub struct OpenAiConfig {
    /// Base URL up to and excluding `/v1/chat/completions`, e.g. `http://127.0.0.1:8000`.
    pub base_url: String,
    pub model: String,
    pub api_key: Option<String>,
    /// Ask for `response_format: {"type": "json_object"}`; turn off for servers that reject it.
    pub json_mode: bool,
    pub timeout: Duration,
    /// Total tries per text, counting bad answers and transient HTTP failures (5xx, connection).
    /// Default 2: one retry.
    pub max_attempts: u32,
    pub temperature: f32,
}

impl Default for OpenAiConfig {
    fn default() -> Self {
        Self {
            base_url: "http://127.0.0.1:8000".into(),
            model: "gpt-4o-mini".into(),
            api_key: None,
            json_mode: true,
            timeout: Duration::from_secs(60),
            max_attempts: 2,
            temperature: 0.0,
        }
    }
}

pub struct OpenAiLabeler {
    name: String,
    cfg: OpenAiConfig,
    ontology: Arc<Ontology>,
    client: reqwest::Client,
}

impl OpenAiLabeler {
    pub fn new(ontology: Ontology, cfg: OpenAiConfig) -> Result<Self, LabelerError> {
        if cfg.max_attempts == 0 {
            return Err(LabelerError::Config("max_attempts must be >= 1".into()));
        }
        let client = reqwest::Client::builder()
            .timeout(cfg.timeout)
            .build()
            .map_err(|e| LabelerError::Http(e.to_string()))?;
        Ok(Self {
            name: format!("openai:{}", cfg.model),
            cfg,
            ontology: Arc::new(ontology),
            client,
        })
    }

    async fn call(&self, messages: &[Value]) -> Result<String, Attempt> {
        let url = format!(
            "{}/v1/chat/completions",
            self.cfg.base_url.trim_end_matches('/')
        );
        let mut body = json!({
            "model": self.cfg.model,
            "messages": messages,
            "temperature": self.cfg.temperature,
        });
        if self.cfg.json_mode {
            body["response_format"] = json!({"type": "json_object"});
        }
        let mut req = self.client.post(&url).json(&body);
        if let Some(k) = &self.cfg.api_key {
            req = req.bearer_auth(k);
        }
        let resp = req
            .send()
            .await
            .map_err(|e| Attempt::Transient(format!("POST {url}: {e}")))?;
        let status = resp.status();
        if !status.is_success() {
            let text = resp.text().await.unwrap_or_default();
            let msg = format!("POST {url}: HTTP {status}: {}", truncate(&text, 300));
            return Err(if status.is_server_error() || status.as_u16() == 429 {
                Attempt::Transient(msg)
            } else {
                Attempt::Fatal(LabelerError::Http(msg))
            });
        }
        let v: Value = resp
            .json()
            .await
            .map_err(|e| Attempt::Bad(format!("response is not JSON: {e}")))?;
        v.pointer("/choices/0/message/content")
            .and_then(Value::as_str)
            .map(str::to_string)
            .ok_or_else(|| Attempt::Bad("no choices[0].message.content in response".into()))
    }

    async fn label_async(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        let mut messages = vec![
            json!({"role": "system", "content": system_prompt(&self.ontology)}),
            json!({"role": "user", "content": user_prompt(text)}),
        ];
        let mut last = String::new();
        let mut last_http: Option<String> = None;
        for attempt in 1..=self.cfg.max_attempts {
            match self.call(&messages).await {
                Ok(content) => match parse_labels(&self.ontology, &content) {
                    Ok(on) => {
                        let scores: Vec<f32> = on.iter().map(|&b| f32::from(u8::from(b))).collect();
                        let mut out = LabelerOutput::from_decisions(&self.ontology, &scores, &on);
                        out.evidence = out
                            .labels
                            .iter()
                            .map(|id| Evidence {
                                label: id.clone(),
                                clause: String::new(),
                                score: 1.0,
                                negated: false,
                                hedged: false,
                                source: EvidenceSource::Llm,
                                accepted: true,
                            })
                            .collect();
                        return Ok(out);
                    }
                    Err(reason) => {
                        tracing::warn!(labeler = %self.name, attempt, %reason, "bad labeler answer");
                        // Tell the model what was wrong: a bare resend at temperature 0 would
                        // likely repeat the same answer.
                        messages.push(json!({"role": "assistant", "content": content}));
                        messages.push(json!({"role": "user", "content": format!(
                            "That answer was invalid ({reason}). Reply with only a JSON object \
                             {{\"labels\": [...]}} using only the listed ids."
                        )}));
                        last = reason;
                        last_http = None;
                    }
                },
                Err(Attempt::Bad(reason)) => {
                    last = reason;
                    last_http = None;
                }
                Err(Attempt::Transient(msg)) => {
                    tracing::warn!(labeler = %self.name, attempt, %msg, "labeler request failed");
                    last_http = Some(msg);
                }
                Err(Attempt::Fatal(e)) => return Err(e),
            }
        }
        match last_http {
            Some(msg) => Err(LabelerError::Http(msg)),
            None => Err(LabelerError::BadAnswer {
                labeler: self.name.clone(),
                attempts: self.cfg.max_attempts,
                reason: last,
            }),
        }
    }
}

enum Attempt {
    Bad(String),
    Transient(String),
    Fatal(LabelerError),
}

fn truncate(s: &str, n: usize) -> &str {
    match s.char_indices().nth(n) {
        Some((i, _)) => &s[..i],
        None => s,
    }
}

impl Labeler for OpenAiLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>> {
        Box::pin(self.label_async(text))
    }
}
