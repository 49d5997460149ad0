#!/usr/bin/env python3
"""What transformers 5.23's `save_pretrained` writes for the project's tiny Qwen3-VL and
VideoLLaVA fixtures, so that the Rust tests can load checkpoints in that layout without torch.

transformers 5.23 writes a checkpoint differently from the releases on the hub: the video
processor settings are nested inside `processor_config.json` (no
`video_preprocessor_config.json`), and VideoLLaVA's towers are saved as `video_tower.*` without
`vision_model`. Weights are never committed: this script records the non-weight files that
`save_pretrained` writes and, per tensor, the name it was saved under (matched to the fixture's
names by value), and the Rust tests rebuild the saved checkpoint from the fixture with them.

    cargo run -q -p vlmfuse-models --example write_fixture -- qwen3_vl /tmp/q3 --seed 7
    cargo run -q -p vlmfuse-models --example video_llava_fixture -- /tmp/vl
    "${PYTHON:-python3}" scripts/parity/saved_layouts.py --qwen /tmp/q3 --video-llava /tmp/vl/model

Writes tests/data/parity/saved_5_23/{qwen3_vl,qwen3_vl_patch16,video_llava}/:

  files.json      the text files save_pretrained wrote (name -> content), weights excluded
  names.json      fixture tensor name -> saved tensor name
  reference.json  (qwen3_vl_patch16 only) a processor with the released checkpoints' settings
                  (patch 16, their pixel budget, mean/std), saved and reloaded by transformers,
                  run on a synthetic clip: grid and grey levels, for the row "loads silently
                  with the wrong pixel budget"

Needs torch 2.15.0, transformers 5.23.0, torchvision 0.29.2, safetensors, numpy.
"""

import argparse
import base64
import json
import os
import sys
import tempfile
import warnings

import numpy as np
import torch
import transformers
from safetensors.torch import load_file

warnings.filterwarnings("ignore")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from qwen3_vl import frames  # noqa: E402  (the synthetic clip the Rust tests rebuild)

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
OUT = os.path.join(ROOT, "tests", "data", "parity", "saved_5_23")
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt")


def tensors(dir_):
    out = {}
    for f in sorted(os.listdir(dir_)):
        if f.endswith(".safetensors"):
            out.update(load_file(os.path.join(dir_, f)))
    return out


def name_map(fixture_dir, saved_dir):
    """Fixture name -> saved name, by equal values (shapes and every element)."""
    a, b = tensors(fixture_dir), tensors(saved_dir)
    assert len(a) == len(b), f"{len(a)} fixture tensors, {len(b)} saved"
    out, left = {}, dict(b)
    for k, t in a.items():
        if k in left and left[k].shape == t.shape and torch.equal(left[k].float(), t.float()):
            out[k] = k
            del left[k]
            continue
        hit = [n for n, u in left.items() if u.shape == t.shape and torch.equal(u.float(), t.float())]
        assert len(hit) == 1, f"{k}: {len(hit)} saved tensors with its values"
        out[k] = hit[0]
        del left[hit[0]]
    return out


def saved_fresh(cls, fixture, out_dir):
    """Saves the fixture as a model built by transformers 5.23 itself (from its config, then
    given the fixture's weights) writes it: a model loaded from a checkpoint keeps that
    checkpoint's tensor names on save, one built in memory (fine-tuned, converted, trained
    from scratch) gets 5.23's own."""
    from transformers import AutoConfig
    loaded = cls.from_pretrained(fixture, dtype=torch.float32)
    fresh = cls(AutoConfig.from_pretrained(fixture)).to(torch.float32)
    missing, unexpected = fresh.load_state_dict(loaded.state_dict(), strict=False)
    assert not unexpected, unexpected
    assert all("lm_head" in m for m in missing), missing
    fresh.save_pretrained(out_dir)


def text_files(dir_):
    out = {}
    for f in sorted(os.listdir(dir_)):
        p = os.path.join(dir_, f)
        if os.path.isfile(p) and not f.endswith(WEIGHT_SUFFIXES):
            with open(p, encoding="utf-8") as fh:
                out[f] = fh.read()
    return out


