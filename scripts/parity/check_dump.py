#!/usr/bin/env python3
"""Checks a `vlmfuse describe --dump DIR` against transformers on the same checkpoint.

Feeds transformers exactly the dumped model inputs (input ids, pixel values, grid), so the check
isolates the model from preprocessing (the parity tests cover the processors), and prints:

  - the max abs difference of the first-token logits (and its share of the logit range);
  - whether transformers' greedy ids (stopping at the checkpoint's EOS ids) equal the dumped
    `generated_ids.json`.

Exit status 0 when the logits agree within --tol and the ids match, 1 otherwise.

    vlmfuse describe clip.mp4 --config vlmfuse.toml --reporter NAME --dump /tmp/d
    "${PYTHON:-python3}" scripts/parity/check_dump.py /tmp/d [--weights DIR] [--tol 1e-4]

Needs torch, transformers (5.23 here), numpy; peft when the reporter has a LoRA adapter ($PYTHON:
such a Python, e.g. a reference venv outside the repository; default python3). Not run in CI (no
torch there). The reporter must run in f32 for the 1e-4 tolerance to make sense.
"""

import argparse
import json
import os
import sys
import warnings

import numpy as np
import torch

warnings.filterwarnings("ignore")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import transformers  # noqa: E402


def read_json(d, name):
    with open(os.path.join(d, name)) as f:
        return json.load(f)


def eos_ids(weights, tokenizer_extra):
    """The ids the Rust reporter stops at: generation_config.json's eos_token_id, plus
    `tokenizer_extra` (Qwen's <|im_end|>)."""
    ids = []
    p = os.path.join(weights, "generation_config.json")
    if os.path.exists(p):
        with open(p) as f:
            e = json.load(f).get("eos_token_id")
        ids = e if isinstance(e, list) else ([e] if e is not None else [])
    return sorted(set(ids + tokenizer_extra))


def qwen_inputs(d, weights):
    from transformers import PreTrainedTokenizerFast, Qwen3VLForConditionalGeneration

    model = Qwen3VLForConditionalGeneration.from_pretrained(weights, dtype=torch.float32).eval()
    tok = PreTrainedTokenizerFast(tokenizer_file=os.path.join(weights, "tokenizer.json"))
    ids = torch.tensor([read_json(d, "input_ids.json")], dtype=torch.long)
    grid = read_json(d, "grid.json")
    pv = torch.from_numpy(np.load(os.path.join(d, "pixel_values.npy")))
    video = model.config.video_token_id
    inputs = {
        "input_ids": ids,
        "attention_mask": torch.ones_like(ids),
        "mm_token_type_ids": (ids == video).long() * 2,
        "pixel_values_videos": pv,
        "video_grid_thw": torch.tensor([[grid["t"], grid["h"], grid["w"]]], dtype=torch.long),
    }
    extra = [tok.convert_tokens_to_ids("<|im_end|>")] if "<|im_end|>" in tok.get_vocab() else []
    return model, inputs, eos_ids(weights, extra)


def llava_inputs(d, weights):
    from transformers import VideoLlavaForConditionalGeneration

    model = VideoLlavaForConditionalGeneration.from_pretrained(weights, dtype=torch.float32).eval()
    ids = torch.tensor([read_json(d, "input_ids.json")], dtype=torch.long)
    pv = torch.from_numpy(np.load(os.path.join(d, "pixel_values.npy")))[None]
    inputs = {"input_ids": ids, "attention_mask": torch.ones_like(ids), "pixel_values_videos": pv}
    return model, inputs, eos_ids(weights, [])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dump", help="directory written by `vlmfuse describe --dump`")
    ap.add_argument("--weights", help="checkpoint directory (default: the dump's meta.json)")
    ap.add_argument("--tol", type=float, default=1e-4, help="max abs logit difference allowed")
    a = ap.parse_args()
    meta = read_json(a.dump, "meta.json")
    weights = a.weights or meta.get("weights")
    if not weights or not os.path.isdir(weights):
        sys.exit(f"no checkpoint directory (meta.json says {weights!r}); pass --weights DIR")
    if meta.get("dtype") not in (None, "f32", "float32"):
        print(f"warning: the reporter ran in {meta['dtype']}; the reference runs in f32")
    kind = meta["model_type"]
    build = {"qwen3_vl": qwen_inputs, "video_llava": llava_inputs}.get(kind)
    if build is None:
        sys.exit(f"model_type {kind!r} is not one this script knows")
    torch.manual_seed(0)
    model, inputs, eos = build(a.dump, weights)
    if meta.get("adapter"):
        from peft import PeftModel  # only needed with an adapter

        model = PeftModel.from_pretrained(model, meta["adapter"]).merge_and_unload().eval()

    ours_logits = np.load(os.path.join(a.dump, "first_token_logits.npy")).astype(np.float32)
    ours_ids = read_json(a.dump, "generated_ids.json")
    with torch.no_grad():
        ref = model(**inputs).logits[0, -1].float().numpy()
        n_new = meta.get("max_new_tokens") or max(len(ours_ids), 1)
        gen = model.generate(**inputs, do_sample=False, max_new_tokens=n_new,
                             eos_token_id=eos or None, pad_token_id=(eos or [0])[0])
    ref_ids = gen[0, inputs["input_ids"].shape[1]:].tolist()
    while ref_ids and ref_ids[-1] in eos:
        ref_ids.pop()
    cut = next((i for i, t in enumerate(ref_ids) if t in eos), len(ref_ids))
    ref_ids = ref_ids[:cut]

    diff = float(np.abs(ref - ours_logits).max())
    span = float(ref.max() - ref.min())
    same = ref_ids == ours_ids
    print(f"model_type        {kind} (transformers {transformers.__version__}, torch {torch.__version__})")
    print(f"checkpoint        {weights}")
    print(f"prompt tokens     {inputs['input_ids'].shape[1]}")
    print(f"first-token logits max |diff| {diff:.3e} ({100 * diff / max(span, 1e-12):.2e}% of the range {span:.2f})")
    print(f"greedy ids        {'identical' if same else 'DIFFER'} ({len(ours_ids)} generated)")
    if not same:
        print(f"  vlmfuse      {ours_ids}")
        print(f"  transformers {ref_ids}")
    ok = diff <= a.tol and same
    print("OK" if ok else "MISMATCH")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
