//! The paper's LLM labelling step in process: an instruct LLM from a GGUF file (Llama 3.x,
//! Qwen2/Qwen3, Gemma 3) reads the answer with the shared prompt (`llm::prompt`) and writes the
//! label list, under constrained decoding (`llm::constrain`) so that the output is always a
//! valid list of distinct ontology ids.
//!
//! Decoding is greedy: labelling is a classification, and the same answer must always get the
//! same labels. Each label's score is the lowest masked probability among the tokens that wrote
//! its id, the model's confidence in choosing it (1 when it was the only choice).
//!
//! A file without a chat template (a base model such as gemma-3-270m) gets its family's turn
//! format, with a warning: a base model does not follow instructions, so expect poor labels;
//! it is useful for loading and speed checks, not for accuracy.

use crate::llm::constrain::{LabelGrammar, TokenTrie};
use crate::llm::prompt::{system_prompt, user_prompt};
use crate::llm::template::{fallback_template, ChatTemplate, Message, TemplateFamily};
use crate::{BlockingLabeler, Evidence, EvidenceSource, LabelerError, LabelerOutput, Ontology};
use candle_core::quantized::gguf_file;
use candle_core::Device;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use vlmfuse_models::text::gguf::GgufTokenizer;
use vlmfuse_models::text::gguf::{Decoder, Family};

#[derive(Debug, Clone)]
pub struct GgufConfig {
    pub model_path: PathBuf,
    /// A Jinja chat template that replaces the file's (for files with a broken or missing one).
    pub chat_template: Option<String>,
    /// Longer answers keep their first tokens only, so that one runaway answer cannot make the
    /// prompt exceed the model's context.
    pub max_answer_tokens: usize,
}

impl GgufConfig {
    pub fn new(model_path: impl Into<PathBuf>) -> Self {
        Self {
            model_path: model_path.into(),
            chat_template: None,
            max_answer_tokens: 512,
        }
    }
}

/// Where the prompt's text comes from and how it was rendered; for logs and tests.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TemplateSource {
    File,
    Config,
    Fallback,
}

/// One greedy, constrained generation.
#[derive(Debug, Clone)]
pub struct Generation {
    /// The answer the model wrote, e.g. `{"labels": ["brake"]}`.
    pub text: String,
    pub tokens: Vec<u32>,
    /// Ontology indices of the ids written, in order, with their scores.
    pub labels: Vec<(usize, f32)>,
    /// Prompt tokens, and how many of them came from the cached prefix.
    pub prompt_tokens: usize,
    pub cached_prompt_tokens: usize,
}

struct Prefix {
    ids: Vec<u32>,
    model: Decoder,
}

struct Inner {
    ontology: Ontology,
    tok: GgufTokenizer,
    template: ChatTemplate,
    template_source: TemplateSource,
    grammar: LabelGrammar,
    trie: TokenTrie,
    /// The model and its KV cache. `BlockingLabeler` takes `&self`, so the cache needs interior
    /// mutability; the service's `BackendPool` runs one call at a time on its own worker, so this
    /// lock is uncontended there and no thread waits on it (a batch tool calling from several
    /// threads gets one generation at a time, which would compete for the same cores anyway).
    model: Mutex<Decoder>,
    prefix: Option<Prefix>,
    system: String,
    bos: String,
    eos: String,
    max_answer_tokens: usize,
}

pub struct GgufLabeler {
    name: String,
    family: Family,
    inner: Inner,
}

fn template_family(f: Family) -> TemplateFamily {
    match f {
        Family::Llama => TemplateFamily::Llama3,
        Family::Qwen2 | Family::Qwen3 => TemplateFamily::ChatMl,
        Family::Gemma3 => TemplateFamily::Gemma,
    }
}

fn log_softmax_at(logits: &[f32], allowed: &[u32], pick: u32) -> f32 {
    let m = allowed
        .iter()
        .map(|&i| logits[i as usize])
        .fold(f32::NEG_INFINITY, f32::max);
    let z: f32 = allowed
        .iter()
        .map(|&i| (logits[i as usize] - m).exp())
        .sum();
    (logits[pick as usize] - m) - z.ln()
}

