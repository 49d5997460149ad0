#!/usr/bin/env python3
"""Reference outputs of the VLAAD repository's own code (sungyeonparkk/vision-assistant-for-driving,
Video-LLaMA's layout) on the project's tiny VLAAD release, for the Rust parity tests
(crates/vlmfuse-models/tests/vlaad_parity.rs).

Not run in CI. It needs the repository's pinned stack in a venv of its own, outside this
repository (transformers 4.28 and timm 0.6.13 as its environment.yml pins; torch 1.13.1, the
oldest release PEFT 0.3 accepts, for the LoRA case):

    /root/.pyenv/versions/3.10.13/bin/python3 -m venv /work/ref-vlaad
    /work/ref-vlaad/bin/pip install torch==1.13.1 torchvision==0.14.1 transformers==4.28.0 \
        tokenizers==0.13.3 timm==0.6.13 einops omegaconf==2.3.0 iopath==0.1.10 "numpy<1.24" \
        pillow sentencepiece peft==0.3.0 accelerate==0.16.0 decord==0.6.0
    git clone https://github.com/sungyeonparkk/vision-assistant-for-driving /work/ref-src/vlaad  # 29a049d
    cargo run -p vlmfuse-models --example vlaad_fixture -- /tmp/vlaad
    /work/ref-vlaad/bin/python scripts/parity/vlaad.py /tmp/vlaad --repo /work/ref-src/vlaad

Writes tests/data/parity/vlaad/cases.json. The clips are the committed
tests/data/parity/vlaad/*.mp4, decoded by the repository's `load_video` (decord, scaling to
the model's input size while decoding).

What is patched to run the repository's code on CPU with tiny weights, here and not in the
project:
- `video_llama/__init__.py` (every dataset, runner and task) is not run: a bare package stands
  in, and the modules the model needs are imported from the repository's files. The audio
  branch (ImageBind), `pycocotools` and `pycocoevalcap` are stubbed (the release runs without
  audio: `equip_audio_branch: False`), as is `cv2` (used by training augmentations only).
- `BertConfig.from_pretrained("bert-base-uncased")` and `BertTokenizer.from_pretrained` (network)
  give the tiny Q-Former config and no tokenizer (the model never uses BERT's tokenizer).
- `create_eva_vit_g` downloads ViT-g and converts it to fp16: the repository's own
  `VisionTransformer` class is built at the tiny size, loaded from the fixture's `eva_vit_g.pth`,
  in fp32.
- `LlamaForCausalLM.from_pretrained(..., torch_dtype=torch.bfloat16)` loads in float32 instead.
- `LlamaTokenizer` (slow, needs `tokenizer.model`) is `LlamaTokenizerFast` on the fixture's
  `tokenizer.json`.
- `Chat.answer` samples (`do_sample=True`): greedy decoding here, checked against the LLaMA's
  `generate` with the same embeddings.
"""

import argparse
import base64
import importlib.machinery
import json
import os
import sys
import types
from functools import partial

import numpy as np

NEW_TOKENS = 16
OUT = os.path.join("tests", "data", "parity", "vlaad")
PROMPTS = {
    "describe": "Describe the dashcam clip.",
    "manoeuvre": "What should the car do? Scene: Manoeuvres: Rationale:",
}


def b64f32(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype="<f4")).tobytes()).decode()


def b64u8(a):
    return base64.b64encode(np.ascontiguousarray(np.asarray(a, dtype=np.uint8)).tobytes()).decode()


