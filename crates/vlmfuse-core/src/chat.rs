//! The one client for OpenAI-compatible `/v1/chat/completions` servers (vLLM, SGLang,
//! llama.cpp, hosted APIs), shared by the remote reporter and the remote LLM labeler.
//!
//! Why one client: both talk to the same kind of server, often the very same vLLM, and used to
//! carry two retry loops that disagreed (one backed off, one did not; one honoured
//! `Retry-After`, one did not). Here is the single transport policy: retry on 408, 429, 5xx,
//! connection errors and attempt timeouts, with capped exponential backoff or the server's
//! `Retry-After`; never retry other 4xx, which mean the request itself is wrong. What a caller
//! does with a well-formed answer it does not like (the labeler's corrective retry) is the
//! caller's business.

use bytes::Bytes;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::sync::OnceLock;
use std::time::Duration;

/// When and how often a failed request is repeated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RetryPolicy {
    /// Extra attempts after the first.
    pub retries: u32,
    /// Backoff before retry k (1-based) is `backoff_initial * 2^(k-1)`, capped at `backoff_max`.
    /// A `Retry-After` (seconds) replaces it, capped the same way so that one server cannot stall
    /// a round past its own timeout.
    pub backoff_initial: Duration,
    pub backoff_max: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        Self {
            retries: 2,
            backoff_initial: Duration::from_millis(500),
            backoff_max: Duration::from_millis(8_000),
        }
    }
}

impl RetryPolicy {
    /// The wait before retry number `attempt` (1-based).
    pub fn delay(&self, attempt: u32, retry_after: Option<Duration>) -> Duration {
        let exp = Duration::from_millis(
            (self.backoff_initial.as_millis() as u64).saturating_mul(1u64 << (attempt - 1).min(30)),
        );
        retry_after.unwrap_or(exp).min(self.backoff_max)
    }
}

/// Why a chat request produced no answer.
#[derive(Debug, Clone, thiserror::Error)]
pub enum ChatError {
    /// The server answered with an error, or could not be reached, after all retries (or at
    /// once for a client error, which is not retried).
    #[error("remote {endpoint}: {message} (status {}, after {attempts} attempt(s))",
        .status.map(|s| s.to_string()).unwrap_or_else(|| "none".into()))]
    Remote {
        endpoint: String,
        status: Option<u16>,
        attempts: u32,
        message: String,
    },
    /// The last attempt ran out of time.
    #[error("POST {endpoint} (attempt {attempt}) timed out after {:.3}s", .after.as_secs_f64())]
    Timeout {
        endpoint: String,
        attempt: u32,
        after: Duration,
    },
    /// The server answered 2xx with a body that is not a chat completion.
    #[error("remote {endpoint} sent an unexpected response: {message}")]
    BadResponse { endpoint: String, message: String },
}

/// A chat completion's text and the model that wrote it (a server may resolve an alias).
#[derive(Debug, Clone, PartialEq)]
pub struct ChatReply {
    pub text: String,
    pub model: Option<String>,
}

/// One connection pool for every remote backend in the process: reporters and labelers often
/// talk to the same vLLM, and per-backend clients would each hold their own idle sockets.
pub fn shared_http_client() -> reqwest::Client {
    static CLIENT: OnceLock<reqwest::Client> = OnceLock::new();
    CLIENT
        .get_or_init(|| {
            reqwest::Client::builder()
                .connect_timeout(Duration::from_secs(10))
                .pool_idle_timeout(Duration::from_secs(90))
                .build()
                .expect("reqwest client with default settings")
        })
        .clone()
}

/// `http://host:port`, `http://host:port/v1` or the full URL -> the chat-completions URL.
pub fn chat_endpoint(base: &str) -> String {
    let b = base.trim_end_matches('/');
    if b.ends_with("/chat/completions") {
        b.to_string()
    } else if b.ends_with("/v1") {
        format!("{b}/chat/completions")
    } else {
        format!("{b}/v1/chat/completions")
    }
}

/// The default cap on an answer's body: a chat completion is a few KiB; 4 MiB leaves room for
/// long answers and verbose servers while bounding what one reply can make us hold.
pub const DEFAULT_MAX_RESPONSE_BYTES: usize = 4 << 20;

