#!/usr/bin/env python3
"""Builds the ONNX test fixtures under tests/data/onnx/ and their expected outputs from torch.

Run with a Python that has torch + transformers ($PYTHON, e.g. a reference venv outside the repo;
default python3; never in CI, which reads the committed files):

    "${PYTHON:-python3}" scripts/onnx/make_fixtures.py [--minilm DIR]

Writes, with random weights from fixed seeds (a few hundred KB in all):

* tiny-clip/           CLIPVisionModelWithProjection: config.json, model.safetensors,
                       preprocessor_config.json, onnx/vision_model.onnx (the transformers.js
                       layout), pixel_values.f32 (what CLIPImageProcessor made of the frames) and
                       expected.json (frames, per-frame image_embeds, clip embedding).
* tiny-clip-full/      a whole CLIPModel (text tower too) as one model.onnx (the Optimum layout),
                       with config.json, preprocessor_config.json and its own expected.json
                       (its image_embeds are unit-normalised per frame, as CLIPModel returns them).
* tiny-bert/           BertModel: config.json, model.safetensors, tokenizer.json (WordPiece),
                       model.onnx (torch export), graph.onnx (scripts/onnx/bert_graph.py over the
                       same safetensors) and expected.json (token ids, mean-pooled unit
                       embeddings).
* all-minilm-l6-v2/expected.json   with --minilm DIR (the fetched asset): reference embeddings of
                       the real model from transformers, for the tests that run when the asset is
                       present. model.onnx beside it is written by bert_graph.py, not here.

Frames are generated, not stored: frame(seed, w, h)[i] = ((i * 2654435761 + seed * 97) mod 2^32)
>> 7, truncated to a byte, the same formula the Rust tests use.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "tests" / "data" / "onnx"
OPSET = 17

FRAMES = [(1, 64, 40), (2, 64, 40), (3, 50, 50), (4, 1280, 720)]


def frame(seed, w, h):
    i = np.arange(w * h * 3, dtype=np.uint64)
    v = ((i * np.uint64(2654435761) + np.uint64(seed * 97)) & np.uint64(0xFFFFFFFF)) >> np.uint64(7)
    return (v & np.uint64(0xFF)).astype(np.uint8).reshape(h, w, 3)


def rounded(a, digits=8):
    return [float(f"{x:.{digits}g}") for x in np.asarray(a, dtype=np.float64).ravel()]


def reinit(model, seed):
    """transformers' init (std 0.02) makes tiny models nearly input-independent; wider random
    weights make the fixtures discriminative."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "norm" in name.lower() and name.endswith("weight"):
                p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                fan_in = p.shape[-1] if p.dim() > 1 else 16
                p.copy_(torch.randn(p.shape, generator=g) / fan_in ** 0.5)


def export(module, args, path, input_names, output_names, dynamic_axes):
    """The exporter restores the wrapper's training flag afterwards, recursively: a wrapper left
    in training mode would switch dropout on in the wrapped model for the expected outputs."""
    module.eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(module, args, str(path), input_names=input_names,
                      output_names=output_names, dynamic_axes=dynamic_axes,
                      opset_version=OPSET, dynamo=False, do_constant_folding=True)