def stub(name, **attrs):
    m = types.ModuleType(name)
    m.__spec__ = importlib.machinery.ModuleSpec(name, None)
    m.__path__ = []
    for k, v in attrs.items():
        setattr(m, k, v)
    sys.modules[name] = m
    return m


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("--repo", required=True)
    ap.add_argument("--bench", action="store_true", help="time the reference on the --mid fixture")
    ap.add_argument("--new-tokens", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args()
    import torch
    import torch.nn as nn
    import transformers
    from transformers import BertConfig, LlamaTokenizerFast

    root = os.path.join(args.root, "release")
    cfg = json.load(open(os.path.join(root, "config.json")))
    q = cfg["qformer"]
    v = cfg["vit"]

    # A bare `video_llama` package (its __init__ imports every dataset and runner).
    pkg = types.ModuleType("video_llama")
    pkg.__path__ = [os.path.join(args.repo, "video_llama")]
    sys.modules["video_llama"] = pkg
    stub("pycocotools")
    stub("pycocotools.coco", COCO=None)
    stub("pycocoevalcap")
    stub("pycocoevalcap.eval", COCOEvalCap=None)
    stub("video_llama.models.ImageBind")
    ib = stub("video_llama.models.ImageBind.models")
    ibm = stub("video_llama.models.ImageBind.models.imagebind_model",
               ImageBindModel=None, ModalityType=types.SimpleNamespace(AUDIO="audio"))
    ib.imagebind_model = ibm
    stub("video_llama.models.ImageBind.data", load_and_transform_audio_data=None)
    stub("cv2")
    models_pkg = types.ModuleType("video_llama.models")
    models_pkg.__path__ = [os.path.join(args.repo, "video_llama", "models")]
    sys.modules["video_llama.models"] = models_pkg

    BertConfig.from_pretrained = classmethod(lambda cls, *a, **k: BertConfig(
        hidden_size=q["hidden_size"], num_hidden_layers=q["num_hidden_layers"],
        num_attention_heads=q["num_attention_heads"], intermediate_size=q["intermediate_size"],
        layer_norm_eps=q["layer_norm_eps"], vocab_size=64, max_position_embeddings=64))
    import video_llama.models.base_model as base_model
    models_pkg.BaseModel = base_model.BaseModel
    import video_llama.models.eva_vit as eva
    import video_llama.models.blip2 as blip2

    def tiny_vit(img_size=224, drop_path_rate=0.4, use_checkpoint=False, precision="fp16"):
        model = eva.VisionTransformer(
            img_size=img_size, patch_size=v["patch_size"], use_mean_pooling=False,
            embed_dim=v["embed_dim"], depth=v["depth"], num_heads=v["num_heads"],
            mlp_ratio=v["mlp_ratio"], qkv_bias=True, drop_path_rate=drop_path_rate,
            norm_layer=partial(nn.LayerNorm, eps=1e-6), use_checkpoint=use_checkpoint)
        sd = torch.load(os.path.join(root, cfg["vit_model"]), map_location="cpu")
        eva.interpolate_pos_embed(model, sd)
        missing = model.load_state_dict(sd, strict=False)
        assert not missing.missing_keys and not missing.unexpected_keys, missing
        return model

    blip2.create_eva_vit_g = tiny_vit
    blip2.Blip2Base.init_tokenizer = classmethod(lambda cls: None)
    import video_llama.models.video_llama as vl

    vl.LlamaTokenizer = LlamaTokenizerFast
    orig = vl.LlamaForCausalLM.from_pretrained.__func__

    def f32_from_pretrained(cls, path, *a, **k):
        k["torch_dtype"] = torch.float32
        k.pop("load_in_8bit", None)
        k.pop("device_map", None)
        return orig(cls, path, *a, **k)

    vl.LlamaForCausalLM.from_pretrained = classmethod(f32_from_pretrained)
    from video_llama.conversation.conversation_video import conv_llava_llama_2
    from video_llama.processors.video_processor import AlproVideoEvalProcessor, load_video

    torch.manual_seed(0)
    torch.set_num_threads(args.threads or max(1, os.cpu_count() or 1))

    def build(lora=None):
        model = vl.VideoLLAMA(
            vit_model="eva_clip_g", q_former_model=os.path.join(root, cfg["q_former_model"]),
            img_size=cfg["img_size"], drop_path_rate=0, use_grad_checkpoint=False,
            vit_precision="fp32", freeze_vit=True, freeze_qformer=True,
            num_query_token=cfg["num_query_token"],
            llama_model=os.path.join(root, cfg["llama_model"]), prompt_path="",
            prompt_template="", max_txt_len=512, end_sym="###", low_resource=False,
            frozen_llama_proj=False, frozen_video_Qformer=False,
            max_frame_pos=cfg["max_frame_pos"],
            num_video_query_token=cfg["num_video_query_token"], equip_audio_branch=False)
        ckpt = torch.load(os.path.join(root, cfg["ckpt"]), map_location="cpu")
        msg = model.load_state_dict(ckpt["model"], strict=False)
        assert not msg.unexpected_keys, msg.unexpected_keys
        if lora:
            from peft import PeftModel
            model.llama_model = PeftModel.from_pretrained(model.llama_model, lora).merge_and_unload()
        return model.eval()

    proc = AlproVideoEvalProcessor(image_size=cfg["img_size"], n_frms=cfg["n_frms"])
    system = ("You are able to understand the visual content that the user provides. "
              "Follow the instructions carefully and explain your answers in detail.")

    def case(model, clip, prompt_key, tag):
        path = os.path.join(OUT, clip)
        # Chat.upload_video_without_audio
        video, msg = load_video(video_path=path, n_frms=cfg["n_frms"], height=cfg["img_size"],
                                width=cfg["img_size"], sampling="uniform", return_msg=True)
        u8 = video.permute(1, 2, 3, 0).to(torch.uint8).numpy()  # T, H, W, C as decoded
        video = proc.transform(video).unsqueeze(0)
        img_list = []
        image_emb, _ = model.encode_videoQformer_visual(video)
        img_list.append(image_emb)
        conv = conv_llava_llama_2.copy()
        conv.system = system
        conv.append_message(conv.roles[0], "<Video><ImageHere></Video> " + msg)
        # Chat.ask, then Chat.answer's prompt
        conv.messages[-1][1] = " ".join([conv.messages[-1][1], PROMPTS[prompt_key]])
        conv.append_message(conv.roles[1], None)
        prompt = conv.get_prompt()
        segs = prompt.split("<ImageHere>")
        seg_tokens = [model.llama_tokenizer(s, return_tensors="pt", add_special_tokens=i == 0).input_ids
                      for i, s in enumerate(segs)]
        seg_embs = [model.llama_model.model.embed_tokens(t) for t in seg_tokens]
        embs = torch.cat([seg_embs[0], img_list[0], seg_embs[1]], dim=1)
        out = model.llama_model(inputs_embeds=embs, use_cache=True)
        first = out.logits[:, -1].float()
        past, logits, got = out.past_key_values, first, []
        for _ in range(NEW_TOKENS):
            nxt = logits.argmax(-1)
            got.append(int(nxt[0]))
            out = model.llama_model(input_ids=nxt[:, None], past_key_values=past, use_cache=True)
            past, logits = out.past_key_values, out.logits[:, -1].float()
        gen = model.llama_model.generate(inputs_embeds=embs, max_new_tokens=NEW_TOKENS,
                                         do_sample=False, num_beams=1)[0].tolist()
        # Chat.answer drops a leading <unk> and <s> from what generate returns.
        if gen and gen[0] == 0:
            gen = gen[1:]
        if gen and gen[0] == 1:
            gen = gen[1:]
        stop = next((i for i, t in enumerate(got) if t == 2), len(got) - 1) + 1
        assert gen[:stop] == got[:stop], f"generate {gen} vs manual greedy {got}"
        return {"tag": tag, "clip": clip, "prompt": prompt_key, "text": prompt,
                "pieces": [t[0].tolist() for t in seg_tokens], "frames_u8": b64u8(u8),
                "frame_shape": list(u8.shape), "message": msg,
                "pixels_frame0": b64f32(video[0, :, 0].numpy()),
                "clip_tokens": b64f32(image_emb[0].numpy()),
                "vocab": first.shape[1], "logits": b64f32(first.numpy()), "greedy": got}

    if args.bench:
        # examples/family_bench.rs's protocol: clip20.mp4 decoded once (not timed), "describe";
        # TTFT from decoded frames to the first token; then exactly --new-tokens greedy tokens.
        import time
        model = build()
        frames, msg = load_video(video_path=os.path.join(OUT, "clip20.mp4"), n_frms=cfg["n_frms"],
                                 height=cfg["img_size"], width=cfg["img_size"], return_msg=True)

        def first():
            t0 = time.perf_counter()
            video = proc.transform(frames.clone()).unsqueeze(0)
            emb, _ = model.encode_videoQformer_visual(video)
            conv = conv_llava_llama_2.copy()
            conv.system = system
            conv.append_message(conv.roles[0], "<Video><ImageHere></Video> " + msg + " " + PROMPTS["describe"])
            conv.append_message(conv.roles[1], None)
            segs = conv.get_prompt().split("<ImageHere>")
            toks = [model.llama_tokenizer(s, return_tensors="pt", add_special_tokens=i == 0).input_ids
                    for i, s in enumerate(segs)]
            embs = torch.cat([model.llama_model.model.embed_tokens(toks[0]), emb,
                              model.llama_model.model.embed_tokens(toks[1])], dim=1)
            out = model.llama_model(inputs_embeds=embs, use_cache=True)
            return time.perf_counter() - t0, out, embs.shape[1]

        with torch.no_grad():
            first()
            ttft = min(first()[0] for _ in range(args.repeats))
            _, out, plen = first()
            past, nxt = out.past_key_values, out.logits[:, -1].argmax(-1)
            t0 = time.perf_counter()
            for _ in range(args.new_tokens - 1):
                out = model.llama_model(input_ids=nxt[:, None], past_key_values=past, use_cache=True)
                past, nxt = out.past_key_values, out.logits[:, -1].argmax(-1)
            tps = (args.new_tokens - 1) / (time.perf_counter() - t0)
        print(json.dumps({"impl": "VLAAD repository", "transformers": transformers.__version__,
                          "torch": torch.__version__, "ttft_s": ttft, "decode_tok_s": tps,
                          "prompt_tokens": plen, "threads": torch.get_num_threads()}))
        return

    cases = []
    with torch.no_grad():
        model = build()
        cases.append(case(model, "clip20.mp4", "describe", "base"))
        cases.append(case(model, "clip3.mp4", "manoeuvre", "base"))
        model = build(lora=os.path.join(args.root, "lora"))
        cases.append(case(model, "clip20.mp4", "manoeuvre", "lora"))
    meta = {"transformers": transformers.__version__, "torch": torch.__version__,
            "repository": "sungyeonparkk/vision-assistant-for-driving", "new_tokens": NEW_TOKENS}
    with open(os.path.join(OUT, "cases.json"), "w") as f:
        json.dump({"meta": meta, "cases": cases}, f)
    print(f"wrote {len(cases)} cases to {OUT}")


if __name__ == "__main__":
    main()
