#!/usr/bin/env python3
"""Writes an ONNX graph of a BERT encoder (HF `BertModel`, e.g. all-MiniLM-L6-v2) whose weights
stay in the checkpoint's own `model.safetensors`, referenced as ONNX external data.

Why this and not a second copy of the weights: no PyPI package ships all-MiniLM-L6-v2 as an fp32
ONNX file, and an export through torch needs torch, which neither CI nor a CPU deployment has. A
safetensors file is an 8-byte header length, a JSON header and the raw little-endian tensors, so
every weight already sits at a known byte range of a file we fetch and SHA-check: the graph only
has to point at those ranges. The graph itself is a few tens of KB, so it is committed and the
fetch script drops it next to the checkpoint; ONNX Runtime then reads the weights straight from
the safetensors file.

Needs only the `onnx` package (no torch, no numpy):

    python scripts/onnx/bert_graph.py MODEL_DIR OUT.onnx

MODEL_DIR holds `config.json` and `model.safetensors` (keys with or without a `bert.` prefix).
The graph has the inputs of an HF export (`input_ids`, `attention_mask`, `token_type_ids`, int64
`[batch, sequence]`) and its output `last_hidden_state` (`[batch, sequence, hidden]`); pooling
is left to the caller, as with an HF export. Its metadata records the SHA-256 of the safetensors
file it was written for (`safetensors_sha256`), because the byte offsets are only valid for that
exact file.
"""

import hashlib
import json
import struct
import sys
from pathlib import Path

import onnx
from onnx import TensorProto, helper

OPSET = 20  # Gelu (20) and LayerNormalization (17) as single ops
IR_VERSION = 10  # readable by every ONNX Runtime since 1.16


def read_header(path: Path):
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
    header.pop("__metadata__", None)
    return 8 + n, header


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class Builder:
    def __init__(self, st_path: Path):
        self.data_start, self.header = read_header(st_path)
        self.location = st_path.name
        self.prefix = "bert." if any(k.startswith("bert.") for k in self.header) else ""
        self.nodes = []
        self.inits = []
        self.n = 0

    def weight(self, key: str):
        """An initializer that reads tensor `key` from the safetensors file."""
        meta = self.header.get(self.prefix + key)
        if meta is None:
            sys.exit(f"tensor {self.prefix + key} not in the checkpoint")
        if meta["dtype"] != "F32":
            sys.exit(f"tensor {key} is {meta['dtype']}; only F32 checkpoints are supported")
        start, end = meta["data_offsets"]
        t = TensorProto()
        t.name = key
        t.data_type = TensorProto.FLOAT
        t.dims.extend(meta["shape"])
        t.data_location = TensorProto.EXTERNAL
        for k, v in (("location", self.location), ("offset", str(self.data_start + start)),
                     ("length", str(end - start))):
            e = t.external_data.add()
            e.key, e.value = k, v
        self.inits.append(t)
        return key

    def const(self, name, dtype, dims, vals):
        self.inits.append(helper.make_tensor(name, dtype, dims, vals))
        return name

    def op(self, op_type, inputs, **attrs):
        self.n += 1
        out = f"{op_type.lower()}_{self.n}"
        self.nodes.append(helper.make_node(op_type, inputs, [out], **attrs))
        return out

    def linear(self, x, key):
        """x @ W^T + b for a torch `Linear` stored as W [out, in]; ONNX Runtime folds the
        transpose of the constant once, at session start."""
        wt = self.op("Transpose", [self.weight(key + ".weight")], perm=[1, 0])
        return self.op("Add", [self.op("MatMul", [x, wt]), self.weight(key + ".bias")])

    def layer_norm(self, x, key, eps):
        return self.op("LayerNormalization",
                       [x, self.weight(key + ".weight"), self.weight(key + ".bias")],
                       axis=-1, epsilon=eps)


