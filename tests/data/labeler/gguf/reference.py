#!/usr/bin/env python3
"""Reference outputs of transformers for the tiny random GGUF files of each family.

The GGUF labeler runs candle's quantized models with a tokenizer and chat template built from the
file's metadata. transformers loads the same GGUF files (its own tokenizer conversion, jinja2 for
the template, PyTorch for the model), so agreeing with it on tiny files checks every piece:

    cargo run -p vlmfuse-labeler --example write_tiny_ggufs -- /tmp/tiny
    /work/venv-ref/bin/python tests/data/labeler/gguf/reference.py /tmp/tiny > tests/data/labeler/gguf/reference.json

and, when the real gemma-3-270m is fetched (scripts/fetch-assets.sh), the tokenizer of the real
262k vocabulary:

    /work/venv-ref/bin/python tests/data/labeler/gguf/reference.py --gemma ~/.cache/vlmfuse-assets/gemma-3-270m-q4_k_m.gguf \
        > tests/data/labeler/gguf/gemma_tokenizer.json

Needs torch, transformers and gguf (pip install gguf). CI does not run this: the Rust tests read
the committed JSON.
"""
import json
import os
import sys

import torch
from transformers import AutoConfig, AutoModelForCausalLM, AutoTokenizer

FAMILIES = ["llama", "qwen2", "qwen3", "gemma3"]

# Texts that exercise the tokenizers: the answer format, ids with underscores, contractions,
# digits, newlines, non-ASCII, and control tokens written literally (they must stay whole).
TEXTS = [
    '{"labels": ["turn_left", "brake"]}',
    "Brake now, the light is red. Don't turn right!",
    "Speed 30 km/h, 2 lanes\n\n- merge  left",
    "Ünïcödé — café, naïve ≠ ascii 😀",
]

MESSAGES = [
    {"role": "system", "content": "You label driving advice. Answer with JSON only."},
    {"role": "user", "content": "Text to label:\n<<<\nSlow down and stop at the red light.\n>>>"},
]

GREEDY_STEPS = 8
DATE = "26 Jul 2024"


def fingerprint(path):
    h = 0xCBF29CE484222325
    with open(path, "rb") as f:
        data = f.read()
    for b in data:
        h ^= b
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return f"{h:016x}"


def family_reference(directory, family):
    name = f"tiny-{family}.gguf"
    path = os.path.join(directory, name)
    tok = AutoTokenizer.from_pretrained(directory, gguf_file=name)
    config = AutoConfig.from_pretrained(directory, gguf_file=name)
    if family == "gemma3":
        # candle and llama.cpp scale Gemma 3 attention by 1/sqrt(head_dim); transformers by
        # 1/sqrt(query_pre_attn_scalar), which equals head_dim in the released models.
        config.query_pre_attn_scalar = config.head_dim
    if family == "qwen3":
        # transformers does not read qwen3.attention.key_length and keeps Qwen3's default head
        # size (128, which every released Qwen3 has); the tiny file uses 16.
        config.head_dim = config.hidden_size // config.num_attention_heads
    model = AutoModelForCausalLM.from_pretrained(
        directory, gguf_file=name, config=config, dtype=torch.float32
    )
    model.eval()
    texts = [{"text": t, "ids": tok(t, add_special_tokens=False)["input_ids"]} for t in TEXTS]
    prompt = tok.apply_chat_template(
        MESSAGES,
        tokenize=False,
        add_generation_prompt=True,
        enable_thinking=False,
        date_string=DATE,
    )
    prompt_ids = tok(prompt, add_special_tokens=False)["input_ids"]
    with torch.no_grad():
        ids = torch.tensor([prompt_ids])
        logits = model(ids).logits[0, -1].tolist()
        greedy = []
        cur = ids
        for _ in range(GREEDY_STEPS):
            nxt = int(model(cur).logits[0, -1].argmax())
            greedy.append(nxt)
            cur = torch.cat([cur, torch.tensor([[nxt]])], dim=1)
    return {
        "family": family,
        "file": name,
        "fingerprint": fingerprint(path),
        "texts": texts,
        "messages": MESSAGES,
        "prompt": prompt,
        "prompt_ids": prompt_ids,
        "last_logits": [round(x, 6) for x in logits],
        "greedy": greedy,
    }


def gemma_tokenizer(path):
    directory, name = os.path.split(path)
    tok = AutoTokenizer.from_pretrained(directory, gguf_file=name)
    texts = TEXTS + [
        "1. Scene: A zebra crossing ahead; pedestrians waiting.\n2. Manoeuvre: Slow down, then stop.",
        "<start_of_turn>user\nHello<end_of_turn>\n<start_of_turn>model\n",
        "  two  spaces and\ttabs\n\n\nthree newlines",
    ]
    return {
        "fingerprint": fingerprint(path),
        "texts": [{"text": t, "ids": tok(t, add_special_tokens=False)["input_ids"]} for t in texts],
    }


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "--gemma":
        out = gemma_tokenizer(sys.argv[2])
    elif len(sys.argv) == 2:
        out = {"families": [family_reference(sys.argv[1], f) for f in FAMILIES]}
    else:
        sys.exit(__doc__)
    json.dump(out, sys.stdout, ensure_ascii=False, indent=1)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
