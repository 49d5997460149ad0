//! The one prompt and the one validator that every LLM labeler uses, in process (GGUF) or remote
//! (OpenAI-compatible), so that switching the engine changes the model and nothing else.
//!
//! The answer format is a JSON object `{"labels": [ids]}`: an object because OpenAI-style JSON
//! mode only guarantees objects, and the same shape lets the in-process labeler's decoding
//! automaton and the remote labeler's validator accept exactly the same strings.

use crate::Ontology;
use serde_json::Value;

/// Rules that hold for any label set: what counts as a label at all.
const GENERAL_RULES: &str = "\
- A label applies when the text recommends that action for our own vehicle (an imperative, \
\"should ...\", \"consider ...\"), or states that the scene contains that thing.
- Hedged or conditional advice is NOT a label: \"be prepared to X\", \"be ready to X\", \"may \
need to X\", \"X if ...\", \"watch for X\".
- Negated mentions are NOT labels: \"no need to brake\", \"there is no traffic light\", \"the \
weather is not a factor\".
- What other road users do is not advice for our vehicle (\"the truck ahead may stop\").
- Scene facts that imply a label count (a red light means there is a traffic light ahead).";

/// The opening of the assistant's answer; the in-process labeler's automaton starts here too.
pub const ANSWER_OPEN: &str = "{\"labels\": [";
/// The end of the assistant's answer.
pub const ANSWER_CLOSE: &str = "]}";

/// System message: the task, the rules, and the labels with their descriptions.
pub fn system_prompt(ontology: &Ontology) -> String {
    let mut s = String::from(
        "You label driving advice. A vision-language model watched a dashcam clip and wrote a \
         scene description, recommended manoeuvres and a rationale. List every label from the \
         list below that its text supports, following these rules:\n",
    );
    s.push_str(GENERAL_RULES);
    s.push_str("\n\nLabels (id: meaning):\n");
    for l in ontology.labels() {
        s.push_str(&format!("- {}: {}\n", l.id, l.gloss()));
    }
    s.push_str(&format!(
        "\nAnswer with a JSON object only, no prose: {ANSWER_OPEN}\"id\", ...{ANSWER_CLOSE}. Use only \
         the ids above, each at most once, in any order. Use an empty list when none applies."
    ));
    s
}

/// User message: the VLM's answer, verbatim between markers so that an answer which itself
/// contains instructions is read as data.
pub fn user_prompt(text: &str) -> String {
    format!("Text to label:\n<<<\n{}\n>>>", text.trim())
}

/// Strictly parses `{"labels": [...]}` (optionally inside a ```json fence, which many models add
/// even in JSON mode). Every entry must resolve to an ontology label (an id, or a display name:
/// models often echo the words they were shown); duplicates are harmless. Returns one flag per
/// ontology label.
pub fn parse_labels(ontology: &Ontology, content: &str) -> Result<Vec<bool>, String> {
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

    #[test]
    fn prompt_lists_every_label_and_the_answer_shape() {
        let o = Ontology::default_driving();
        let p = system_prompt(&o);
        for l in o.labels() {
            assert!(p.contains(&format!("- {}: ", l.id)), "{}", l.id);
        }
        assert!(p.contains("{\"labels\": [\"id\", ...]}"), "{p}");
        assert!(user_prompt("  Brake.\n").contains("<<<\nBrake.\n>>>"));
    }
}