impl GgufLabeler {
    /// Loads the model, builds the tokenizer, template and decoding automaton, and caches the
    /// system prompt where the family allows it (blocking; seconds for real models).
    pub fn load(ontology: Ontology, cfg: GgufConfig) -> Result<Self, LabelerError> {
        if !cfg.model_path.is_file() {
            return Err(LabelerError::AssetMissing(
                cfg.model_path.display().to_string(),
            ));
        }
        if cfg.max_answer_tokens == 0 {
            return Err(LabelerError::Config(
                "max_answer_tokens must be >= 1".into(),
            ));
        }
        let device = Device::Cpu;
        let mut file = std::fs::File::open(&cfg.model_path)?;
        let ct = gguf_file::Content::read(&mut file).map_err(|e| e.with_path(&cfg.model_path))?;
        let tok = GgufTokenizer::from_gguf(&ct)?;
        let file_template = ct
            .metadata
            .get("tokenizer.chat_template")
            .and_then(|v| v.to_string().ok())
            .cloned();
        let model_name = ct
            .metadata
            .get("general.name")
            .and_then(|v| v.to_string().ok())
            .cloned()
            .unwrap_or_else(|| {
                cfg.model_path
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default()
            });
        let model = Decoder::load(ct, &mut file, &device)?;
        let family = model.family();
        let (source, template_source) = match (&cfg.chat_template, file_template) {
            (Some(t), _) => (t.clone(), TemplateSource::Config),
            (None, Some(t)) => (t, TemplateSource::File),
            (None, None) => {
                tracing::warn!(
                    model = %model_name,
                    "GGUF has no chat template; using the {} turn format (a base model does not \
                     follow instructions: expect poor labels)",
                    family.name()
                );
                (
                    fallback_template(template_family(family)).to_string(),
                    TemplateSource::Fallback,
                )
            }
        };
        let template = ChatTemplate::new(&source)?;
        let grammar = LabelGrammar::new(ontology.ids())?;
        let alphabet = grammar.alphabet();
        let trie = TokenTrie::build(tok.vocab_size(), |i| tok.token_bytes(i), &alphabet);
        trie.spells_every_byte(&alphabet).map_err(|b| {
            LabelerError::Tokenizer(format!(
                "the vocabulary cannot spell byte {:?} on its own, so constrained decoding could \
                 get stuck",
                b as char
            ))
        })?;
        let tok_str = |id: Option<u32>| {
            id.and_then(|i| tok.token_str(i))
                .unwrap_or_default()
                .to_string()
        };
        let (bos, eos) = (tok_str(tok.bos_id()), tok_str(tok.eos_id()));
        let mut inner = Inner {
            system: system_prompt(&ontology),
            ontology,
            tok,
            template,
            template_source,
            grammar,
            trie,
            model: Mutex::new(model),
            prefix: None,
            bos,
            eos,
            max_answer_tokens: cfg.max_answer_tokens,
        };
        inner.prime()?;
        Ok(Self {
            name: format!("gguf:{model_name}"),
            family,
            inner,
        })
    }

    pub fn ontology(&self) -> &Ontology {
        &self.inner.ontology
    }

    pub fn family(&self) -> Family {
        self.family
    }

    pub fn template_source(&self) -> &TemplateSource {
        &self.inner.template_source
    }

    pub fn tokenizer(&self) -> &GgufTokenizer {
        &self.inner.tok
    }

    /// The rendered prompt for an answer (system and user turn, generation prompt).
    pub fn prompt(&self, text: &str) -> Result<String, LabelerError> {
        self.inner.render(text)
    }

    /// Generates the label list for one answer (blocking).
    pub fn generate(&self, text: &str) -> Result<Generation, LabelerError> {
        self.inner.generate(text, true, &AtomicBool::new(false))
    }

    /// As [`GgufLabeler::generate`], never using the cached system prompt; exists to check
    /// that the cached path gives the same answer.
    pub fn generate_uncached(&self, text: &str) -> Result<Generation, LabelerError> {
        self.inner.generate(text, false, &AtomicBool::new(false))
    }
}

impl Inner {
    fn render(&self, text: &str) -> Result<String, LabelerError> {
        let clean = self.tok.strip_control(text);
        // Truncate by tokens of the answer alone, before it enters the prompt.
        let body = {
            let ids = self.tok.encode_prompt(&clean)?;
            let skip = usize::from(self.tok.add_bos() && ids.first() == self.tok.bos_id().as_ref());
            if ids.len() - skip > self.max_answer_tokens {
                self.tok.decode(&ids[skip..skip + self.max_answer_tokens])
            } else {
                clean
            }
        };
        let messages = [
            Message::new("system", &self.system),
            Message::new("user", &user_prompt(&body)),
        ];
        Ok(self.template.render(&messages, &self.bos, &self.eos)?)
    }

    /// Caches the system part of the prompt (see `llm::model`).
    fn prime(&mut self) -> Result<(), LabelerError> {
        let mut model = self.model.lock().map_err(poisoned)?;
        let Some(_) = model.snapshot() else {
            return Ok(());
        };
        let probe = self.render("x")?;
        let Some(cut) = probe.find(&user_prompt("x")) else {
            return Ok(());
        };
        let mut ids = self.tok.encode_prompt(&probe[..cut])?;
        // The last tokens of a cut string may merge differently in the full prompt.
        ids.truncate(ids.len().saturating_sub(2));
        if ids.is_empty() {
            return Ok(());
        }
        model.reset();
        model.feed(&ids)?;
        let snap = model.snapshot().ok_or_else(|| {
            LabelerError::Internal("model family lost its snapshot support".into())
        })?;
        model.reset();
        drop(model);
        self.prefix = Some(Prefix { ids, model: snap });
        Ok(())
    }

