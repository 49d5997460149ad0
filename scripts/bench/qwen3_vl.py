#!/usr/bin/env python3
"""Qwen3-VL on CPU, f32: vlmfuse's engine against transformers on the same weights, frames and
prompt, in one run. Prints a table of time to first token (preprocessing + vision tower +
prefill) and decode tokens/s, the ratios, and whether both decoded the same greedy ids.

Models: the tiny test fixture (8 frames of 64x64, 256 visual tokens) and a mid-size random one
(text hidden 512, 8 layers; 16 px patches; 8 frames of 256x256, 256 visual tokens), both
written by the `write_fixture` example.

    "${PYTHON:-python3}" scripts/bench/qwen3_vl.py [--runs 5] [--new 32] [--json out.json]

($PYTHON: a Python with torch and transformers, e.g. a reference venv outside the repository;
default python3.) Builds `qwen3_vl_bench` and `write_fixture` in release under $CARGO_TARGET_DIR
(default: the repository's `target/`, as cargo's) unless --bin-dir points at existing binaries. Both engines use all cores
(torch's default intra-op threads, candle's rayon pool) unless --threads says otherwise.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np
import torch

warnings.filterwarnings("ignore")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

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
PROMPT = "describe the dashcam clip"
MODELS = [
    {"name": "tiny", "size": "tiny", "frames": 8, "width": 64, "height": 64},
    {"name": "mid (h512, 8 layers)", "size": "mid", "frames": 8, "width": 256, "height": 256},
]


def frames(n, w, h):
    """The parity tests' synthetic clip (same integer formula as the Rust side)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.int64)
    out = []
    for k in range(n):
        chans = [(3 * x * x + 5 * y + 71 * c + 29 * k + (x * y) % 17
                  + 60 * (((x >> 2) + (y >> 2)) & 1)) % 256 for c in range(3)]
        out.append(np.stack(chans, -1))
    return np.stack(out).astype(np.uint8)


def build(target):
    env = dict(os.environ, CARGO_TARGET_DIR=target)
    subprocess.run(["cargo", "build", "--release", "-q", "-p", "vlmfuse-models",
                    "--example", "qwen3_vl_bench", "--example", "write_fixture"],
                   cwd=ROOT, env=env, check=True)
    return os.path.join(target, "release", "examples")


def hf_bench(dir_, m, runs, new):
    tok = PreTrainedTokenizerFast(tokenizer_file=os.path.join(dir_, "tokenizer.json"))
    proc = Qwen3VLProcessor(image_processor=Qwen2VLImageProcessor.from_pretrained(dir_),
                            tokenizer=tok,
                            video_processor=Qwen3VLVideoProcessor.from_pretrained(dir_))
    model = Qwen3VLForConditionalGeneration.from_pretrained(dir_, dtype=torch.float32).eval()
    model.generation_config.eos_token_id = None
    model.generation_config.pad_token_id = 0
    video = frames(m["frames"], m["width"], m["height"])
    # Same timestamps as the Rust bench: frames 0.5 s apart.
    md = VideoMetadata(total_num_frames=2 * m["frames"], fps=4.0,
                       frames_indices=list(range(0, 2 * m["frames"], 2)))
    text = f"<|im_start|>user\n<|video_pad|>{PROMPT}<|im_end|>\n<|im_start|>assistant\n"

    def prep():
        return proc(text=[text], videos=[video], video_metadata=[md], do_sample_frames=False,
                    return_tensors="pt")

    pre, ttft, tps, ids = [], [], [], None
    with torch.inference_mode():
        for run in range(runs + 1):
            t0 = time.perf_counter()
            inp = prep()
            t1 = time.perf_counter()
            model.generate(**inp, max_new_tokens=1, do_sample=False)
            t2 = time.perf_counter()
            out = model.generate(**inp, max_new_tokens=new, do_sample=False)
            t3 = time.perf_counter()
            if run > 0:
                pre.append((t1 - t0) * 1e3)
                ttft.append((t2 - t0) * 1e3)
                # generate(new) - generate(1) = the new - 1 decode steps.
                tps.append((new - 1) / max((t3 - t2) - (t2 - t1), 1e-9))
            ids = out[0, inp["input_ids"].shape[1]:].tolist()
    return {
        "engine": "transformers",
        "threads": torch.get_num_threads(),
        "prompt_tokens": int(inp["input_ids"].shape[1]),
        "preprocess_ms": statistics.median(pre),
        "ttft_ms": statistics.median(ttft),
        "decode_tokens_per_s": statistics.median(tps),
        "ids": ids,
    }


def ours_bench(bin_dir, dir_, m, runs, new):
    out = subprocess.run(
        [os.path.join(bin_dir, "qwen3_vl_bench"), dir_, "--frames", str(m["frames"]),
         "--size", f"{m['width']}x{m['height']}", "--new", str(new), "--runs", str(runs),
         "--prompt", PROMPT],
        check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--new", type=int, default=32, help="tokens to generate per run")
    ap.add_argument("--bin-dir", help="directory with release qwen3_vl_bench and write_fixture")
    ap.add_argument("--json", help="also write the results here")
    ap.add_argument("--threads", type=int,
                    help="threads for both engines (torch.set_num_threads, RAYON_NUM_THREADS); "
                         "default: all cores. 1 is the least sensitive to a busy machine")
    a = ap.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
        os.environ["RAYON_NUM_THREADS"] = str(a.threads)
    bin_dir = a.bin_dir or build(os.environ.get("CARGO_TARGET_DIR") or os.path.join(ROOT, "target"))
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in MODELS:
            d = os.path.join(tmp, m["size"])
            subprocess.run([os.path.join(bin_dir, "write_fixture"), "qwen3_vl", d,
                            "--size", m["size"], "--seed", "7"], check=True,
                           capture_output=True)
            print(f"{m['name']}: running ours ...", file=sys.stderr)
            ours = ours_bench(bin_dir, d, m, a.runs, a.new)
            print(f"{m['name']}: running transformers ...", file=sys.stderr)
            ref = hf_bench(d, m, a.runs, a.new)
            results.append({"model": m, "ours": ours, "transformers": ref})

    print(f"\nQwen3-VL, CPU f32, {a.new} new tokens, median of {a.runs} runs "
          f"(torch {torch.__version__}, {torch.get_num_threads()} threads)\n")
    hdr = f"{'model':<22}{'tokens':>7}{'TTFT ours':>11}{'TTFT HF':>10}{'ratio':>7}" \
          f"{'tok/s ours':>12}{'tok/s HF':>10}{'ratio':>7}  same ids"
    print(hdr)
    print("-" * len(hdr))
    for r in results:
        o, t = r["ours"], r["transformers"]
        print(f"{r['model']['name']:<22}{o['prompt_tokens']:>7}{o['ttft_ms']:>9.1f}ms"
              f"{t['ttft_ms']:>8.1f}ms{t['ttft_ms'] / o['ttft_ms']:>6.2f}x"
              f"{o['decode_tokens_per_s']:>12.1f}{t['decode_tokens_per_s']:>10.1f}"
              f"{o['decode_tokens_per_s'] / t['decode_tokens_per_s']:>6.2f}x  "
              f"{'yes' if o['ids'] == t['ids'] else 'NO'}")
    print("\nratio > 1 means vlmfuse is faster (TTFT: HF/ours; tok/s: ours/HF). TTFT includes "
          "preprocessing: ours " + ", ".join(f"{r['ours']['preprocess_ms']:.1f}" for r in results)
          + " ms, HF " + ", ".join(f"{r['transformers']['preprocess_ms']:.1f}" for r in results)
          + " ms.")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