/// How much of an error answer is kept for the message.
const ERROR_BODY_BYTES: usize = 4096;

/// A client for one endpoint with one retry policy.
#[derive(Debug, Clone)]
pub struct ChatClient {
    endpoint: String,
    api_key: Option<String>,
    /// Per attempt.
    timeout: Duration,
    policy: RetryPolicy,
    http: reqwest::Client,
    /// Largest answer body read; past it the answer is refused, not buffered.
    max_response_bytes: usize,
}

/// Whether a transport error is a refused connection (nothing listens there): retrying in a
/// few hundred milliseconds only delays the round's failure.
fn is_refused(e: &reqwest::Error) -> bool {
    let mut src: Option<&dyn std::error::Error> = Some(e);
    while let Some(c) = src {
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            if io.kind() == std::io::ErrorKind::ConnectionRefused {
                return true;
            }
        }
        src = c.source();
    }
    false
}

/// Reads at most `cap` bytes of a body: `Ok(None)` when it is longer (the rest is not read).
async fn read_capped(
    mut resp: reqwest::Response,
    cap: usize,
) -> Result<Option<Vec<u8>>, reqwest::Error> {
    if resp.content_length().is_some_and(|n| n > cap as u64) {
        return Ok(None);
    }
    let mut buf = Vec::new();
    while let Some(chunk) = resp.chunk().await? {
        if buf.len() + chunk.len() > cap {
            return Ok(None);
        }
        buf.extend_from_slice(&chunk);
    }
    Ok(Some(buf))
}

/// The first bytes of an error answer, as text.
async fn error_text(mut resp: reqwest::Response) -> String {
    let mut buf = Vec::new();
    while buf.len() < ERROR_BODY_BYTES {
        match resp.chunk().await {
            Ok(Some(c)) => buf.extend_from_slice(&c),
            _ => break,
        }
    }
    buf.truncate(ERROR_BODY_BYTES);
    String::from_utf8_lossy(&buf).into_owned()
}

impl ChatClient {
    pub fn new(
        base_url: &str,
        api_key: Option<String>,
        timeout: Duration,
        policy: RetryPolicy,
    ) -> Self {
        Self {
            endpoint: chat_endpoint(base_url),
            api_key,
            timeout,
            policy,
            http: shared_http_client(),
            max_response_bytes: DEFAULT_MAX_RESPONSE_BYTES,
        }
    }

    /// Caps the answer body (default [`DEFAULT_MAX_RESPONSE_BYTES`]).
    pub fn with_max_response_bytes(mut self, cap: usize) -> Self {
        self.max_response_bytes = cap.max(1);
        self
    }

    /// Uses another connection pool (tests, custom TLS).
    pub fn with_http(mut self, http: reqwest::Client) -> Self {
        self.http = http;
        self
    }

    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    pub fn policy(&self) -> &RetryPolicy {
        &self.policy
    }

    /// The server's `/v1/models` URL, beside the chat endpoint (the health probe's target).
    pub fn models_endpoint(&self) -> String {
        let base = self
            .endpoint
            .strip_suffix("/chat/completions")
            .unwrap_or(&self.endpoint);
        format!("{base}/models")
    }

    /// A health probe: `GET /v1/models` once, no retry, within `timeout`. The server is up when
    /// it answers 2xx, or 404/405 (a server without a model listing still serves chat); a
    /// refused connection, a timeout, a 5xx or a 401/403 (a key the server refuses) is the
    /// one-line reason it is not.
    pub async fn probe(&self, timeout: Duration) -> Result<(), String> {
        let url = self.models_endpoint();
        let mut req = self.http.get(&url).timeout(timeout);
        if let Some(k) = &self.api_key {
            req = req.bearer_auth(k);
        }
        match req.send().await {
            Ok(r) if r.status().is_success() || matches!(r.status().as_u16(), 404 | 405) => Ok(()),
            Ok(r) => Err(format!("GET {url}: status {}", r.status().as_u16())),
            Err(e) if e.is_timeout() => Err(format!(
                "GET {url}: no answer within {:.1}s",
                timeout.as_secs_f64()
            )),
            Err(e) => Err(format!("GET {url}: {}", error_chain(&e))),
        }
    }