    /// Greedy constrained generation; stops with [`LabelerError::Cancelled`] at the next token
    /// once `cancel` is set.
    fn generate(
        &self,
        text: &str,
        use_prefix: bool,
        cancel: &AtomicBool,
    ) -> Result<Generation, LabelerError> {
        let prompt = self.render(text)?;
        let ids = self.tok.encode_prompt(&prompt)?;
        let mut guard = self.model.lock().map_err(poisoned)?;
        let mut owned;
        let (model, cached): (&mut Decoder, usize) = match &self.prefix {
            Some(p) if use_prefix && ids.len() > p.ids.len() && ids.starts_with(&p.ids) => {
                owned = p.model.snapshot().ok_or_else(|| {
                    LabelerError::Internal("cached prefix cannot be cloned".into())
                })?;
                (&mut owned, p.ids.len())
            }
            _ => {
                guard.reset();
                (&mut *guard, 0)
            }
        };
        let mut logits = model.feed(&ids[cached..])?;
        let mut state = self.grammar.start();
        let mut tokens = Vec::new();
        let mut labels = Vec::new();
        let mut min_lp = 0f32;
        loop {
            let allowed = self.trie.allowed(&self.grammar, &state);
            if allowed.is_empty() {
                return Err(LabelerError::Internal(
                    "constrained decoding reached a state with no allowed token".into(),
                ));
            }
            let ids_allowed: Vec<u32> = allowed.iter().map(|(i, _)| *i).collect();
            let (best, _) = allowed.iter().enumerate().fold(
                (0usize, f32::NEG_INFINITY),
                |(bi, bv), (j, (id, _))| {
                    let v = logits[*id as usize];
                    // Ties go to the lower token id, so decoding is deterministic.
                    if v > bv || (v == bv && *id < allowed[bi].0) {
                        (j, v)
                    } else {
                        (bi, bv)
                    }
                },
            );
            let (id, next) = allowed[best].clone();
            let lp = log_softmax_at(&logits, &ids_allowed, id);
            min_lp = min_lp.min(lp);
            let before = state.written().len();
            state = next;
            tokens.push(id);
            if state.written().len() > before {
                for &k in &state.written()[before..] {
                    labels.push((k, min_lp.exp()));
                }
                min_lp = 0.0;
            }
            if state.is_done() {
                break;
            }
            if cancel.load(Ordering::Relaxed) {
                return Err(LabelerError::Cancelled);
            }
            logits = model.feed(&[id])?;
        }
        drop(guard);
        Ok(Generation {
            text: self.tok.decode(&tokens),
            tokens,
            labels,
            prompt_tokens: ids.len(),
            cached_prompt_tokens: cached,
        })
    }

    fn label(&self, text: &str, cancel: &AtomicBool) -> Result<LabelerOutput, LabelerError> {
        if cancel.load(Ordering::Relaxed) {
            return Err(LabelerError::Cancelled);
        }
        let g = self.generate(text, true, cancel)?;
        let n = self.ontology.len();
        let mut scores = vec![0f32; n];
        let mut on = vec![false; n];
        let mut evidence = Vec::new();
        for &(k, s) in &g.labels {
            scores[k] = s;
            on[k] = true;
            evidence.push(Evidence {
                label: self.ontology.labels()[k].id.clone(),
                clause: String::new(),
                score: s,
                negated: false,
                hedged: false,
                source: EvidenceSource::Llm,
                accepted: true,
            });
        }
        let mut out = LabelerOutput::from_decisions(&self.ontology, &scores, &on);
        out.evidence = evidence;
        Ok(out)
    }
}

fn poisoned<T>(_: std::sync::PoisonError<T>) -> LabelerError {
    LabelerError::Internal("a previous generation panicked".into())
}

impl BlockingLabeler for GgufLabeler {
    fn name(&self) -> &str {
        &self.name
    }

    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError> {
        self.inner.label(text, &AtomicBool::new(false))
    }

    /// Generation takes seconds per answer on CPU: an abandoned round stops at its next token.
    fn label_batch_cancellable(
        &self,
        texts: &[&str],
        cancel: &AtomicBool,
    ) -> Result<Vec<LabelerOutput>, LabelerError> {
        texts.iter().map(|t| self.inner.label(t, cancel)).collect()
    }
}
