"""Writes clip_transformers_config.json: the config.json that transformers itself writes for a
CLIPModel shaped like vlmfuse_testkit_models::fixtures::TinyClip (projection 16).

transformers puts CLIPVisionConfig's own default `projection_dim: 512` inside `vision_config`
next to the real top-level `projection_dim`, and CLIPModel sizes `visual_projection` from the
top-level one; the Rust test loads TinyClip weights with this file to check we do the same.

Run with a Python that has transformers ($PYTHON, e.g. a reference venv outside the repository;
default python3): "${PYTHON:-python3}" make_clip_transformers_config.py
"""

import json
import pathlib
import tempfile

from transformers import CLIPConfig, CLIPModel

HERE = pathlib.Path(__file__).parent

config = CLIPConfig(
    projection_dim=16,
    vision_config=dict(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        image_size=32,
        patch_size=8,
    ),
    text_config=dict(
        hidden_size=16,
        intermediate_size=32,
        num_attention_heads=2,
        num_hidden_layers=1,
        vocab_size=64,
        max_position_embeddings=8,
        bos_token_id=0,
        eos_token_id=2,
    ),
)
model = CLIPModel(config)
# The shape transformers gives the projection: [top-level projection_dim, vision hidden_size].
assert tuple(model.visual_projection.weight.shape) == (16, 32), model.visual_projection
with tempfile.TemporaryDirectory() as d:
    config.save_pretrained(d)
    written = json.loads((pathlib.Path(d) / "config.json").read_text())
assert written["projection_dim"] == 16
assert written["vision_config"]["projection_dim"] == 512, written["vision_config"]
(HERE / "clip_transformers_config.json").write_text(json.dumps(written, indent=2) + "\n")
print("wrote", HERE / "clip_transformers_config.json")
