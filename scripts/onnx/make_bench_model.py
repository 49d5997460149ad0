#!/usr/bin/env python3
"""Writes a full-size CLIP ViT-B/32 vision tower + projection with random weights (transformers'
own initialisation, fixed seed) for the encoder benchmark, in the layout users have:

    OUT/config.json  OUT/model.safetensors  OUT/preprocessor_config.json  OUT/onnx/vision_model.onnx

OUT defaults to $VLMFUSE_ASSETS/bench/clip-vit-b32-random (outside the repository: about
700 MB, never committed). Needs torch + transformers; $PYTHON is such a Python (a reference venv
outside the repository; default python3):

    "${PYTHON:-python3}" scripts/onnx/make_bench_model.py [OUT]

Idempotent: an OUT that already holds all four files is left alone.
"""

import os
import sys
from pathlib import Path

import torch
from transformers import CLIPImageProcessor, CLIPVisionConfig, CLIPVisionModelWithProjection


def main():
    root = Path(os.environ.get("VLMFUSE_ASSETS") or Path.home() / ".cache" / "vlmfuse-assets")
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else root / "bench" / "clip-vit-b32-random"
    files = ["config.json", "model.safetensors", "preprocessor_config.json",
             "onnx/vision_model.onnx"]
    if all((out / f).is_file() for f in files):
        print(f"{out}: already there")
        return
    torch.manual_seed(0)
    # transformers' defaults are ViT-B/32: 768 wide, 12 layers, patch 32, 224 px, projection 512.
    model = CLIPVisionModelWithProjection(CLIPVisionConfig(projection_dim=512)).eval()
    model.save_pretrained(out, safe_serialization=True)
    CLIPImageProcessor().save_pretrained(out)

    class Vision(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, pixel_values):
            o = self.m(pixel_values=pixel_values)
            return o.image_embeds, o.last_hidden_state

    (out / "onnx").mkdir(parents=True, exist_ok=True)
    torch.onnx.export(Vision(model).eval(), (torch.zeros(2, 3, 224, 224),),
                      str(out / "onnx" / "vision_model.onnx"), input_names=["pixel_values"],
                      output_names=["image_embeds", "last_hidden_state"],
                      dynamic_axes={"pixel_values": {0: "batch"}, "image_embeds": {0: "batch"},
                                    "last_hidden_state": {0: "batch"}},
                      opset_version=17, dynamo=False, do_constant_folding=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
