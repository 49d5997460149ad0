#!/usr/bin/env python3
"""Reference outputs of ultralytics' own ONNX detection path and trackers, for vlmfuse-detect.

What it writes (tests/data/parity/detect/, compared by crates/vlmfuse-detect/tests/parity.rs):

  model.onnx        a YOLO11 built from scripts/parity/yolo/yolo11-tiny.yaml with random weights
                    (seed 0; nothing downloaded), exported by ultralytics to ONNX at imgsz 160
                    (static shape, opset and graph simplification as ultralytics chooses them),
                    with 8 COCO class names in its metadata; about 0.6 MB
  frame_*.png       synthetic dashcam-like frames of different sizes and aspect ratios (RGB)
  letterbox_*.png   the predictor's preprocessed input for each frame, as grey levels (RGB): the
                    tensor is exactly these bytes / 255
  detect.json       per frame: the letterbox geometry, the raw output [1, 4 + nc, anchors] (f32
                    little-endian, base64) and, for three (conf, iou, max_det) settings, the final
                    boxes (xyxy in the frame's pixels), scores and classes of
                    `YOLO(model.onnx).predict(...)`
  tracker.json      a synthetic detection sequence (objects moving and crossing, an occlusion,
                    low-score detections, a one-frame false positive, a long absence) and the
                    tracks that ultralytics' BOTSORT (with_reid False, gmc_method none) and
                    BYTETracker output for it, frame by frame, under a few settings; and lap's
                    answers on 60 random cost matrices with a cost limit (the assignment the
                    trackers call), which `--tracker-only` rewrites alone

Random weights make every activation vanish through the network (default inits shrink the
variance layer by layer) and every class score sigmoid(bias) ~ 0.01 (ultralytics initialises the
class bias for a 640 px image), so nothing would pass a threshold. PATCHED, deterministically
(seed 0): the BatchNorm running statistics are set from one pass over 12 letterboxed synthetic
scenes (train mode, cumulative average), and in the last 1x1 conv of each level's class branch
(Detect.cv3[i][-1]) the weights are multiplied by CLS_WEIGHT_SCALE (0.7) and the bias set to
CLS_BIAS (-3) for every class, so that scores spread over (0, 1) with the image content and NMS
has overlapping candidates of several classes to choose between (some frames keep none, some
are cut by max_det). Nothing else of the model is changed.

The reference ran with (pinned; the script refuses other versions of the first two):
    ultralytics 8.4.190, torch 2.15.0 (CPU), onnx 1.23.2, onnxruntime 1.31.1, onnxslim 0.1.98,
    opencv-python 5.1.0.95, lap 0.5.13, numpy 2.5.5, Python 3.12
in a venv outside the repository, e.g.

    python3.12 -m venv /work/venvs/ultralytics
    PIP_CACHE_DIR=/work/venvs/pip-cache /work/venvs/ultralytics/bin/pip install torch==2.15.0
    /work/venvs/ultralytics/bin/pip install --no-deps torchvision==0.29.2
    /work/venvs/ultralytics/bin/pip install ultralytics==8.4.190 onnx onnxruntime==1.31.1 onnxslim lap
    /work/venvs/ultralytics/bin/python scripts/parity/yolo_detect.py

The export is not byte-for-byte reproducible (ultralytics writes the date into the metadata), so
a rerun rewrites model.onnx and its sha256 in detect.json with the same weights and outputs;
commit a rerun only when the model or the cases change.

ultralytics is kept offline (YOLO_OFFLINE=1, YOLO_AUTOINSTALL=False, its settings in a temporary
directory): nothing is downloaded, no font, no weights, no package.

Other modes (nothing in the repository is written):
    --model yolo11n.yaml --imgsz 640 --out DIR   the same files for the real YOLO11n (80 classes,
                                                 ~10 MB ONNX, so never committed); check them with
                                                 `cargo run --release -p vlmfuse-detect --example parity -- DIR`
    --bench MODEL.onnx [--threads N]             per-frame latency of ultralytics' ONNX path
                                                 (onnxruntime-python) on the 1280x720 parity frame
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

CFG_DIR = tempfile.mkdtemp(prefix="ultralytics-cfg-")
os.environ.update(
    YOLO_OFFLINE="1",
    YOLO_AUTOINSTALL="False",
    YOLO_CONFIG_DIR=CFG_DIR,
    YOLO_VERBOSE="False",
)

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import ultralytics  # noqa: E402
from ultralytics import YOLO  # noqa: E402
from ultralytics.engine.results import Boxes  # noqa: E402

CLS_WEIGHT_SCALE, CLS_BIAS = 0.7, -3.0
REPO = Path(__file__).resolve().parents[2]
TINY_YAML = Path(__file__).resolve().parent / "yolo" / "yolo11-tiny.yaml"
PINNED = {"ultralytics": "8.4.190", "torch": "2.15.0"}
# A driving subset of COCO, in COCO's order.
NAMES = {0: "person", 1: "bicycle", 2: "car", 3: "motorcycle", 4: "bus", 5: "truck", 6: "traffic light", 7: "stop sign"}
SETTINGS = [
    {"conf": 0.25, "iou": 0.7, "max_det": 300},  # ultralytics' predict defaults
    {"conf": 0.1, "iou": 0.45, "max_det": 300},
    {"conf": 0.05, "iou": 0.5, "max_det": 7},  # max_det truncates
]
# (width, height): landscape, odd sizes, exact model size, portrait, downscale by 8.
FRAME_SIZES = [(320, 180), (97, 61), (160, 160), (150, 400), (1280, 720), (641, 479)]


def versions() -> dict:
    import lap
    import onnx
    import onnxruntime

    v = {
        "ultralytics": ultralytics.__version__,
        "torch": torch.__version__.split("+")[0],
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "opencv": cv2.__version__,
        "lap": lap.__version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
    }
    try:
        import onnxslim

        v["onnxslim"] = onnxslim.__version__
    except ImportError:
        pass
    return v


def scene(w: int, h: int, seed: int) -> np.ndarray:
    """A synthetic road scene (BGR, uint8): sky and road gradients, lane marks, boxes and discs."""
    rng = np.random.default_rng(seed)
    y = np.linspace(0.0, 1.0, h)[:, None]
    x = np.linspace(0.0, 1.0, w)[None, :]
    img = np.zeros((h, w, 3), np.float64)
    sky = y < 0.45
    img[..., 0] = np.where(sky, 200 - 80 * y, 90 + 40 * y + 10 * x)
    img[..., 1] = np.where(sky, 160 - 60 * y, 90 + 30 * y)
    img[..., 2] = np.where(sky, 120 - 40 * y + 30 * x, 90 + 25 * y)
    img = np.clip(img, 0, 255).astype(np.uint8)
    s = max(w, h) / 320.0
    for _ in range(7):
        cx, cy = int(rng.uniform(0.05, 0.95) * w), int(rng.uniform(0.3, 0.95) * h)
        bw, bh = int(rng.uniform(10, 60) * s), int(rng.uniform(10, 50) * s)
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.rectangle(img, (cx - bw // 2, cy - bh // 2), (cx + bw // 2, cy + bh // 2), colour, -1)
    for _ in range(4):
        cx, cy = int(rng.uniform(0.05, 0.95) * w), int(rng.uniform(0.05, 0.5) * h)
        r = max(1, int(rng.uniform(3, 12) * s))
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.circle(img, (cx, cy), r, colour, -1)
    for k in range(5):
        x0 = int(w / 2 + (k - 2) * 0.05 * w)
        cv2.line(img, (x0, int(0.5 * h)), (int(w / 2 + (k - 2) * 0.4 * w), h - 1), (230, 230, 230), max(1, int(s)))
    return img


def calibrate_batchnorm(model, imgsz: int) -> None:
    """BatchNorm running statistics from one pass over letterboxed synthetic scenes (cumulative
    average), so that activations keep unit scale through the random network."""
    from ultralytics.data.augment import LetterBox

    lb = LetterBox((imgsz, imgsz), auto=False, stride=32)
    batch = [lb(image=scene(w, h, seed=500 + k)) for k, (w, h) in enumerate(FRAME_SIZES * 2)]
    x = torch.from_numpy(np.stack(batch)[..., ::-1].copy()).permute(0, 3, 1, 2).float() / 255.0
    net = model.model
    for mod in net.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.reset_running_stats()
            mod.momentum = None
    net.train()
    with torch.no_grad():
        net(x)
    net.eval()


def patch_class_heads(model) -> None:
    det = model.model.model[-1]
    with torch.no_grad():
        for seq in det.cv3:
            conv = seq[-1]
            conv.weight.mul_(CLS_WEIGHT_SCALE)
            conv.bias.fill_(CLS_BIAS)


def build_and_export(yaml: Path, imgsz: int, out: Path, names: dict | None, patch: bool) -> Path:
    torch.manual_seed(0)
    model = YOLO(str(yaml))
    if names is not None:
        model.model.names = names
    if patch:
        calibrate_batchnorm(model, imgsz)
        patch_class_heads(model)
    work = Path(tempfile.mkdtemp(prefix="yolo-export-"))
    cwd = os.getcwd()
    try:
        os.chdir(work)
        exported = work / Path(model.export(format="onnx", imgsz=imgsz, dynamic=False, device="cpu"))
    finally:
        os.chdir(cwd)
    dest = out / "model.onnx"
    shutil.copyfile(exported, dest)
    shutil.rmtree(work, ignore_errors=True)
    return dest


def f32_b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode()


def detect_reference(model_path: Path, imgsz: int, out: Path) -> dict:
    model = YOLO(str(model_path), task="detect")
    frames = []
    for i, (w, h) in enumerate(FRAME_SIZES):
        bgr = scene(w, h, seed=100 + i)
        name = f"frame_{i}_{w}x{h}.png"
        cv2.imwrite(str(out / name), bgr)  # PNG stores RGB; the Rust test reads RGB
        assert (cv2.imread(str(out / name)) == bgr).all()
        runs = []
        for s in SETTINGS:
            r = model.predict(bgr, imgsz=imgsz, verbose=False, **s)[0]
            b = r.boxes
            runs.append(
                {
                    **s,
                    "boxes": [
                        [*map(float, xyxy), float(c), int(k)]
                        for xyxy, c, k in zip(b.xyxy.numpy(), b.conf.numpy(), b.cls.numpy())
                    ],
                }
            )
        pred = model.predictor
        im = pred.preprocess([bgr])  # exactly the predictor's letterbox, BGR->RGB, /255
        raw = pred.inference(im)
        raw = raw[0] if isinstance(raw, (list, tuple)) else raw
        raw = raw.numpy() if isinstance(raw, torch.Tensor) else np.asarray(raw)
        levels = np.rint(im[0].numpy() * 255.0)
        assert np.array_equal(levels / 255.0, im[0].numpy().astype(np.float64)) or np.abs(
            levels.astype(np.float32) / 255.0 - im[0].numpy()
        ).max() == 0.0
        lb_name = f"letterbox_{i}.png"
        rgb = levels.astype(np.uint8).transpose(1, 2, 0)
        cv2.imwrite(str(out / lb_name), rgb[..., ::-1])
        frames.append(
            {
                "file": name,
                "width": w,
                "height": h,
                "letterbox": lb_name,
                "input_shape": list(im.shape),
                "raw_shape": list(raw.shape),
                "raw_f32_le": f32_b64(raw),
                "runs": runs,
            }
        )
        print(f"frame {w}x{h}: " + ", ".join(f"conf {r['conf']}: {len(r['boxes'])} boxes" for r in runs))
    return {"frames": frames}


# --- trackers ---------------------------------------------------------------------------------


class Obj:
    def __init__(self, cls, x, y, w, h, vx, vy, frames, score=(0.7, 0.9), low=()):
        self.cls, self.x, self.y, self.w, self.h, self.vx, self.vy = cls, x, y, w, h, vx, vy
        self.frames, self.score, self.low = frames, score, set(low)


def detection_sequence(seed: int = 7, n: int = 60):
    """Objects in a 1280x720 frame; each frame's detections in a shuffled order, with noise."""
    rng = np.random.default_rng(seed)
    on = lambda a, b: set(range(a, b))  # noqa: E731
    objs = [
        Obj(2, 100, 450, 160, 90, 9.0, 0.5, on(0, 60)),  # car driving right
        Obj(0, 900, 480, 40, 110, -8.0, 0.0, on(0, 60)),  # person walking left: crosses the car
        Obj(6, 640, 150, 24, 60, 0.3, -0.2, on(5, 14) | on(18, 60)),  # light, occluded 14-17
        Obj(7, 1000, 300, 50, 50, -1.0, 0.2, on(10, 60), low=on(20, 28)),  # stop sign, weak 20-27
        Obj(2, 300, 300, 120, 70, 2.0, 0.0, {12}),  # a one-frame false positive
        Obj(5, 1100, 500, 150, 120, -3.0, 0.0, on(0, 8) | on(45, 60)),  # truck gone 37 frames
        Obj(0, 200, 200, 30, 80, 0.5, 0.0, on(0, 60), score=(0.12, 0.22)),  # only ever weak
        Obj(3, 500, 600, 60, 50, 4.0, -1.0, on(30, 60), score=(0.26, 0.4)),  # new, near threshold
    ]
    seq = []
    for t in range(n):
        dets = []
        for o in objs:
            if t not in o.frames:
                continue
            cx, cy = o.x + o.vx * t, o.y + o.vy * t
            w = o.w * (1 + 0.002 * t) + rng.normal(0, 1.0)
            h = o.h * (1 + 0.002 * t) + rng.normal(0, 1.0)
            cx += rng.normal(0, 1.5)
            cy += rng.normal(0, 1.5)
            lo, hi = (0.12, 0.2) if t in o.low else o.score
            conf = float(rng.uniform(lo, hi))
            dets.append([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2, conf, o.cls])
        order = rng.permutation(len(dets))
        seq.append([[round(float(v), 3) for v in dets[k][:5]] + [int(dets[k][5])] for k in order])
    return seq


