#!/usr/bin/env python3
"""Reference outputs of the VideoLLaMA2 repository's own code (DAMO-NLP-SG/VideoLLaMA2) on the
project's tiny VideoLLaMA2 fixtures, for the Rust parity tests
(crates/vlmfuse-models/tests/videollama2_parity.rs).

Not run in CI. It needs the repository's pinned stack in a venv of its own, outside this
repository (the versions its requirements.txt pins, where they exist for this Python):

    python3 -m venv /work/ref-vl2
    /work/ref-vl2/bin/pip install torch==2.2.0 torchvision==0.17.0 transformers==4.40.0 \
        tokenizers==0.19.1 timm==1.0.3 einops==0.6.1 einops-exts==0.0.4 "numpy<2" pillow \
        safetensors sentencepiece peft==0.10.0 accelerate==0.26.1
    git clone https://github.com/DAMO-NLP-SG/VideoLLaMA2 /work/ref-src/VideoLLaMA2   # c0bb03a
    cargo run -p vlmfuse-models --example videollama2_fixture -- /tmp/vl2
    /work/ref-vl2/bin/python scripts/parity/videollama2.py /tmp/vl2 --repo /work/ref-src/VideoLLaMA2

Writes tests/data/parity/videollama2/{preprocess,cases}.json (floats as base64 of f32).

What is patched to run the repository's code on CPU, here and not in the project:
- `decord`, `cv2`, `imageio` (video readers `mm_utils` imports at the top) are stubbed: frames
  come from the fixture's raw RGB, and `frame_sample` picks them as `process_video` would.
- `CLIPVisionTower` asks for flash-attention 2, which needs CUDA: its config class is swapped
  for one that keeps the eager attention.
- `load_pretrained_model` and `mm_infer` hard-code float16 and `.cuda()`: their steps are run
  here in float32 on CPU (the same classes, prompt, tokenization and LoRA merge).
- The fixture ships `tokenizer.json` only, so the tokenizer loads as the fast one
  (`use_fast=True`) where the repository asks for the slow sentencepiece one.
"""

import argparse
import base64
import importlib.machinery
import json
import os
import sys
import time
import types

import numpy as np

NEW_TOKENS = 16
PROMPTS = {
    "describe": "Describe the dashcam clip.",
    "manoeuvre": "What should the car do? Scene: Manoeuvres: Rationale:",
}
OUT = os.path.join("tests", "data", "parity", "videollama2")


def b64f32(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype="<f4")).tobytes()).decode()


def b64u8(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype=np.uint8)).tobytes()).decode()


def stub_modules():
    for name in ["decord", "cv2", "imageio"]:
        m = types.ModuleType(name)
        m.__spec__ = importlib.machinery.ModuleSpec(name, None)
        m.VideoReader = None
        m.cpu = None
        m.COLOR_RGBA2RGB = None
        sys.modules[name] = m


def load_clips(frames_dir):
    meta = json.load(open(os.path.join(frames_dir, "frames.json")))
    clips = {}
    for c in meta["clips"]:
        raw = np.fromfile(os.path.join(frames_dir, c["file"]), dtype=np.uint8)
        clips[c["name"]] = raw.reshape(c["frames"], c["height"], c["width"], 3)
    return clips


