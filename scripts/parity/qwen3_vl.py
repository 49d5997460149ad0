#!/usr/bin/env python3
"""Reference outputs of transformers' Qwen3-VL on the project's own tiny fixture.

Builds, with transformers' `Qwen3VLForConditionalGeneration` and `Qwen3VLProcessor` on CPU in
f32, from the files the Rust fixture writer produces (`TinyQwen3Vl`, seed 7):

  tests/data/parity/qwen3_vl/reference.json      first-token logits, 16 greedy ids and the
                                                 logits of the 16th, input ids, per case
                                                 (2 and 8 frames, text only, two prompts) and
                                                 for a left-padded batch of three
  tests/data/parity/qwen3_vl/preprocessing.json  the video processor's pixel values (as grey
                                                 levels), grids, resized sizes, prompt text and
                                                 ids for synthetic frames (rounding, odd frame
                                                 count, budget shrink, tiny frames, per-frame
                                                 cap), and frame sampling indices

The Rust tests (crates/vlmfuse-models/tests/qwen3_vl_parity.rs) compare against these files; CI
has no torch and never runs this script. Run it after changing the fixture or the cases, with a
Python that has the packages below ($PYTHON, e.g. a reference venv outside the repository;
default python3):

    "${PYTHON:-python3}" scripts/parity/qwen3_vl.py            # builds the fixture with cargo
    "${PYTHON:-python3}" scripts/parity/qwen3_vl.py --fixture DIR
    "${PYTHON:-python3}" scripts/parity/qwen3_vl.py --candle-transformers

With --candle-transformers it then measures candle-transformers' own `qwen3_vl` against the same
references (the cargo example `candle_transformers_qwen3_vl`, which needs no torch and can be
run alone against the committed files): the ids, pixels and grid of the 8-frame case fed as one
chunk, and as the service ran it before owning the model (text token by token, the video span as
one chunk). This is the documented reason the models crate carries its own Qwen3-VL, kept as a
measurement rather than a test so that an upstream fix shows up as a number, not a red build.
With candle-transformers 0.11.1 (1-D positions instead of M-RoPE, no causal mask inside a chunk,
tanh GELU in the patch merger):

    case video8_describe, logit range 14.03, tolerance 1e-4
    one chunk                      max |d| 0.962   (outside)
    causal text + video chunk      max |d| 0.923   (outside)

When both come within the tolerance, upstream computes what transformers computes and the own
model could give way to it.

Needs torch 2.15.0, transformers 5.23.0, torchvision 0.29.2 (video processor), numpy,
safetensors.
"""

import argparse
import base64
import json
import os
import subprocess
import sys
import tempfile
import warnings

import numpy as np
import torch

warnings.filterwarnings("ignore")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import transformers  # noqa: E402
from safetensors.numpy import load_file  # noqa: E402
from transformers import (  # noqa: E402
    PreTrainedTokenizerFast,
    Qwen2VLImageProcessor,
    Qwen3VLForConditionalGeneration,
    Qwen3VLProcessor,
)
from transformers.models.qwen3_vl.video_processing_qwen3_vl import (  # noqa: E402
    Qwen3VLVideoProcessor,
)
from transformers.video_utils import VideoMetadata  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
OUT = os.path.join(ROOT, "tests", "data", "parity", "qwen3_vl")
SEED = 7
GREEDY = 16


