//! Labeler backed by an LLM behind an OpenAI-compatible `/v1/chat/completions` endpoint.
//!
//! An LLM's answer is untrusted: it may invent labels or wrap JSON in prose. The answer is parsed
//! strictly against the ontology; a bad answer gets one corrective retry, then the labeler fails,
//! so that the engine counts this reporter as absent rather than fusing garbage. The prompt and the
//! validator are the ones the in-process GGUF labeler uses (`llm::prompt`).
//!
//! The transport (retries on 5xx, 429, connection errors, with backoff) is the shared
//! [`ChatClient`], the same one the remote reporter uses.

use crate::llm::prompt::{parse_labels, system_prompt, user_prompt};
use crate::{Evidence, EvidenceSource, Labeler, LabelerError, LabelerOutput, Ontology};
use futures::future::BoxFuture;
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::Duration;
use vlmfuse_core::chat::{ChatClient, ChatError, RetryPolicy};

#[derive(Debug, Clone)]
pub struct OpenAiConfig {
    /// Base URL up to and excluding `/v1/chat/completions`, e.g. `http://127.0.0.1:8000`.
    pub base_url: String,
    pub model: String,
    pub api_key: Option<String>,
    /// Ask for `response_format: {"type": "json_object"}`; turn off for servers that reject it.
    pub json_mode: bool,
    /// Per HTTP attempt.
    pub timeout: Duration,
    /// Tries per text while the answer is not a valid label set; each retry tells the model what
    /// was wrong. Default 2: one corrective retry.
    pub max_attempts: u32,
    /// Transport retries (5xx, 429, connection errors, timeouts): the policy the remote reporters
    /// use too. Default: one retry.
    pub retry: RetryPolicy,
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
            retry: RetryPolicy {
                retries: 1,
                ..RetryPolicy::default()
            },
            temperature: 0.0,
        }
    }
}

pub struct OpenAiLabeler {
    name: String,
    cfg: OpenAiConfig,
    ontology: Arc<Ontology>,
    client: ChatClient,
}

impl OpenAiLabeler {
    pub fn new(ontology: Ontology, cfg: OpenAiConfig) -> Result<Self, LabelerError> {
        if cfg.max_attempts == 0 {
            return Err(LabelerError::Config("max_attempts must be >= 1".into()));
        }
        let client = ChatClient::new(&cfg.base_url, cfg.api_key.clone(), cfg.timeout, cfg.retry);
        Ok(Self {
            name: format!("openai:{}", cfg.model),
            cfg,
            ontology: Arc::new(ontology),
            client,
        })
    }

    async fn call(&self, messages: &[Value]) -> Result<String, Attempt> {
        let mut body = json!({
            "model": self.cfg.model,
            "messages": messages,
            "temperature": self.cfg.temperature,
        });
        if self.cfg.json_mode {
            body["response_format"] = json!({"type": "json_object"});
        }
        match self.client.complete(&body).await {
            Ok(reply) => Ok(reply.text),
            // A well-formed HTTP exchange whose body is not an answer: worth another try.
            Err(ChatError::BadResponse { message, .. }) => Err(Attempt::Bad(message)),
            // The client has already retried what is worth retrying.
            Err(e) => Err(Attempt::Fatal(e.into())),
        }
    }

    async fn label_async(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        let mut messages = vec![
            json!({"role": "system", "content": system_prompt(&self.ontology)}),
            json!({"role": "user", "content": user_prompt(text)}),
        ];
        let mut last = String::new();
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
                    }
                },
                Err(Attempt::Bad(reason)) => last = reason,
                Err(Attempt::Fatal(e)) => {
                    tracing::warn!(labeler = %self.name, attempt, error = %e, "labeler request failed");
                    return Err(e);
                }
            }
        }
        Err(LabelerError::BadAnswer {
            labeler: self.name.clone(),
            attempts: self.cfg.max_attempts,
            reason: last,
        })
    }
}

enum Attempt {
    Bad(String),
    Fatal(LabelerError),
}

impl Labeler for OpenAiLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>> {
        Box::pin(self.label_async(text))
    }

    /// A round's answers as concurrent requests: the server batches them, and the round waits
    /// for the slowest answer instead of the sum.
    fn label_batch<'a>(
        &'a self,
        texts: &'a [&'a str],
    ) -> BoxFuture<'a, Result<Vec<LabelerOutput>, LabelerError>> {
        Box::pin(futures::future::try_join_all(
            texts.iter().map(|t| self.label_async(t)),
        ))
    }
}