def to_u8(pv, mean, std):
    x = pv * (np.asarray(std)[:, None, None] * 255.0) + np.asarray(mean)[:, None, None] * 255.0
    r = np.rint(x)
    err = np.abs(x - r).max()
    assert err < 2e-3, f"pixel values are not an affine image of uint8 values (off by {err})"
    return r.clip(0, 255).astype(np.uint8)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("--repo", required=True)
    ap.add_argument("--bench", action="store_true", help="time the reference on the --mid fixture")
    ap.add_argument("--new-tokens", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args()
    stub_modules()
    sys.path.insert(0, args.repo)
    import torch
    import transformers
    from transformers import AutoTokenizer, CLIPVisionConfig, PretrainedConfig

    import videollama2.model.encoder as enc

    class EagerCLIPVisionConfig(CLIPVisionConfig):
        @property
        def _attn_implementation(self):
            return "eager"

        @_attn_implementation.setter
        def _attn_implementation(self, value):
            self._attn_implementation_internal = "eager"

    enc.CLIPVisionConfig = EagerCLIPVisionConfig
    from videollama2.constants import DEFAULT_VIDEO_TOKEN, NUM_FRAMES
    from videollama2.mm_utils import frame_sample, process_video, tokenizer_multimodal_token
    from videollama2.model import Videollama2MistralForCausalLM

    torch.manual_seed(0)
    torch.set_num_threads(args.threads or max(1, os.cpu_count() or 1))
    root = args.root
    clips = load_clips(os.path.join(root, "frames"))

    def load(name):
        path = os.path.join(root, name)
        tok = AutoTokenizer.from_pretrained(path, use_fast=True)
        if tok.pad_token is None and tok.unk_token is not None:
            tok.pad_token = tok.unk_token
        model = Videollama2MistralForCausalLM.from_pretrained(path, torch_dtype=torch.float32).eval()
        return tok, model

    def load_lora(lora_dir):
        # load_pretrained_model's LoRA branch, in float32.
        cfg = transformers.AutoConfig.from_pretrained(lora_dir)
        base = PretrainedConfig.from_pretrained(lora_dir)._name_or_path
        tok = AutoTokenizer.from_pretrained(base, use_fast=True)
        if tok.pad_token is None and tok.unk_token is not None:
            tok.pad_token = tok.unk_token
        model = Videollama2MistralForCausalLM.from_pretrained(base, config=cfg, torch_dtype=torch.float32)
        extra = torch.load(os.path.join(lora_dir, "non_lora_trainables.bin"), map_location="cpu")
        extra = {(k[11:] if k.startswith("base_model.") else k): v for k, v in extra.items()}
        if any(k.startswith("model.model.") for k in extra):
            extra = {(k[6:] if k.startswith("model.") else k): v for k, v in extra.items()}
        missing = model.load_state_dict(extra, strict=False)
        assert not missing.unexpected_keys, missing.unexpected_keys
        from peft import PeftModel
        model = PeftModel.from_pretrained(model, lora_dir).merge_and_unload().eval()
        return tok, model

    def video_tensor(model, clip, aspect):
        processor = model.get_vision_tower().image_processor
        n = model.config.num_frames if hasattr(model.config, "num_frames") else NUM_FRAMES
        idx = frame_sample(len(clip), mode="uniform", num_frames=n)
        frames = [clip[i] for i in idx]
        return process_video(frames, processor, aspect_ratio=aspect, num_frames=n), [int(i) for i in idx]

    def prompt_ids(tok, model, instruct):
        # mm_infer's text side.
        modal_token = DEFAULT_VIDEO_TOKEN
        message = [{"role": "user", "content": modal_token + "\n" + instruct}]
        if model.config.model_type in ["videollama2", "videollama2_mistral", "videollama2_mixtral"]:
            system_message = [{"role": "system", "content": (
                """<<SYS>>\nYou are a helpful, respectful and honest assistant. Always answer as helpfully as possible, while being safe.  Your answers should not include any harmful, unethical, racist, sexist, toxic, dangerous, or illegal content. Please ensure that your responses are socially unbiased and positive in nature."""
                """\n"""
                """If a question does not make any sense, or is not factually coherent, explain why instead of answering something not correct. If you don't know the answer to a question, please don't share false information.\n<</SYS>>""")}]
        else:
            system_message = []
        prompt = tok.apply_chat_template(system_message + message, tokenize=False, add_generation_prompt=True)
        ids = tokenizer_multimodal_token(prompt, tok, modal_token, return_tensors="pt").unsqueeze(0).long()
        return prompt, ids

    def greedy(model, tok, ids, video):
        """Greedy decoding with the cache, without stopping at EOS, and checked against the
        repository's `generate` up to its stop."""
        mask = ids.ne(tok.pad_token_id).long()
        images = [(video, "video")]
        out = model(input_ids=ids, attention_mask=mask, images=images, use_cache=True)
        first = out.logits[:, -1].float()
        past = out.past_key_values
        length = out.logits.shape[1]
        logits, got = first, []
        for _ in range(NEW_TOKENS):
            nxt = logits.argmax(-1)
            got.append(int(nxt[0]))
            length += 1
            out = model(input_ids=nxt[:, None], attention_mask=torch.ones(1, length, dtype=torch.long),
                        past_key_values=past, use_cache=True)
            past = out.past_key_values
            logits = out.logits[:, -1].float()
        gen = model.generate(ids, attention_mask=mask, images=images, do_sample=False,
                             max_new_tokens=NEW_TOKENS, use_cache=True, pad_token_id=tok.eos_token_id)
        g = gen[0].tolist()
        stop = next((i for i, t in enumerate(got) if t == tok.eos_token_id), len(got) - 1) + 1
        assert g[:stop] == got[:stop], f"generate {g} vs manual greedy {got}"
        return first, got, length - NEW_TOKENS

    if args.bench:
        # examples/family_bench.rs's protocol: the landscape clip, "describe"; TTFT from decoded
        # frames to the first token; then exactly --new-tokens greedy tokens (no EOS).
        tok, model = load("mistral-base")
        clip = clips["landscape"]

        def first():
            t0 = time.perf_counter()
            video, _ = video_tensor(model, clip, "pad")
            _, ids = prompt_ids(tok, model, PROMPTS["describe"])
            mask = ids.ne(tok.pad_token_id).long()
            out = model(input_ids=ids, attention_mask=mask, images=[(video, "video")], use_cache=True)
            nxt = out.logits[:, -1].argmax(-1)
            return time.perf_counter() - t0, out, nxt

        with torch.no_grad():
            first()
            ttft = min(first()[0] for _ in range(args.repeats))
            _, out, nxt = first()
            past, length = out.past_key_values, out.logits.shape[1]
            t0 = time.perf_counter()
            for _ in range(args.new_tokens - 1):
                length += 1
                out = model(input_ids=nxt[:, None], attention_mask=torch.ones(1, length, dtype=torch.long),
                            past_key_values=past, use_cache=True)
                past, nxt = out.past_key_values, out.logits[:, -1].argmax(-1)
            tps = (args.new_tokens - 1) / (time.perf_counter() - t0)
        print(json.dumps({"impl": "VideoLLaMA2 repository", "transformers": transformers.__version__,
                          "torch": torch.__version__, "ttft_s": ttft, "decode_tok_s": tps,
                          "prompt_tokens": length - args.new_tokens + 1,
                          "threads": torch.get_num_threads()}))
        return

    pre = {"transformers": transformers.__version__, "torch": torch.__version__, "clips": {}}
    cases = []
    with torch.no_grad():
        for variant, aspect in [("mistral-base", "pad"), ("mistral-crop", None)]:
            tok, model = load(variant)
            proc = model.get_vision_tower().image_processor
            for name, clip in clips.items():
                video, idx = video_tensor(model, clip, aspect)
                pv = video.numpy()
                u8 = np.stack([to_u8(f, proc.image_mean, proc.image_std) for f in pv])
                entry = {"indices": idx, "shape": list(pv.shape), "u8": b64u8(u8)}
                if name == "landscape":
                    entry["f32_frame0"] = b64f32(pv[0])
                pre["clips"][f"{variant}/{name}"] = entry
            for name, p in [("landscape", "describe"), ("portrait12", "manoeuvre"),
                            ("short5", "describe")] + ([("upscale", "manoeuvre")] if aspect else []):
                video, _ = video_tensor(model, clips[name], aspect)
                prompt, ids = prompt_ids(tok, model, PROMPTS[p])
                first, got, plen = greedy(model, tok, ids, video)
                cases.append({"model": variant, "clip": name, "prompt": p, "text": prompt,
                              "input_ids": ids[0].tolist(), "prompt_len": plen,
                              "vocab": first.shape[1], "logits": b64f32(first.numpy()),
                              "greedy": got})
        tok, model = load("mistral-notemplate")
        prompt, ids = prompt_ids(tok, model, PROMPTS["describe"])
        cases.append({"model": "mistral-notemplate", "clip": None, "prompt": "describe",
                      "text": prompt, "input_ids": ids[0].tolist()})
        tok, model = load_lora(os.path.join(root, "videollama2-lora"))
        for name, p in [("landscape", "describe"), ("portrait12", "manoeuvre")]:
            video, _ = video_tensor(model, clips[name], "pad")
            prompt, ids = prompt_ids(tok, model, PROMPTS[p])
            first, got, plen = greedy(model, tok, ids, video)
            cases.append({"model": "videollama2-lora", "clip": name, "prompt": p, "text": prompt,
                          "input_ids": ids[0].tolist(), "prompt_len": plen,
                          "vocab": first.shape[1], "logits": b64f32(first.numpy()), "greedy": got})
    os.makedirs(OUT, exist_ok=True)
    meta = {"transformers": transformers.__version__, "torch": torch.__version__,
            "repository": "DAMO-NLP-SG/VideoLLaMA2", "new_tokens": NEW_TOKENS}
    with open(os.path.join(OUT, "preprocess.json"), "w") as f:
        json.dump(pre, f)
    with open(os.path.join(OUT, "cases.json"), "w") as f:
        json.dump({"meta": meta, "cases": cases}, f)
    print(f"wrote {len(cases)} cases and {len(pre['clips'])} preprocessed clips to {OUT}")


if __name__ == "__main__":
    main()