def run_tracker(kind: str, overrides: dict, seq):
    from types import SimpleNamespace

    from ultralytics.trackers.bot_sort import BOTSORT
    from ultralytics.trackers.byte_tracker import BYTETracker
    from ultralytics.utils import YAML
    from ultralytics.utils.checks import check_yaml

    cfg = YAML.load(check_yaml(f"{kind}.yaml"))
    cfg.update(overrides)
    args = SimpleNamespace(**cfg)
    tracker = BOTSORT(args) if kind == "botsort" else BYTETracker(args)
    img = np.zeros((720, 1280, 3), np.uint8)
    frames = []
    for dets in seq:
        data = np.asarray(dets, np.float32).reshape(-1, 6)
        boxes = Boxes(data, orig_shape=(720, 1280)).numpy()
        out = tracker.update(boxes, img)
        frames.append([[round(float(v), 6) for v in row[:4]] + [int(row[4]), float(row[5]), int(row[6]), int(row[7])] for row in out])
    return frames


def assignment_reference(seed: int = 11, n: int = 60) -> list:
    """lap.lapjv(cost, extend_cost=True, cost_limit=thresh) on random f32 cost matrices, as
    ultralytics' matching.linear_assignment calls it: the row -> column answer (-1 unmatched)."""
    import lap

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        rows, cols = int(rng.integers(1, 9)), int(rng.integers(1, 9))
        cost = rng.random((rows, cols)).astype(np.float32)
        if k % 3 == 0:  # IoU-like: most pairs far apart (cost 1), a few close
            cost = np.where(rng.random((rows, cols)) < 0.7, np.float32(1.0), cost * np.float32(0.6))
        thresh = float(rng.choice([0.5, 0.7, 0.8]))
        _, x, _ = lap.lapjv(cost, extend_cost=True, cost_limit=thresh)
        out.append({"rows": rows, "cols": cols, "thresh": thresh, "cost": [float(v) for v in cost.ravel()], "x": [int(v) for v in x]})
    return out