def build(model_dir: Path, out: Path):
    cfg = json.loads((model_dir / "config.json").read_text())
    st = model_dir / "model.safetensors"
    if cfg.get("hidden_act", "gelu") != "gelu":
        sys.exit(f"hidden_act {cfg['hidden_act']} unsupported (exact gelu only)")
    if cfg.get("position_embedding_type", "absolute") != "absolute":
        sys.exit("only absolute position embeddings are supported")
    hidden, heads = cfg["hidden_size"], cfg["num_attention_heads"]
    if hidden % heads:
        sys.exit("hidden_size not divisible by num_attention_heads")
    dh = hidden // heads
    eps = float(cfg.get("layer_norm_eps", 1e-12))

    b = Builder(st)
    # Embeddings: word + absolute position (0..seq) + token type, then LayerNorm.
    word = b.op("Gather", [b.weight("embeddings.word_embeddings.weight"), "input_ids"])
    seq = b.op("Gather", [b.op("Shape", ["input_ids"]),
                          b.const("one_i", TensorProto.INT64, [], [1])], axis=0)
    pos_ids = b.op("Range", [b.const("zero_i", TensorProto.INT64, [], [0]), seq, "one_i"])
    pos = b.op("Gather", [b.weight("embeddings.position_embeddings.weight"), pos_ids])
    tt = b.op("Gather", [b.weight("embeddings.token_type_embeddings.weight"), "token_type_ids"])
    x = b.op("Add", [b.op("Add", [word, pos]), tt])
    x = b.layer_norm(x, "embeddings.LayerNorm", eps)

    # Additive attention mask [batch, 1, 1, seq]: 0 where attended, the lowest float where
    # padded (what transformers adds), so padded keys get exactly zero weight.
    maskf = b.op("Cast", ["attention_mask"], to=TensorProto.FLOAT)
    inv = b.op("Sub", [b.const("one_f", TensorProto.FLOAT, [], [1.0]), maskf])
    bias = b.op("Mul", [inv, b.const("neg_big", TensorProto.FLOAT, [], [-3.4028234663852886e38])])
    bias = b.op("Unsqueeze", [bias, b.const("axes_12", TensorProto.INT64, [2], [1, 2])])
    split = b.const("shape_bshd", TensorProto.INT64, [4], [0, 0, heads, dh])
    merge = b.const("shape_bsh", TensorProto.INT64, [3], [0, 0, hidden])
    scale = b.const("scale", TensorProto.FLOAT, [], [1.0 / dh ** 0.5])

    for i in range(cfg["num_hidden_layers"]):
        p = f"encoder.layer.{i}."
        q = b.op("Transpose", [b.op("Reshape", [b.linear(x, p + "attention.self.query"), split])],
                 perm=[0, 2, 1, 3])
        k = b.op("Transpose", [b.op("Reshape", [b.linear(x, p + "attention.self.key"), split])],
                 perm=[0, 2, 3, 1])
        v = b.op("Transpose", [b.op("Reshape", [b.linear(x, p + "attention.self.value"), split])],
                 perm=[0, 2, 1, 3])
        scores = b.op("Add", [b.op("Mul", [b.op("MatMul", [q, k]), scale]), bias])
        ctx = b.op("MatMul", [b.op("Softmax", [scores], axis=-1), v])
        ctx = b.op("Reshape", [b.op("Transpose", [ctx], perm=[0, 2, 1, 3]), merge])
        attn = b.linear(ctx, p + "attention.output.dense")
        x = b.layer_norm(b.op("Add", [attn, x]), p + "attention.output.LayerNorm", eps)
        inter = b.op("Gelu", [b.linear(x, p + "intermediate.dense")], approximate="none")
        y = b.linear(inter, p + "output.dense")
        x = b.layer_norm(b.op("Add", [y, x]), p + "output.LayerNorm", eps)
    b.nodes.append(helper.make_node("Identity", [x], ["last_hidden_state"]))

    ids = lambda n: helper.make_tensor_value_info(n, TensorProto.INT64, ["batch", "sequence"])
    graph = helper.make_graph(
        b.nodes, "bert_encoder",
        [ids("input_ids"), ids("attention_mask"), ids("token_type_ids")],
        [helper.make_tensor_value_info("last_hidden_state", TensorProto.FLOAT,
                                       ["batch", "sequence", hidden])],
        initializer=b.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="vlmfuse scripts/onnx/bert_graph.py")
    model.ir_version = IR_VERSION
    helper.set_model_props(model, {"safetensors_sha256": sha256(st),
                                   "weights_file": st.name})
    out.write_bytes(model.SerializeToString(deterministic=True))
    # The checker resolves external data beside the graph, so it can only run where the
    # checkpoint is next to the output (as the fetch script lays it out).
    if (out.parent / st.name).is_file():
        onnx.checker.check_model(str(out))
    print(f"wrote {out} ({out.stat().st_size} bytes, {len(b.nodes)} nodes, "
          f"{len(b.inits)} initializers, weights from {st.name})")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    build(Path(sys.argv[1]), Path(sys.argv[2]))
