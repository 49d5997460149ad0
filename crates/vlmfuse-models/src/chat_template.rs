//! Chat templates: a checkpoint's Jinja template (`tokenizer_config.json`'s `chat_template`,
//! a GGUF's `tokenizer.chat_template`), rendered with minijinja the way transformers'
//! `apply_chat_template` renders it with jinja2 (`trim_blocks`, `lstrip_blocks`, Python string
//! methods, `raise_exception`, `tojson`).
//!
//! Why the file's own template: an instruct model only follows instructions in the exact turn
//! format it was tuned on, and that format differs per family and even per release.

use crate::ModelError;
use minijinja::{Environment, ErrorKind, Value};
use serde::Serialize;

/// The date Llama 3.x templates print in their system header when none is given. Fixed so that
/// the same answer always renders to the same prompt (and the same labels).
pub const TEMPLATE_DATE: &str = "26 Jul 2024";

#[derive(Debug, Clone, Serialize)]
pub struct Message {
    pub role: String,
    pub content: String,
}

impl Message {
    pub fn new(role: &str, content: &str) -> Self {
        Self {
            role: role.into(),
            content: content.into(),
        }
    }
}

/// A compiled chat template.
pub struct ChatTemplate {
    env: Environment<'static>,
    source: String,
}

fn raise_exception(msg: String) -> Result<Value, minijinja::Error> {
    Err(minijinja::Error::new(ErrorKind::InvalidOperation, msg))
}

fn strftime_now(_fmt: String) -> String {
    TEMPLATE_DATE.to_string()
}

impl ChatTemplate {
    pub fn new(source: &str) -> Result<Self, ModelError> {
        let mut env = Environment::new();
        // transformers renders with jinja2's trim_blocks and lstrip_blocks on.
        env.set_syntax(
            minijinja::syntax::SyntaxConfig::builder()
                .trim_blocks(true)
                .lstrip_blocks(true)
                .build()
                .map_err(|e| ModelError::BadConfig(e.to_string()))?,
        );
        env.set_unknown_method_callback(minijinja_contrib::pycompat::unknown_method_callback);
        env.add_function("raise_exception", raise_exception);
        env.add_function("strftime_now", strftime_now);
        env.add_template_owned("chat", source.to_string())
            .map_err(|e| ModelError::BadConfig(format!("chat template does not compile: {e}")))?;
        Ok(Self {
            env,
            source: source.to_string(),
        })
    }

    pub fn source(&self) -> &str {
        &self.source
    }

    /// Renders `messages` with the generation prompt for the assistant's turn.
    pub fn render(
        &self,
        messages: &[Message],
        bos_token: &str,
        eos_token: &str,
    ) -> Result<String, ModelError> {
        let t = self
            .env
            .get_template("chat")
            .map_err(|e| ModelError::BadConfig(e.to_string()))?;
        t.render(minijinja::context! {
            messages => Value::from(minijinja::value::Serde(messages)),
            add_generation_prompt => true,
            bos_token => bos_token,
            eos_token => eos_token,
            // Qwen3: answer directly instead of opening a <think> block.
            enable_thinking => false,
            date_string => TEMPLATE_DATE,
        })
        .map_err(|e| ModelError::BadConfig(format!("chat template failed to render: {e:#}")))
    }
}