def frames(n, w, h, k0=0):
    """The synthetic clip the Rust tests rebuild (integer formula, identical in both)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.int64)
    out = []
    for k in range(k0, k0 + n):
        chans = []
        for c in range(3):
            v = 3 * x * x + 5 * y + 71 * c + 29 * k + (x * y) % 17 + 60 * (((x >> 2) + (y >> 2)) & 1)
            chans.append(v % 256)
        out.append(np.stack(chans, -1))
    return np.stack(out).astype(np.uint8)


# Logits cases: frames are 64x64 (the fixture's budget keeps them as they are), so the model
# sees exactly the pixels the Rust side builds; resizing is covered by PREPROCESSING.
CASES = [
    {"name": "video2_describe", "frames": 2, "width": 64, "height": 64, "k0": 0,
     "indices": [0, 3], "video_fps": 6.0, "prompt": "describe the dashcam clip"},
    {"name": "video8_describe", "frames": 8, "width": 64, "height": 64, "k0": 0,
     "indices": [0, 4, 8, 12, 16, 20, 24, 28], "video_fps": 10.0,
     "prompt": "describe the dashcam clip"},
    {"name": "video8_light", "frames": 8, "width": 64, "height": 64, "k0": 5,
     "indices": [1, 5, 9, 13, 17, 21, 25, 29], "video_fps": 8.0,
     "prompt": "is the light red or green ahead"},
    {"name": "text_describe", "frames": 0, "prompt": "describe the road ahead and the car"},
]
BATCH = ["video2_describe", "text_describe", "video8_light"]

PREPROCESSING = [
    {"name": "round_50x30_4f", "frames": 4, "width": 50, "height": 30, "k0": 0,
     "indices": [0, 2, 4, 6], "video_fps": 4.0, "overrides": {}},
    {"name": "odd_44x28_3f", "frames": 3, "width": 44, "height": 28, "k0": 3,
     "indices": [0, 5, 10], "video_fps": 5.0, "overrides": {}},
    {"name": "shrink_64x48_4f", "frames": 4, "width": 64, "height": 48, "k0": 1,
     "indices": [0, 1, 2, 3], "video_fps": 2.0,
     "overrides": {"size": {"shortest_edge": 256, "longest_edge": 4096}}},
    {"name": "tiny_6x5_2f", "frames": 2, "width": 6, "height": 5, "k0": 2,
     "indices": [0, 7], "video_fps": 7.0, "overrides": {}},
    {"name": "cap_96x64_4f", "frames": 4, "width": 96, "height": 64, "k0": 4,
     "indices": [0, 3, 6, 9], "video_fps": 3.0,
     "overrides": {"cap_pixels_per_frame": True, "max_video_tokens": 4}},
]
SAMPLING = [(30, 10.0), (7, 30.0), (1000, 25.0), (100, 29.97), (3, 1.0)]
PREPROCESS_PROMPT = "describe the clip"


def build_fixture(dir_):
    subprocess.run(
        ["cargo", "run", "-q", "-p", "vlmfuse-models", "--example", "write_fixture", "--",
         "qwen3_vl", dir_, "--seed", str(SEED)],
        cwd=ROOT, check=True)


def chat(prompt, video):
    v = "<|video_pad|>" if video else ""
    return f"<|im_start|>user\n{v}{prompt}<|im_end|>\n<|im_start|>assistant\n"


class Recorder:
    """Wraps the tokenizer call to capture the exact text the processor tokenizes."""

    def __init__(self, tok):
        self.texts = []
        cls = tok.__class__
        orig = cls.__call__
        rec = self

        def spy(self_, *a, **k):
            t = a[0] if a else k.get("text")
            rec.texts.append(t)
            return orig(self_, *a, **k)

        cls.__call__ = spy


def load(dir_):
    tok = PreTrainedTokenizerFast(tokenizer_file=os.path.join(dir_, "tokenizer.json"))
    tok.pad_token = "<|endoftext|>"
    tok.padding_side = "left"
    vp = Qwen3VLVideoProcessor.from_pretrained(dir_)
    ip = Qwen2VLImageProcessor.from_pretrained(dir_)
    proc = Qwen3VLProcessor(image_processor=ip, tokenizer=tok, video_processor=vp)
    model = Qwen3VLForConditionalGeneration.from_pretrained(dir_, dtype=torch.float32).eval()
    # The greedy reference runs 16 tokens whatever the random model picks.
    model.generation_config.eos_token_id = None
    model.generation_config.pad_token_id = tok.pad_token_id
    return tok, proc, model


def inputs_for(proc, cases, **kw):
    texts, videos, metas = [], [], []
    for c in cases:
        texts.append(chat(c["prompt"], c["frames"] > 0))
        if c["frames"] > 0:
            videos.append(frames(c["frames"], c["width"], c["height"], c["k0"]))
            metas.append(VideoMetadata(total_num_frames=max(c["indices"]) + 1,
                                       fps=c["video_fps"], frames_indices=list(c["indices"])))
    args = dict(text=texts, return_tensors="pt", padding=True, **kw)
    if videos:
        args.update(videos=videos, video_metadata=metas, do_sample_frames=False)
    return proc(**args)


def run_case(model, inputs):
    with torch.no_grad():
        first = model(**inputs).logits[:, -1, :].float()
        gen = model.generate(**inputs, max_new_tokens=GREEDY, do_sample=False,
                             output_logits=True, return_dict_in_generate=True)
    n = inputs["input_ids"].shape[1]
    ids = gen.sequences[:, n:].tolist()
    last = gen.logits[-1].float()
    return first, ids, last


def grey(pv):
    g = np.rint(pv.numpy().astype(np.float64) * 127.5 + 127.5)
    assert np.abs(g - (pv.numpy() * 127.5 + 127.5)).max() < 1e-3, "pixel values are not grey levels"
    return base64.b64encode(np.clip(g, 0, 255).astype(np.uint8).tobytes()).decode()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fixture", help="directory written by `write_fixture qwen3_vl` (else built)")
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--candle-transformers", action="store_true",
                    help="then measure candle-transformers' qwen3_vl against the references")
    a = ap.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    tmp = None
    if a.fixture is None:
        tmp = tempfile.TemporaryDirectory()
        a.fixture = tmp.name
        build_fixture(a.fixture)
    tok, proc, model = load(a.fixture)
    rec = Recorder(tok)
    weights = load_file(os.path.join(a.fixture, "model.safetensors"))
    meta = {
        "generator": "scripts/parity/qwen3_vl.py",
        "transformers": transformers.__version__,
        "torch": torch.__version__,
        "attn_implementation": model.config._attn_implementation,
        "dtype": "float32",
        "fixture": {"model": "TinyQwen3Vl::default()", "seed": SEED,
                    "tensor_sums": {k: float(np.asarray(v, dtype=np.float64).sum())
                                    for k, v in sorted(weights.items())}},
    }

    cases = []
    for c in CASES:
        rec.texts.clear()
        inp = inputs_for(proc, [c])
        first, ids, last = run_case(model, inp)
        fl = first[0]
        case = dict(c)
        case.update({
            "prompt_text": rec.texts[-1][0] if isinstance(rec.texts[-1], list) else rec.texts[-1],
            "input_ids": inp["input_ids"][0].tolist(),
            "video_grid_thw": inp["video_grid_thw"][0].tolist() if "video_grid_thw" in inp else None,
            "pixel_sum": float(inp["pixel_values_videos"].double().sum()) if "pixel_values_videos" in inp else None,
            "first_logits": fl.tolist(),
            "logit_range": float(fl.max() - fl.min()),
            "greedy_ids": ids[0],
            "greedy_last_logits": last[0].tolist(),
        })
        cases.append(case)
        print(f"{c['name']}: {len(case['input_ids'])} tokens, greedy {ids[0]}", file=sys.stderr)

    by = {c["name"]: c for c in CASES}
    inp = inputs_for(proc, [by[n] for n in BATCH])
    first, ids, last = run_case(model, inp)
    mask = inp["attention_mask"]
    batch = {
        "rows": BATCH,
        "padding": (mask.shape[1] - mask.sum(1)).tolist(),
        "first_logits": first.tolist(),
        "greedy_ids": ids,
        "greedy_last_logits": last.tolist(),
    }
    print(f"batch: padding {batch['padding']}, greedy {ids}", file=sys.stderr)

    prep = []
    for c in PREPROCESSING:
        rec.texts.clear()
        video = frames(c["frames"], c["width"], c["height"], c["k0"])
        md = VideoMetadata(total_num_frames=max(c["indices"]) + 1, fps=c["video_fps"],
                           frames_indices=list(c["indices"]))
        # Overrides go into the video processor's config, as a checkpoint would set them
        # (`max_video_tokens`, for one, is only read from the instance, never from call kwargs).
        p = proc
        if c["overrides"]:
            vp_c = Qwen3VLVideoProcessor.from_pretrained(a.fixture, **c["overrides"])
            p = Qwen3VLProcessor(image_processor=proc.image_processor, tokenizer=tok,
                                 video_processor=vp_c)
        out = p(text=[chat(PREPROCESS_PROMPT, True)], videos=[video], video_metadata=[md],
                do_sample_frames=False, return_tensors="pt")
        g = out["video_grid_thw"][0].tolist()
        pstride = proc.video_processor.patch_size
        entry = dict(c)
        entry.update({
            "prompt": PREPROCESS_PROMPT,
            "resized": [g[1] * pstride, g[2] * pstride],
            "video_grid_thw": g,
            "pixel_grey_b64": grey(out["pixel_values_videos"]),
            "prompt_text": rec.texts[-1][0] if isinstance(rec.texts[-1], list) else rec.texts[-1],
            "input_ids": out["input_ids"][0].tolist(),
        })
        prep.append(entry)
        print(f"{c['name']}: grid {g}", file=sys.stderr)

    vp = proc.video_processor
    sampling = []
    for total, fps in SAMPLING:
        idx = vp.sample_frames(VideoMetadata(total_num_frames=total, fps=fps))
        sampling.append({"total": total, "video_fps": fps, "indices": [int(i) for i in idx]})

    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "reference.json"), "w") as f:
        json.dump({"meta": meta, "cases": cases, "batch": batch}, f, indent=1)
    with open(os.path.join(a.out, "preprocessing.json"), "w") as f:
        json.dump({"meta": {k: meta[k] for k in ("generator", "transformers", "torch")},
                   "video_processor": json.loads(vp.to_json_string()),
                   "cases": prep, "sampling": sampling}, f, indent=1)
    print(f"wrote {a.out}", file=sys.stderr)
    if a.candle_transformers:
        compare_candle_transformers(a.fixture, os.path.join(a.out, "reference.json"))


def compare_candle_transformers(fixture, reference):
    """Runs the cargo example and prints its verdict (see the module docstring)."""
    out = subprocess.run(
        ["cargo", "run", "-q", "-p", "vlmfuse-models", "--example",
         "candle_transformers_qwen3_vl", "--", "--fixture", fixture, "--reference", reference],
        cwd=ROOT, check=True, capture_output=True, text=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    version = "?"
    with open(os.path.join(ROOT, "Cargo.lock")) as f:
        lock = f.read().split("[[package]]")
    for p in lock:
        if 'name = "candle-transformers"' in p:
            version = p.split('version = "')[1].split('"')[0]
    print(f"candle-transformers {version} qwen3_vl, case {r['case']}, "
          f"logit range {r['logit_range']:.2f}, tolerance {r['tolerance']:g}:", file=sys.stderr)
    for key, what in [("one_chunk", "one chunk"),
                      ("causal_text_video_chunk", "causal text + video chunk")]:
        d = r[f"{key}_max_abs_diff"]
        verdict = "within" if d <= r["tolerance"] else "outside"
        print(f"  {what:<28} max |d| {d:.3g} ({verdict})", file=sys.stderr)
    if r["one_chunk_within_tolerance"] and r["causal_within_tolerance"]:
        print("  upstream now agrees with transformers: the own Qwen3-VL could give way to it",
              file=sys.stderr)


if __name__ == "__main__":
    main()
