#!/usr/bin/env python3
"""Reference outputs of transformers' VideoLlavaForConditionalGeneration on the project's tiny
VideoLLaVA fixture, for the Rust parity tests (crates/vlmfuse-models/tests/video_llava_parity.rs).

Not run in CI (it needs torch). Run it from the repository root with a Python that has the
packages below ($PYTHON, e.g. a reference venv outside the repository; default python3):

    cargo run -p vlmfuse-models --example video_llava_fixture -- /tmp/vl
    "${PYTHON:-python3}" scripts/parity/video_llava.py /tmp/vl

Needs torch 2.15.0, transformers 5.23.0, torchvision 0.29.2 and peft (for the LoRA case). Reads
DIR/model (checkpoint), DIR/adapter (PEFT adapter), DIR/frames (raw RGB clips) that the Rust
fixture writer made, and writes tests/data/parity/video_llava/{preprocess,cases}.json. Float
arrays are base64 of little-endian f32, so the files stay small.

`--bench DIR` instead times time-to-first-token and decode tokens/s of transformers on DIR (the
`--mid` fixture) and prints one JSON line for examples/video_llava_bench.rs.
"""

import argparse
import base64
import copy
import json
import os
import sys
import time

import numpy as np
import torch
import transformers
from transformers import AutoProcessor, VideoLlavaForConditionalGeneration

OUT = os.path.join("tests", "data", "parity", "video_llava")
PROMPTS = {
    "describe": "Describe the dashcam clip.",
    "manoeuvre": "What should the car do? Scene: Manoeuvres: Rationale:",
}
NEW_TOKENS = 16


def b64f32(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype="<f4")).tobytes()).decode()


def b64u8(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype=np.uint8)).tobytes()).decode()


def load_clips(frames_dir):
    meta = json.load(open(os.path.join(frames_dir, "frames.json")))
    clips = {}
    for c in meta["clips"]:
        raw = np.fromfile(os.path.join(frames_dir, c["file"]), dtype=np.uint8)
        clips[c["name"]] = raw.reshape(c["frames"], c["height"], c["width"], 3)
    return clips


def sample(clip, n=8):
    """The Video-LLaVA model card's frame choice: np.arange(0, total, total / n).astype(int)."""
    total = clip.shape[0]
    if total <= n:
        return clip, list(range(total))
    idx = np.arange(0, total, total / n).astype(int)
    return clip[idx], idx.tolist()


def to_u8(pv, mean, std):
    """Recovers the uint8 image both processors normalise (CHW); asserts it is integral."""
    x = pv * (np.asarray(std)[:, None, None] * 255.0) + np.asarray(mean)[:, None, None] * 255.0
    r = np.rint(x)
    err = np.abs(x - r).max()
    assert err < 2e-3, f"pixel values are not an affine image of uint8 values (off by {err})"
    return r.clip(0, 255).astype(np.uint8)


def greedy(model, inputs, steps):
    """Greedy decoding with the KV cache, feeding positions and the padding mask exactly as
    `generate` does, but without stopping at EOS (so every case yields `steps` ids)."""
    mask = inputs["attention_mask"]
    pos = (mask.long().cumsum(-1) - 1).masked_fill(mask == 0, 0)
    out = model(**inputs, position_ids=pos, use_cache=True)
    first = out.logits[:, -1].float()
    ids = []
    logits = first
    past = out.past_key_values
    for _ in range(steps):
        nxt = logits.argmax(-1)
        ids.append(nxt)
        mask = torch.cat([mask, torch.ones_like(mask[:, :1])], dim=1)
        pos = pos[:, -1:] + 1
        out = model(input_ids=nxt[:, None], attention_mask=mask, position_ids=pos,
                    past_key_values=past, use_cache=True)
        past = out.past_key_values
        logits = out.logits[:, -1].float()
    return first, torch.stack(ids, dim=1)


def check_against_generate(model, inputs, ids, eos):
    """`generate` (with the checkpoint's EOS) must agree with the manual loop up to its stop."""
    gen = model.generate(**inputs, do_sample=False, max_new_tokens=ids.shape[1])
    gen = gen[:, inputs["input_ids"].shape[1]:]
    for r in range(ids.shape[0]):
        g = gen[r].tolist()
        m = ids[r].tolist()
        stop = next((i for i, t in enumerate(m) if t == eos), len(m) - 1) + 1
        assert g[:stop] == m[:stop], f"generate {g} vs manual greedy {m}"