def tracker_reference() -> dict:
    seq = detection_sequence()
    runs = []
    for kind, overrides in [
        ("botsort", {"gmc_method": "none", "with_reid": False}),
        ("botsort", {"gmc_method": "none", "with_reid": False, "track_buffer": 10, "fuse_score": False}),
        ("bytetrack", {}),
        ("bytetrack", {"track_buffer": 10, "match_thresh": 0.6, "new_track_thresh": 0.5}),
    ]:
        frames = run_tracker(kind, overrides, seq)
        ids = sorted({r[4] for f in frames for r in f})
        print(f"{kind} {overrides}: {len(ids)} ids")
        runs.append({"tracker": kind, "overrides": overrides, "frames": frames})
    return {"detections": seq, "width": 1280, "height": 720, "runs": runs, "assignments": assignment_reference()}


# --- bench ------------------------------------------------------------------------------------


def bench(model_path: Path, threads: int | None, n: int = 30) -> None:
    """ultralytics' predict() per frame, and its three steps each timed alone, like the Rust
    example: preprocess (letterbox, BGR->RGB, /255), the ONNX run through its AutoBackend
    (onnxruntime-python), postprocess (NMS, scale_boxes, Results)."""
    bgr = cv2.imread(str(REPO / "tests/data/parity/detect/frame_4_1280x720.png"))
    model = YOLO(str(model_path), task="detect")
    model.predict(bgr, verbose=False)
    pred = model.predictor
    if threads:  # the AutoBackend's session, rebuilt with the same thread count as the Rust one
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        be = pred.model.backend if hasattr(pred.model, "backend") else pred.model
        sess = getattr(be, "session", None)
        if sess is not None:
            be.session = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
        model.predict(bgr, verbose=False)

    def timed(f) -> float:
        t = time.perf_counter()
        for _ in range(n):
            out = f()
        timed.last = out
        return (time.perf_counter() - t) / n * 1e3

    full = timed(lambda: model.predict(bgr, verbose=False))
    pre = timed(lambda: pred.preprocess([bgr]))
    im = timed.last
    inf = timed(lambda: pred.inference(im))
    raw = timed.last
    post = timed(lambda: pred.postprocess(raw, im, [bgr]))
    print(
        f"ultralytics {model_path.name} {im.shape[2]}x{im.shape[3]}: predict() {full:.2f} ms/frame "
        f"(alone: preprocess {pre:.2f}, onnxruntime {inf:.2f}, postprocess {post:.2f}; "
        f"intra threads {threads or 'default'}; {n} runs)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "tests/data/parity/detect")
    ap.add_argument("--model", default=str(TINY_YAML), help="model yaml (default: the tiny parity model)")
    ap.add_argument("--imgsz", type=int, default=160)
    ap.add_argument("--bench", type=Path, help="time ultralytics' ONNX path on this model and exit")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--tracker-only", action="store_true", help="rewrite tracker.json alone (no export)")
    a = ap.parse_args()

    v = versions()
    for k, want in PINNED.items():
        if v[k] != want:
            sys.exit(f"{k} {v[k]} is not the pinned {want}")
    if a.bench:
        bench(a.bench, a.threads)
        return
    tiny = Path(a.model).resolve() == TINY_YAML
    a.out.mkdir(parents=True, exist_ok=True)
    if a.tracker_only:
        tr = tracker_reference()
        tr["versions"] = v
        (a.out / "tracker.json").write_text(json.dumps(tr) + "\n")
        return
    for old in a.out.glob("*.png"):
        old.unlink()
    if tiny:
        names = NAMES
    else:  # COCO's 80 names (shipped with ultralytics), as a real detector's metadata has them
        from ultralytics.utils import YAML
        from ultralytics.utils.checks import check_yaml

        names = YAML.load(check_yaml("coco.yaml"))["names"]
    model_path = build_and_export(Path(a.model), a.imgsz, a.out, names, patch=True)
    digest = hashlib.sha256(model_path.read_bytes()).hexdigest()
    print(f"{model_path}: {model_path.stat().st_size} bytes, sha256 {digest}")
    det = detect_reference(model_path, a.imgsz, a.out)
    det.update(
        versions=v,
        model={"file": model_path.name, "sha256": digest, "yaml": Path(a.model).name, "imgsz": a.imgsz, "seed": 0},
        patched=f"BatchNorm statistics from synthetic scenes; Detect.cv3[i][-1]: weight *= {CLS_WEIGHT_SCALE}, bias = {CLS_BIAS}",
    )
    (a.out / "detect.json").write_text(json.dumps(det) + "\n")
    if tiny:
        tr = tracker_reference()
        tr["versions"] = v
        (a.out / "tracker.json").write_text(json.dumps(tr) + "\n")


if __name__ == "__main__":
    main()