def clip_fixtures():
    from transformers import (CLIPConfig, CLIPImageProcessor, CLIPModel, CLIPTextConfig,
                              CLIPVisionConfig, CLIPVisionModelWithProjection)

    vcfg = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                image_size=32, patch_size=8, projection_dim=16, hidden_act="quick_gelu")
    proc = CLIPImageProcessor(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32})
    frames = [frame(*f) for f in FRAMES]
    pixels = proc(images=[Image.fromarray(f) for f in frames], return_tensors="pt")["pixel_values"]

    # Vision tower + projection, the transformers.js layout (onnx/vision_model.onnx).
    d = OUT / "tiny-clip"
    torch.manual_seed(0)
    model = CLIPVisionModelWithProjection(CLIPVisionConfig(**vcfg)).eval()
    reinit(model, 1)
    model.save_pretrained(d, safe_serialization=True)
    proc.save_pretrained(d)

    class Vision(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, pixel_values):
            o = self.m(pixel_values=pixel_values)
            return o.image_embeds, o.last_hidden_state

    export(Vision(model), (pixels[:2],), d / "onnx" / "vision_model.onnx", ["pixel_values"],
           ["image_embeds", "last_hidden_state"],
           {"pixel_values": {0: "batch"}, "image_embeds": {0: "batch"},
            "last_hidden_state": {0: "batch"}})
    with torch.no_grad():
        emb = model(pixel_values=pixels).image_embeds.numpy()
    pixels.numpy().astype("<f4").tofile(d / "pixel_values.f32")
    write_clip_expected(d, frames, pixels, emb)

    # A whole CLIPModel in one model.onnx (the Optimum layout): text inputs are required even
    # though the embedder only wants image_embeds.
    d = OUT / "tiny-clip-full"
    torch.manual_seed(0)
    cfg = CLIPConfig(text_config=CLIPTextConfig(vocab_size=64, hidden_size=16,
                                                intermediate_size=32, num_hidden_layers=1,
                                                num_attention_heads=2, max_position_embeddings=8,
                                                projection_dim=16).to_dict(),
                     vision_config=CLIPVisionConfig(**vcfg).to_dict(), projection_dim=16)
    full = CLIPModel(cfg).eval()
    reinit(full, 2)
    full.config.save_pretrained(d)  # the weights live only in model.onnx here
    proc.save_pretrained(d)

    class Full(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, input_ids, pixel_values, attention_mask):
            o = self.m(input_ids=input_ids, pixel_values=pixel_values,
                       attention_mask=attention_mask)
            return o.logits_per_image, o.logits_per_text, o.text_embeds, o.image_embeds

    ids = torch.tensor([[3, 5, 7]], dtype=torch.int64)
    export(Full(full), (ids, pixels[:2], torch.ones_like(ids)), d / "model.onnx",
           ["input_ids", "pixel_values", "attention_mask"],
           ["logits_per_image", "logits_per_text", "text_embeds", "image_embeds"],
           {"input_ids": {0: "text_batch", 1: "sequence"},
            "attention_mask": {0: "text_batch", 1: "sequence"},
            "pixel_values": {0: "image_batch"}, "image_embeds": {0: "image_batch"},
            "text_embeds": {0: "text_batch"},
            "logits_per_image": {0: "image_batch", 1: "text_batch"},
            "logits_per_text": {0: "text_batch", 1: "image_batch"}})
    # CLIPModel's own image_embeds are unit-normalised per image (the vision-only export's are
    # not), and that is what this layout gives the embedder.
    with torch.no_grad():
        emb = full(input_ids=ids, pixel_values=pixels, attention_mask=torch.ones_like(ids))
        emb = emb.image_embeds.numpy()
    write_clip_expected(d, frames, pixels, emb)


def write_clip_expected(d, frames, pixels, emb):
    mean = emb.mean(axis=0)
    (d / "expected.json").write_text(json.dumps({
        "frames": [{"seed": s, "width": w, "height": h} for s, w, h in FRAMES],
        "pixel_values_shape": list(pixels.shape),
        "image_embeds": [rounded(r) for r in emb],
        "clip_embedding": rounded(mean / np.linalg.norm(mean)),
    }, indent=1) + "\n")
    print(f"wrote {d}")


BERT_TEXTS = [
    "turn left at the junction",
    "slow down because of the rain",
    "there is no traffic light",
    "stop",
    "the zebra crossing is unmarked",  # "unmarked" is out of vocabulary: [UNK]
]