def write(sub, name, obj):
    d = os.path.join(OUT, sub)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=1, sort_keys=True)
        f.write("\n")


def qwen(fixture):
    from transformers import (AutoProcessor, Qwen3VLForConditionalGeneration,
                              Qwen3VLVideoProcessor)
    proc = AutoProcessor.from_pretrained(fixture)
    with tempfile.TemporaryDirectory() as tmp:
        saved_fresh(Qwen3VLForConditionalGeneration, fixture, tmp)
        proc.save_pretrained(tmp)
        files = text_files(tmp)
        assert "video_preprocessor_config.json" not in files, sorted(files)
        write("qwen3_vl", "files.json", files)
        write("qwen3_vl", "names.json", name_map(fixture, tmp))

    # The released checkpoints' video processor (Qwen3-VL-2B/4B/8B-Instruct): patch 16, their
    # pixel budget, mean/std 0.5. Saved by transformers 5.23 and read back by it.
    vp = Qwen3VLVideoProcessor(patch_size=16, temporal_patch_size=2, merge_size=2,
                               size={"shortest_edge": 4096, "longest_edge": 25165824},
                               image_mean=[0.5, 0.5, 0.5], image_std=[0.5, 0.5, 0.5],
                               fps=2, min_frames=4, max_frames=768)
    tok_dir = fixture
    proc16 = AutoProcessor.from_pretrained(tok_dir)
    proc16.video_processor = vp
    with tempfile.TemporaryDirectory() as tmp:
        proc16.save_pretrained(tmp)
        files = text_files(tmp)
        assert "video_preprocessor_config.json" not in files, sorted(files)
        back = AutoProcessor.from_pretrained(tmp).video_processor
        clip = frames(2, 100, 60)
        from transformers.video_utils import VideoMetadata
        meta = VideoMetadata(total_num_frames=2, fps=2.0, frames_indices=[0, 1])
        out = back(videos=[clip], video_metadata=[meta], do_sample_frames=False,
                   return_tensors="pt")
        pv = out["pixel_values_videos"].numpy().astype(np.float64)
        g = np.rint(pv * 127.5 + 127.5)
        assert np.abs(g - (pv * 127.5 + 127.5)).max() < 1e-3
        ref = {
            "transformers": transformers.__version__,
            "frames": {"n": 2, "width": 100, "height": 60, "k0": 0},
            "grid_thw": out["video_grid_thw"][0].tolist(),
            "shape": list(pv.shape),
            "grey_u8": base64.b64encode(np.clip(g, 0, 255).astype(np.uint8).tobytes()).decode(),
            "settings": {"patch_size": back.patch_size, "size": dict(back.size),
                         "image_mean": list(back.image_mean), "image_std": list(back.image_std),
                         "fps": back.fps, "min_frames": back.min_frames,
                         "max_frames": back.max_frames},
        }
        write("qwen3_vl_patch16", "files.json", files)
        write("qwen3_vl_patch16", "reference.json", ref)


def video_llava(fixture):
    from transformers import AutoProcessor, VideoLlavaForConditionalGeneration
    proc = AutoProcessor.from_pretrained(fixture)
    with tempfile.TemporaryDirectory() as tmp:
        saved_fresh(VideoLlavaForConditionalGeneration, fixture, tmp)
        proc.save_pretrained(tmp)
        write("video_llava", "files.json", text_files(tmp))
        names = name_map(fixture, tmp)
        write("video_llava", "names.json", names)
        print("video_llava: e.g.", list(names.items())[:3], file=sys.stderr)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--qwen", help="the Qwen3-VL fixture directory (write_fixture qwen3_vl)")
    ap.add_argument("--video-llava", help="the VideoLLaVA fixture's model directory")
    a = ap.parse_args()
    if transformers.__version__ != "5.23.0":
        print(f"warning: reference is transformers 5.23.0, this is {transformers.__version__}",
              file=sys.stderr)
    if a.qwen:
        qwen(a.qwen)
    if a.video_llava:
        video_llava(a.video_llava)


if __name__ == "__main__":
    main()