def reference(root):
    torch.manual_seed(0)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    mdir = os.path.join(root, "model")
    proc = AutoProcessor.from_pretrained(mdir)
    model = VideoLlavaForConditionalGeneration.from_pretrained(mdir, dtype=torch.float32).eval()
    clips = load_clips(os.path.join(root, "frames"))
    vp, ip = proc.video_processor, proc.image_processor
    eos = model.generation_config.eos_token_id
    eos = eos[0] if isinstance(eos, list) else eos

    pre = {"transformers": transformers.__version__, "torch": torch.__version__, "clips": {}}
    for name, clip in clips.items():
        frames, idx = sample(clip)
        pv = vp(videos=frames, return_tensors="pt")["pixel_values_videos"][0].numpy()
        u8 = np.stack([to_u8(f, vp.image_mean, vp.image_std) for f in pv])
        img = ip(images=clip[0], return_tensors="pt", return_legacy_image_output=False)
        ipv = img["pixel_values"][0].numpy()
        iu8 = to_u8(ipv, ip.image_mean, ip.image_std)
        # The first and last sampled frames as uint8 (every frame of a clip shares the resampling
        # coefficients), and the normalised floats of one clip, keep the file small.
        entry = {
            "indices": idx,
            "shape": list(pv.shape),
            "video_u8_first_last": b64u8(u8[[0, -1]]),
            "image_shape": list(ipv.shape),
            "image_u8": b64u8(iu8),
        }
        if name == "landscape":
            entry["video_frame0_f32"] = b64f32(pv[0])
            entry["image_f32"] = b64f32(ipv)
        pre["clips"][name] = entry

    def video_case(name, items, model=model, adapter=False):
        texts = [f"USER: <video>\n{PROMPTS[p]} ASSISTANT:" for (_, p) in items]
        vids = [sample(clips[c])[0] for (c, _) in items]
        inp = proc(text=texts, videos=vids, padding=True, return_tensors="pt")
        with torch.no_grad():
            first, ids = greedy(model, dict(inp), NEW_TOKENS)
            check_against_generate(model, dict(inp), ids, eos)
        return {
            "name": name, "adapter": adapter,
            "clips": [c for (c, _) in items], "prompts": [p for (_, p) in items],
            "input_ids": inp["input_ids"].tolist(),
            "attention_mask": inp["attention_mask"].tolist(),
            "vocab": first.shape[1],
            "logits": b64f32(first.numpy()),
            "greedy": ids.tolist(),
        }

    cases = [
        video_case("landscape_describe", [("landscape", "describe")]),
        video_case("portrait12_manoeuvre", [("portrait12", "manoeuvre")]),
        video_case("upscale_describe", [("upscale", "describe")]),
        video_case("short5_manoeuvre", [("short5", "manoeuvre")]),
        video_case("batch_padded", [("landscape", "describe"), ("portrait12", "manoeuvre")]),
    ]
    # Text only, and one image through the image tower (CLS dropped: strategy "default").
    for name, text, kwargs in [
        ("text_only", "USER: What should the car do? ASSISTANT:", {}),
        ("image_describe", "USER: <image>\nDescribe this image. ASSISTANT:",
         {"images": clips["landscape"][0]}),
    ]:
        inp = proc(text=[text], return_tensors="pt", **kwargs)
        with torch.no_grad():
            first, ids = greedy(model, dict(inp), NEW_TOKENS)
        cases.append({"name": name, "adapter": False, "clips": [], "prompts": [text],
                      "image": "landscape" if kwargs else None,
                      "input_ids": inp["input_ids"].tolist(),
                      "attention_mask": inp["attention_mask"].tolist(),
                      "vocab": first.shape[1], "logits": b64f32(first.numpy()),
                      "greedy": ids.tolist()})

    # The same adapter merged by PEFT, after checking that PEFT used every tensor of the file.
    from peft import PeftModel
    from peft.utils import get_peft_model_state_dict
    from safetensors.torch import load_file

    adir = os.path.join(root, "adapter")
    lora = PeftModel.from_pretrained(copy.deepcopy(model), adir).eval()
    want = set(load_file(os.path.join(adir, "adapter_model.safetensors")).keys())
    got = set(get_peft_model_state_dict(lora).keys())
    assert want == got, f"PEFT ignored {sorted(want - got)[:4]}, invented {sorted(got - want)[:4]}"
    merged = lora.merge_and_unload().eval()
    cases.append(video_case("lora_landscape_describe", [("landscape", "describe")], merged, True))

    os.makedirs(OUT, exist_ok=True)
    for fname, obj in [("preprocess.json", pre), ("cases.json", {"cases": cases})]:
        with open(os.path.join(OUT, fname), "w") as f:
            json.dump(obj, f, indent=1)
            f.write("\n")
    print(f"wrote {OUT}: {len(pre['clips'])} clips, {len(cases)} cases")


def bench(root, new_tokens, repeats, threads):
    """Same inputs as examples/video_llava_bench.rs: the landscape clip, 'describe' prompt."""
    torch.set_num_threads(threads or max(1, os.cpu_count() or 1))
    mdir = os.path.join(root, "model")
    proc = AutoProcessor.from_pretrained(mdir)
    model = VideoLlavaForConditionalGeneration.from_pretrained(mdir, dtype=torch.float32).eval()
    clip = sample(load_clips(os.path.join(root, "frames"))["landscape"])[0]
    text = f"USER: <video>\n{PROMPTS['describe']} ASSISTANT:"
    # No EOS: every run decodes exactly `new_tokens`.
    gen = dict(do_sample=False, eos_token_id=None, pad_token_id=0)
    model.generation_config.eos_token_id = None

    def run(n):
        t0 = time.perf_counter()
        inp = proc(text=[text], videos=[clip], return_tensors="pt")
        with torch.no_grad():
            out = model.generate(**inp, max_new_tokens=n, min_new_tokens=n, **gen)
        dt = time.perf_counter() - t0
        assert out.shape[1] - inp["input_ids"].shape[1] == n
        return dt, inp["input_ids"].shape[1]

    run(2)  # warm-up
    ttft = min(run(1)[0] for _ in range(repeats))
    full, prompt = min(run(new_tokens) for _ in range(repeats))
    tps = (new_tokens - 1) / max(full - ttft, 1e-9)
    print(json.dumps({"impl": "transformers", "version": transformers.__version__, "ttft_s": ttft, "decode_tok_s": tps,
                      "prompt_tokens": prompt, "new_tokens": new_tokens,
                      "threads": torch.get_num_threads()}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="directory the Rust fixture writer filled")
    ap.add_argument("--bench", action="store_true", help="time transformers instead")
    ap.add_argument("--new-tokens", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (default: all cores)")
    a = ap.parse_args()
    if transformers.__version__ != "5.23.0":
        print(f"warning: reference is transformers 5.23.0, this is {transformers.__version__}",
              file=sys.stderr)
    if a.bench:
        bench(a.dir, a.new_tokens, a.repeats, a.threads)
    else:
        reference(a.dir)


if __name__ == "__main__":
    main()
