//! Chat templates: the Jinja template stored in a GGUF's `tokenizer.chat_template`, rendered
//! with minijinja (the renderer lives in `vlmfuse_models::chat_template`) the way transformers' `apply_chat_template` renders it with jinja2
//! (`trim_blocks`, `lstrip_blocks`, Python string methods, `raise_exception`, `tojson`).
//!
//! Why the file's own template: an instruct model only follows instructions in the exact turn
//! format it was tuned on, and that format differs per family and even per release. A file
//! without a template (base models such as gemma-3-270m) gets its family's turn format from
//! [`fallback_template`], and the labeler logs that it did.

pub use vlmfuse_models::chat_template::{ChatTemplate, Message, TEMPLATE_DATE};

/// The model families whose turn formats the labeler knows without a template in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TemplateFamily {
    Llama3,
    ChatMl,
    Gemma,
}

/// Turn formats for files that carry no template. Written for this crate from the families'
/// documented formats; the system message goes where each family expects it (Gemma has no
/// system role and reads it at the top of the first user turn).
pub fn fallback_template(family: TemplateFamily) -> &'static str {
    match family {
        TemplateFamily::Llama3 => {
            "{{- bos_token }}\
{%- for m in messages %}\
<|start_header_id|>{{ m.role }}<|end_header_id|>\n\n{{ m.content | trim }}<|eot_id|>\
{%- endfor %}\
{%- if add_generation_prompt %}<|start_header_id|>assistant<|end_header_id|>\n\n{% endif %}"
        }
        TemplateFamily::ChatMl => {
            "{% for m in messages %}<|im_start|>{{ m.role }}\n{{ m.content }}<|im_end|>\n{% endfor %}\
{% if add_generation_prompt %}<|im_start|>assistant\n\
{% if enable_thinking is defined and not enable_thinking %}<think>\n\n</think>\n\n{% endif %}\
{% endif %}"
        }
        TemplateFamily::Gemma => {
            "{{ bos_token }}\
{% if messages[0].role == 'system' %}\
{% set first = messages[0].content + '\n\n' %}{% set rest = messages[1:] %}\
{% else %}{% set first = '' %}{% set rest = messages %}{% endif %}\
{% for m in rest %}\
{% if m.role == 'assistant' %}{% set role = 'model' %}{% else %}{% set role = m.role %}{% endif %}\
<start_of_turn>{{ role }}\n{% if loop.first %}{{ first }}{% endif %}{{ m.content | trim }}<end_of_turn>\n\
{% endfor %}\
{% if add_generation_prompt %}<start_of_turn>model\n{% endif %}"
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msgs() -> Vec<Message> {
        vec![
            Message::new("system", "Label it."),
            Message::new("user", "Brake now."),
        ]
    }

    #[test]
    fn fallbacks_render_each_family_turn_format() {
        let l = ChatTemplate::new(fallback_template(TemplateFamily::Llama3)).unwrap();
        assert_eq!(
            l.render(&msgs(), "<|begin_of_text|>", "<|eot_id|>")
                .unwrap(),
            "<|begin_of_text|><|start_header_id|>system<|end_header_id|>\n\nLabel it.<|eot_id|>\
<|start_header_id|>user<|end_header_id|>\n\nBrake now.<|eot_id|>\
<|start_header_id|>assistant<|end_header_id|>\n\n"
        );
        let q = ChatTemplate::new(fallback_template(TemplateFamily::ChatMl)).unwrap();
        assert_eq!(
            q.render(&msgs(), "", "<|im_end|>").unwrap(),
            "<|im_start|>system\nLabel it.<|im_end|>\n<|im_start|>user\nBrake now.<|im_end|>\n\
<|im_start|>assistant\n<think>\n\n</think>\n\n"
        );
        let g = ChatTemplate::new(fallback_template(TemplateFamily::Gemma)).unwrap();
        assert_eq!(
            g.render(&msgs(), "<bos>", "<eos>").unwrap(),
            "<bos><start_of_turn>user\nLabel it.\n\nBrake now.<end_of_turn>\n<start_of_turn>model\n"
        );
    }

    #[test]
    fn python_string_methods_and_errors_work() {
        let t = ChatTemplate::new(
            "{% if messages[0].content.startswith('x') %}{{ raise_exception('no x') }}{% endif %}\
{{ messages[0].content.strip().upper() }}|{{ strftime_now('%d %b %Y') }}",
        )
        .unwrap();
        assert_eq!(
            t.render(&[Message::new("user", "  hi ")], "", "").unwrap(),
            "HI|26 Jul 2024"
        );
        let e = t.render(&[Message::new("user", "xx")], "", "").unwrap_err();
        assert!(e.to_string().contains("no x"), "{e}");
        assert!(ChatTemplate::new("{% if %}").is_err());
    }
}
