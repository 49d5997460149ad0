//! Labeler backed by an LLM behind an OpenAI-compatible `/v1/chat/completions` endpoint.
//!
//! An LLM's answer is untrusted: it may invent labels or wrap JSON in prose. The answer is parsed
//! strictly against the ontology; a bad answer gets one corrective retry, then the labeler fails,
//! so that the engine counts this reporter as absent rather than fusing garbage.
//!
//! The transport (retries on 5xx, 429, connection errors, with backoff) is the shared
//! [`ChatClient`], the same one the remote reporter uses.

use crate::{Labeler, LabelerError, LabelerOutput, Ontology};
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

    fn system_prompt(&self) -> String {
        let mut s = String::from(
            "You label driving advice. Read the text written by a vision-language model about a \
             dashcam clip (scene description, recommended manoeuvres, rationale) and list every \
             label from the list below that the text mentions as present in the scene or \
             recommends as an action. A label that the text explicitly negates (\"no need to \
             brake\", \"there is no traffic light\") is NOT present. Hedged recommendations \
             (\"might need to brake\") count as present.\n\nLabels (id: meaning):\n",
        );
        for l in self.ontology.labels() {
            s.push_str(&format!("- {}: {}\n", l.id, l.gloss()));
        }
        s.push_str(
            "\nAnswer with a JSON object only, no prose: {\"labels\": [ids]}. Use only the ids \
             above. Use an empty list if none applies.",
        );
        s
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
            json!({"role": "system", "content": self.system_prompt()}),
            json!({"role": "user", "content": text}),
        ];
        let mut last = String::new();
        for attempt in 1..=self.cfg.max_attempts {
            match self.call(&messages).await {
                Ok(content) => match parse_labels(&self.ontology, &content) {
                    Ok(on) => {
                        let scores: Vec<f32> = on.iter().map(|&b| f32::from(u8::from(b))).collect();
                        return Ok(LabelerOutput::from_decisions(&self.ontology, &scores, &on));
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

/// Strictly parses `{"labels": [...]}` (optionally inside a ```json fence, which many models add
/// even in JSON mode). Every entry must resolve to an ontology label; duplicates are harmless.
fn parse_labels(ontology: &Ontology, content: &str) -> Result<Vec<bool>, String> {
    let mut s = content.trim();
    if let Some(rest) = s.strip_prefix("```") {
        let rest = rest.trim_start_matches("json").trim_start_matches("JSON");
        s = rest.trim().trim_end_matches("```").trim();
    }
    let v: Value = serde_json::from_str(s).map_err(|e| format!("not valid JSON: {e}"))?;
    let arr = v
        .get("labels")
        .and_then(Value::as_array)
        .ok_or_else(|| "missing array field \"labels\"".to_string())?;
    let mut on = vec![false; ontology.len()];
    for item in arr {
        let name = item
            .as_str()
            .ok_or_else(|| format!("label {item} is not a string"))?;
        let k = ontology
            .resolve(name)
            .ok_or_else(|| format!("unknown label {name:?}"))?;
        on[k] = true;
    }
    Ok(on)
}

impl Labeler for OpenAiLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>> {
        Box::pin(self.label_async(text))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_fenced_and_names() {
        let o = Ontology::default_driving();
        let on =
            parse_labels(&o, "```json\n{\"labels\": [\"brake\", \"Turn Left\"]}\n```").unwrap();
        assert!(on[0] && on[2]);
        assert_eq!(on.iter().filter(|&&b| b).count(), 2);
        assert!(parse_labels(&o, "{\"labels\": [\"fly\"]}").is_err());
        assert!(parse_labels(&o, "brake, stop").is_err());
        assert!(parse_labels(&o, "{\"labels\": \"brake\"}").is_err());
        assert!(parse_labels(&o, "{\"labels\": []}")
            .unwrap()
            .iter()
            .all(|b| !b));
    }
}