    /// Sends a chat-completions request body, retrying per the policy.
    pub async fn complete(&self, body: &Value) -> Result<ChatReply, ChatError> {
        let bytes = serde_json::to_vec(body).map_err(|e| ChatError::BadResponse {
            endpoint: self.endpoint.clone(),
            message: format!("request serialisation: {e}"),
        })?;
        self.complete_bytes(Bytes::from(bytes)).await
    }

    /// [`complete`](Self::complete) for an already serialised body; every attempt shares the
    /// same buffer.
    pub async fn complete_bytes(&self, body: Bytes) -> Result<ChatReply, ChatError> {
        let mut attempt: u32 = 0;
        loop {
            attempt += 1;
            let mut req = self
                .http
                .post(&self.endpoint)
                .timeout(self.timeout)
                .header(reqwest::header::CONTENT_TYPE, "application/json")
                .body(body.clone());
            if let Some(k) = &self.api_key {
                req = req.bearer_auth(k);
            }
            let (err, retry_after) = match req.send().await {
                Ok(resp) if resp.status().is_success() => {
                    let bad = |message: String| ChatError::BadResponse {
                        endpoint: self.endpoint.clone(),
                        message,
                    };
                    let cap = self.max_response_bytes;
                    let body = read_capped(resp, cap)
                        .await
                        .map_err(|e| bad(format!("reading the answer: {}", error_chain(&e))))?
                        .ok_or_else(|| {
                            bad(format!(
                                "the answer is larger than {cap} bytes (max_response_bytes); \
                                 nothing past it was read"
                            ))
                        })?;
                    let v: Value = serde_json::from_slice(&body)
                        .map_err(|e| bad(format!("body is not JSON: {e}")))?;
                    return parse_chat_response(&v).map_err(|m| ChatError::BadResponse {
                        endpoint: self.endpoint.clone(),
                        message: m,
                    });
                }
                Ok(resp) => {
                    let status = resp.status().as_u16();
                    let retry_after = resp
                        .headers()
                        .get(reqwest::header::RETRY_AFTER)
                        .and_then(|h| h.to_str().ok())
                        .and_then(parse_retry_after);
                    let mut msg = error_text(resp).await;
                    truncate(&mut msg, 500);
                    let err = ChatError::Remote {
                        endpoint: self.endpoint.clone(),
                        status: Some(status),
                        attempts: attempt,
                        message: msg,
                    };
                    if !(status == 408 || status == 429 || status >= 500) {
                        return Err(err);
                    }
                    (err, retry_after)
                }
                Err(e) if e.is_timeout() => (
                    ChatError::Timeout {
                        endpoint: self.endpoint.clone(),
                        attempt,
                        after: self.timeout,
                    },
                    None,
                ),
                // Nothing listens there: fail now, a retry in half a second finds the same.
                Err(e) if is_refused(&e) => {
                    return Err(ChatError::Remote {
                        endpoint: self.endpoint.clone(),
                        status: None,
                        attempts: attempt,
                        message: error_chain(&e),
                    })
                }
                Err(e) if e.is_connect() || e.is_request() => (
                    ChatError::Remote {
                        endpoint: self.endpoint.clone(),
                        status: None,
                        attempts: attempt,
                        message: error_chain(&e),
                    },
                    None,
                ),
                Err(e) => {
                    return Err(ChatError::Remote {
                        endpoint: self.endpoint.clone(),
                        status: None,
                        attempts: attempt,
                        message: error_chain(&e),
                    })
                }
            };
            if attempt > self.policy.retries {
                return Err(err);
            }
            let delay = self.policy.delay(attempt, retry_after);
            tracing::debug!(endpoint = %self.endpoint, attempt, ?delay, error = %err, "retrying");
            tokio::time::sleep(delay).await;
        }
    }
}

