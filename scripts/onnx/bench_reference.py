#!/usr/bin/env python3
"""The reference side of the encoder benchmark (scripts/bench-encoders.sh), and its summary.

measure: embeds the frames that the Rust benchmark dumped with the two Python references, each
the way a Python user would run it: CLIPImageProcessor (PIL) + onnxruntime on the same
onnx/vision_model.onnx, and CLIPImageProcessor + torch on the same safetensors. Same threads
(onnxruntime intra-op N, inter-op 1, sequential, all optimisations; torch.set_num_threads(N)),
same timing rule (two warm-ups, median of the timed runs, cores busy = process CPU time / wall).

    python bench_reference.py measure --model DIR --frames F.rgb --threads 2 --reps 10 --out py.json

summary: merges the Rust and Python JSON files of all rounds (medians over every timed run of an
engine) and prints the table, the ratios against the issue's targets and the cosines.

    python bench_reference.py summary --rust r1.json r2.json --python p1.json p2.json [--out all.json]
"""

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np


def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(reps, f):
    f()
    out = f()
    walls = []
    c0, w0 = cpu(), time.perf_counter()
    for _ in range(reps):
        t = time.perf_counter()
        out = f()
        walls.append((time.perf_counter() - t) * 1e3)
    cores = (cpu() - c0) / (time.perf_counter() - w0)
    return walls, cores, out


def unit_mean(rows):
    m = np.asarray(rows, dtype=np.float64).mean(axis=0)
    return (m / np.linalg.norm(m)).tolist()


def measure(a):
    import onnxruntime as ort
    import torch
    from PIL import Image
    from transformers import CLIPImageProcessor, CLIPVisionModelWithProjection

    meta = json.loads(Path(a.frames).with_suffix(".json").read_text())
    n, w, h = meta["n"], meta["width"], meta["height"]
    raw = np.fromfile(a.frames, dtype=np.uint8).reshape(n, h, w, 3)
    images = [Image.fromarray(f) for f in raw]
    proc = CLIPImageProcessor.from_pretrained(a.model)
    results = {}

    so = ort.SessionOptions()
    so.intra_op_num_threads = a.threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    sess = ort.InferenceSession(str(Path(a.model) / "onnx" / "vision_model.onnx"), so,
                                providers=["CPUExecutionProvider"])

    def ort_embed():
        px = proc(images=images, return_tensors="np")["pixel_values"]
        return unit_mean(sess.run(["image_embeds"], {"pixel_values": px})[0])

    px = proc(images=images, return_tensors="np")["pixel_values"]
    pre_walls, pre_cores, _ = timed(a.reps, lambda: proc(images=images, return_tensors="np"))
    fwd_walls, fwd_cores, _ = timed(a.reps, lambda: sess.run(["image_embeds"], {"pixel_values": px}))
    walls, cores, emb = timed(a.reps, ort_embed)
    results["onnxruntime-python"] = dict(walls_ms=walls, cores_busy=cores, embedding=emb,
                                         preprocess_ms=float(np.median(pre_walls)),
                                         forward_ms=float(np.median(fwd_walls)))
    print(f"onnxruntime-python: median {np.median(walls):.1f} ms, {cores:.2f} cores busy")
    del sess

    torch.set_num_threads(a.threads)
    torch.set_num_interop_threads(1)
    model = CLIPVisionModelWithProjection.from_pretrained(a.model).eval()

    def torch_embed():
        with torch.inference_mode():
            t = proc(images=images, return_tensors="pt")["pixel_values"]
            return unit_mean(model(pixel_values=t).image_embeds.numpy())

    walls, cores, emb = timed(a.reps, torch_embed)
    results["torch"] = dict(walls_ms=walls, cores_busy=cores, embedding=emb)
    print(f"torch: median {np.median(walls):.1f} ms, {cores:.2f} cores busy")
    Path(a.out).write_text(json.dumps({"threads": a.threads, "frames": n, "width": w,
                                       "height": h, "engines": results}))


def cosine(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def summary(a):
    runs = {}
    meta = None
    for f in a.rust + a.python:
        d = json.loads(Path(f).read_text())
        meta = meta or d
        for name, r in d["engines"].items():
            name = {"ort": "vlmfuse ort", "candle": "vlmfuse candle"}.get(name, name)
            e = runs.setdefault(name, {"walls": [], "cores": [], "emb": r["embedding"],
                                       "pre": [], "fwd": []})
            e["walls"] += r["walls_ms"]
            e["cores"].append(r["cores_busy"])
            if "preprocess_ms" in r:
                e["pre"].append(r["preprocess_ms"])
            if "forward_ms" in r:
                e["fwd"].append(r["forward_ms"])
    med = {k: float(np.median(v["walls"])) for k, v in runs.items()}
    print(f"\nembed {meta['frames']} frames of {meta['width']}x{meta['height']} "
          f"(preprocess + forward), {meta['threads']} threads, "
          f"{len(a.rust)} round(s), {sum(len(v['walls']) for v in runs.values())} timed runs")
    print(f"{'engine':22} {'median':>9} {'p10':>8} {'p90':>8} {'cores':>6} {'prep':>7} {'fwd':>7}")
    for k, v in sorted(runs.items(), key=lambda kv: med[kv[0]]):
        w = np.asarray(v["walls"])
        pre = f"{np.median(v['pre']):7.1f}" if v["pre"] else f"{'':7}"
        fwd = f"{np.median(v['fwd']):7.1f}" if v["fwd"] else f"{'':7}"
        print(f"{k:22} {med[k]:7.1f}ms {np.percentile(w, 10):6.1f}ms {np.percentile(w, 90):6.1f}ms "
              f"{np.mean(v['cores']):6.2f} {pre} {fwd}")
    out = {"medians_ms": med, "meta": {k: meta[k] for k in ("frames", "width", "height", "threads")}}
    if "vlmfuse ort" in med:
        ours = med["vlmfuse ort"]
        checks = []
        if "onnxruntime-python" in med:
            r = ours / med["onnxruntime-python"]
            checks.append(("ort / onnxruntime-python", r, r <= 1.05, "<= 1.05"))
        if "vlmfuse candle" in med:
            r = med["vlmfuse candle"] / ours
            checks.append(("candle / ort (speed-up)", r, r >= 1.7, ">= 1.7"))
        if "torch" in med:
            checks.append(("torch / ort", med["torch"] / ours, True, "(information)"))
        print()
        for name, r, ok, target in checks:
            print(f"{name:28} {r:6.3f}  target {target:14} {'met' if ok else 'MISSED'}")
        out["ratios"] = {n: r for n, r, _, _ in checks}
        print()
        cos = {}
        for other in ("vlmfuse candle", "torch", "onnxruntime-python"):
            if other in runs:
                c = cosine(runs["vlmfuse ort"]["emb"], runs[other]["emb"])
                cos[other] = c
                print(f"cosine ort vs {other:20} {c:.8f}  target >= 0.99999 "
                      f"{'met' if c >= 0.99999 else 'MISSED'}")
        out["cosines"] = cos
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("measure")
    m.add_argument("--model", required=True)
    m.add_argument("--frames", required=True)
    m.add_argument("--threads", type=int, default=2)
    m.add_argument("--reps", type=int, default=10)
    m.add_argument("--out", required=True)
    s = sub.add_parser("summary")
    s.add_argument("--rust", nargs="+", required=True)
    s.add_argument("--python", nargs="*", default=[])
    s.add_argument("--out")
    a = ap.parse_args()
    measure(a) if a.cmd == "measure" else summary(a)