def bert_fixtures():
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import BertConfig, BertModel

    d = OUT / "tiny-bert"
    d.mkdir(parents=True, exist_ok=True)
    words = sorted({w for t in BERT_TEXTS[:-1] for w in t.split()} | {"zebra", "crossing", "is"})
    vocab = {t: i for i, t in enumerate(["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"] + words)}
    tok = Tokenizer(models.WordPiece(vocab=vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.BertNormalizer(lowercase=True)
    tok.pre_tokenizer = pre_tokenizers.BertPreTokenizer()
    tok.post_processor = processors.TemplateProcessing(
        single="[CLS] $A [SEP]", pair="[CLS] $A [SEP] $B:1 [SEP]:1",
        special_tokens=[("[CLS]", vocab["[CLS]"]), ("[SEP]", vocab["[SEP]"])])
    tok.save(str(d / "tokenizer.json"))

    torch.manual_seed(0)
    cfg = BertConfig(vocab_size=len(vocab), hidden_size=32, num_hidden_layers=2,
                     num_attention_heads=4, intermediate_size=64, max_position_embeddings=64,
                     type_vocab_size=2, hidden_act="gelu")
    model = BertModel(cfg, add_pooling_layer=False).eval()
    reinit(model, 3)
    model.save_pretrained(d, safe_serialization=True)

    tok.enable_padding(pad_id=0, pad_token="[PAD]")
    enc = tok.encode_batch(BERT_TEXTS)
    ids = torch.tensor([e.ids for e in enc], dtype=torch.int64)
    mask = torch.tensor([e.attention_mask for e in enc], dtype=torch.int64)
    tt = torch.zeros_like(ids)

    class Bert(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, input_ids, attention_mask, token_type_ids):
            return self.m(input_ids=input_ids, attention_mask=attention_mask,
                          token_type_ids=token_type_ids).last_hidden_state

    axes = {0: "batch", 1: "sequence"}
    export(Bert(model), (ids, mask, tt), d / "model.onnx",
           ["input_ids", "attention_mask", "token_type_ids"], ["last_hidden_state"],
           {"input_ids": axes, "attention_mask": axes, "token_type_ids": axes,
            "last_hidden_state": axes})
    subprocess.run([sys.executable, str(REPO / "scripts/onnx/bert_graph.py"), str(d),
                    str(d / "graph.onnx")], check=True)
    with torch.no_grad():
        hidden = model(input_ids=ids, attention_mask=mask, token_type_ids=tt).last_hidden_state
    (d / "expected.json").write_text(json.dumps({
        "texts": BERT_TEXTS,
        "ids": [[i for i, m in zip(e.ids, e.attention_mask) if m] for e in enc],
        "embeddings": [rounded(r) for r in pool(hidden, mask)],
    }, indent=1) + "\n")
    print(f"wrote {d}")


def pool(hidden, mask):
    """sentence-transformers' mean pooling over attended tokens, then L2 normalisation."""
    m = mask.unsqueeze(-1).to(hidden.dtype)
    mean = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)
    return torch.nn.functional.normalize(mean, dim=-1).numpy()


MINILM_TEXTS = [
    "turn left at the junction",
    "there is no traffic light at this intersection",
    "slow down because of the rain on the wet road",
    "keep a safe distance from the truck ahead",
    "stop",
    "pedestrians are waiting to cross at the zebra crossing while the signal is still red",
]


def minilm_expected(model_dir: Path):
    from tokenizers import Tokenizer
    from transformers import BertModel

    tok = Tokenizer.from_file(str(model_dir / "tokenizer.json"))
    tok.enable_padding(pad_id=0, pad_token="[PAD]")
    tok.enable_truncation(128)
    enc = tok.encode_batch(MINILM_TEXTS)
    ids = torch.tensor([e.ids for e in enc], dtype=torch.int64)
    mask = torch.tensor([e.attention_mask for e in enc], dtype=torch.int64)
    model = BertModel.from_pretrained(str(model_dir), add_pooling_layer=False).eval()
    with torch.no_grad():
        hidden = model(input_ids=ids, attention_mask=mask).last_hidden_state
    d = OUT / "all-minilm-l6-v2"
    d.mkdir(parents=True, exist_ok=True)
    (d / "expected.json").write_text(json.dumps({
        "texts": MINILM_TEXTS,
        "embeddings": [rounded(r) for r in pool(hidden, mask)],
    }, indent=1) + "\n")
    print(f"wrote {d / 'expected.json'}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--minilm", type=Path, help="all-MiniLM-L6-v2 dir (the fetched asset)")
    a = ap.parse_args()
    clip_fixtures()
    bert_fixtures()
    if a.minilm:
        minilm_expected(a.minilm)