/// `choices[0].message.content` as a string (also accepting the list-of-parts form some servers
/// return), plus the answering model's name.
pub fn parse_chat_response(v: &Value) -> Result<ChatReply, String> {
    if let Some(err) = v.get("error") {
        return Err(format!("error object in 2xx response: {err}"));
    }
    let content = v
        .pointer("/choices/0/message/content")
        .ok_or_else(|| "no choices[0].message.content".to_string())?;
    let text = match content {
        Value::String(s) => s.clone(),
        Value::Array(parts) => parts
            .iter()
            .filter_map(|p| p.get("text").and_then(Value::as_str))
            .collect::<Vec<_>>()
            .join(""),
        Value::Null => String::new(),
        other => return Err(format!("content of unexpected type: {other}")),
    };
    if text.trim().is_empty() {
        let reason = v
            .pointer("/choices/0/finish_reason")
            .and_then(Value::as_str)
            .unwrap_or("?");
        return Err(format!("empty completion (finish_reason {reason})"));
    }
    let model = v.get("model").and_then(Value::as_str).map(str::to_string);
    Ok(ChatReply { text, model })
}

fn truncate(s: &mut String, max: usize) {
    if s.len() > max {
        let mut cut = max;
        while !s.is_char_boundary(cut) {
            cut -= 1;
        }
        s.truncate(cut);
        s.push('…');
    }
}

fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(c) = src {
        s.push_str(": ");
        s.push_str(&c.to_string());
        src = c.source();
    }
    s
}

/// A `Retry-After` in seconds. Anything that is not a finite, non-negative number of seconds
/// that a `Duration` can hold (`1e20`, `NaN`, `-1`, an HTTP date) is ignored, and the policy's
/// own backoff applies; the policy caps whatever is returned.
fn parse_retry_after(v: &str) -> Option<Duration> {
    let s: f64 = v.trim().parse().ok()?;
    Duration::try_from_secs_f64(s).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn retry_after_values_a_duration_cannot_hold_are_ignored() {
        assert_eq!(parse_retry_after("2"), Some(Duration::from_secs(2)));
        assert_eq!(parse_retry_after(" 0.5 "), Some(Duration::from_millis(500)));
        for bad in [
            "1e20",
            "NaN",
            "inf",
            "-1",
            "Wed, 21 Oct 2015 07:28:00 GMT",
            "",
        ] {
            assert_eq!(parse_retry_after(bad), None, "{bad}");
        }
    }

    #[test]
    fn endpoint_forms() {
        assert_eq!(
            chat_endpoint("http://h:8000"),
            "http://h:8000/v1/chat/completions"
        );
        assert_eq!(
            chat_endpoint("http://h:8000/v1/"),
            "http://h:8000/v1/chat/completions"
        );
        assert_eq!(
            chat_endpoint("http://h/v1/chat/completions"),
            "http://h/v1/chat/completions"
        );
    }

    #[test]
    fn parse_response_forms() {
        let v = json!({"model":"m","choices":[{"message":{"content":"hi"}}]});
        assert_eq!(
            parse_chat_response(&v).unwrap(),
            ChatReply {
                text: "hi".into(),
                model: Some("m".into())
            }
        );
        let v = json!({"choices":[{"message":{"content":[{"type":"text","text":"a"},{"type":"text","text":"b"}]}}]});
        assert_eq!(parse_chat_response(&v).unwrap().text, "ab");
        let v = json!({"choices":[{"message":{"content":null},"finish_reason":"length"}]});
        assert!(parse_chat_response(&v).unwrap_err().contains("length"));
        assert!(parse_chat_response(&json!({"choices":[]})).is_err());
    }

    #[test]
    fn backoff_doubles_and_caps_and_honours_retry_after() {
        let p = RetryPolicy {
            retries: 2,
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_millis(1000),
        };
        let ms = |d: Duration| d.as_millis();
        assert_eq!(ms(p.delay(1, None)), 100);
        assert_eq!(ms(p.delay(2, None)), 200);
        assert_eq!(ms(p.delay(3, None)), 400);
        assert_eq!(ms(p.delay(10, None)), 1000);
        assert_eq!(ms(p.delay(1, Some(Duration::from_millis(700)))), 700);
        assert_eq!(ms(p.delay(1, Some(Duration::from_secs(60)))), 1000);
    }
}
