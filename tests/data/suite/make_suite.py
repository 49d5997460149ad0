#!/usr/bin/env python3
"""Writes the fusion benchmark suite: rounds files (docs/PAPER-METHOD.md §8, JSON Lines) and, for
sets whose labels are not the 14 driving labels, a TOML config with their `[[ontology]]`.
tests/data/suite/README.md describes every set; `scripts/fusion-suite` runs them.

Deterministic: the same command (with the same package versions, see README.md) writes the same
bytes. It needs scikit-learn and river (river only for the two datasets it ships), in a venv
outside the repository:

    python3 -m venv /work/venvs/suite
    /work/venvs/suite/bin/pip install scikit-learn==1.9.1 river==0.26.1
    /work/venvs/suite/bin/python tests/data/suite/make_suite.py            # every set
    /work/venvs/suite/bin/python tests/data/suite/make_suite.py --sets yeast,digits

Every set has two instances that share nothing, `<set>.dev.jsonl` and `<set>.heldout.jsonl`:
for real data, disjoint halves of the rows not used to train the reporters; for generated sets,
different seeds (another world of the same shape). CI does not run this script: its outputs are
committed.
"""
import argparse
import csv
import gzip
import io
import json
import os
import random
import subprocess
import sys
import zipfile

# One BLAS thread: identical floating-point reductions wherever this runs.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import numpy as np  # noqa: E402
import sklearn  # noqa: E402
from sklearn.datasets import load_digits  # noqa: E402
from sklearn.decomposition import PCA  # noqa: E402
from sklearn.linear_model import LogisticRegression  # noqa: E402
from sklearn.naive_bayes import GaussianNB  # noqa: E402
from sklearn.neighbors import KNeighborsClassifier  # noqa: E402
from sklearn.pipeline import make_pipeline  # noqa: E402
from sklearn.preprocessing import StandardScaler  # noqa: E402
from sklearn.svm import SVC  # noqa: E402
from sklearn.tree import DecisionTreeClassifier  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.dirname(HERE)

DRIVING = ["turn_left", "turn_right", "brake", "accelerate", "stop", "traffic_light_ahead",
           "junction_ahead", "pedestrian_crossing_ahead", "merge", "maintain_safe_distance",
           "check_blind_spot", "adjust_speed_due_to_weather", "yield_to_traffic",
           "drive_as_normal"]

# yeast-drift: round index (0-based, in file order) from which the best reporter hallucinates.
YEAST_DRIFT_AT = 350
YEAST_DRIFT_RATE = 0.30   # = the mean label density of yeast (4.24 of 14 labels)

# Generated sets: seeds per instance (dev, heldout).
SEEDS = {
    "near-oracle": (20261401, 20261402),
    "specialists": (20261501, 20261502),
    # make_hard_rounds.py's own seeds are the dev instances (the committed rounds_hard.jsonl and
    # rounds_drift.jsonl); the held-out instances are these other worlds.
    "hard": (None, 20261301),
    "drift": (None, 20261302),
}


# ---------------------------------------------------------------------------------------------
# Writing


def _num(v):
    r = round(float(v), 4)
    return 0.0 if r == 0 else r


def write_rounds(path, rounds):
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        for r in rounds:
            f.write(json.dumps(r, separators=(",", ":")) + "\n")


def write_config(path, title, labels):
    lines = [f"# {title}", "# `vlmfuse eval FILE --config THIS` (only [[ontology]]: [fusion] stays the default).", ""]
    for lab_id, name, desc in labels:
        lines += ["[[ontology]]", f'id = "{lab_id}"', f'name = "{name}"',
                  f'description = "{desc}"', ""]
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write("\n".join(lines))


def scores(rounds, reporter, labels):
    """Hamming and micro-F1 of one reporter over the rounds (absent = empty report)."""
    err = tp = fp = fn = 0
    for r in rounds:
        rep = set(r["reports"].get(reporter, []))
        tru = set(r["truth"])
        err += len(rep ^ tru)
        tp += len(rep & tru)
        fp += len(rep - tru)
        fn += len(tru - rep)
    ham = err / (len(rounds) * len(labels))
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0
    return ham, f1


def summary(name, rounds, labels):
    names = []
    for r in rounds:
        for n in r["reports"]:
            if n not in names:
                names.append(n)
    parts = []
    for n in names:
        h, f = scores(rounds, n, labels)
        parts.append(f"{n} H={h:.3f} F1={f:.3f}")
    return f"{name}: {len(rounds)} rounds; " + ", ".join(parts)


# ---------------------------------------------------------------------------------------------
# Real data: reporters are real classifiers, each trained on its own slice of a training part and
# on its own feature subset.


class PerLabel:
    """A binary classifier per label (multi-label); a label constant in the training slice is
    predicted with that constant."""

    def __init__(self, make):
        self.make = make

    def fit(self, x, y):
        self.models = []
        for k in range(y.shape[1]):
            col = y[:, k]
            if col.min() == col.max():
                self.models.append(float(col[0]))
            else:
                self.models.append(self.make().fit(x, col))
        return self

    def proba(self, x):
        out = np.zeros((x.shape[0], len(self.models)))
        for k, m in enumerate(self.models):
            out[:, k] = m if isinstance(m, float) else m.predict_proba(x)[:, 1]
        return out


def build_real(name, x, y, labels, one_hot, n_train, n_dev, n_heldout, reporters, shuffle_seed,
               pca_dims=None, missing=None):
    """Returns {"dev": rounds, "heldout": rounds}, the reporters' out-of-slice training scores and
    the row counts. `reporters`: list of (name, make_classifier, feature columns)."""
    n = len(x)
    assert n_train + n_dev + n_heldout <= n, (name, n)
    order = list(range(n))
    random.Random(shuffle_seed).shuffle(order)
    tr = order[:n_train]
    parts = {"dev": order[n_train:n_train + n_dev],
             "heldout": order[n_train + n_dev:n_train + n_dev + n_heldout]}
    # Context: standardized features (PCA when pca_dims), fitted on the training part only.
    ctx_model = StandardScaler()
    if pca_dims:
        ctx_model = make_pipeline(StandardScaler(), PCA(n_components=pca_dims, svd_solver="full"))
    ctx_model.fit(x[tr])
    # Reporters: disjoint contiguous slices of the (shuffled) training part.
    k = len(reporters)
    fitted = []
    oos = {}
    for i, (rname, make, cols) in enumerate(reporters):
        sl = tr[i * n_train // k:(i + 1) * n_train // k]
        in_slice = set(sl)
        rest = [j for j in tr if j not in in_slice]
        if one_hot:
            m = make_pipeline(StandardScaler(), make()).fit(x[sl][:, cols], y[sl])
        else:
            m = PerLabel(lambda: make_pipeline(StandardScaler(), make())).fit(
                x[sl][:, cols], y[sl])
        fitted.append((rname, m, cols))
        # Out-of-slice score on the rest of the training part (picks the drift set's best
        # reporter without looking at the scored rows).
        pred = predict(m, x[rest][:, cols], one_hot, len(labels))
        truth = onehot(y[rest], len(labels)) if one_hot else y[rest]
        oos[rname] = micro_f1(pred, truth)
    out = {}
    for part, idx in parts.items():
        ctx = ctx_model.transform(x[idx])
        preds = {rname: predict(m, x[idx][:, cols], one_hot, len(labels))
                 for rname, m, cols in fitted}
        truth = onehot(y[idx], len(labels)) if one_hot else y[idx]
        miss_rng = random.Random(f"{name}-{part}-missing")
        rounds = []
        for t in range(len(idx)):
            absent = None
            if missing and miss_rng.random() < missing[1]:
                absent = missing[0]
            reports = {rname: [labels[j] for j in np.flatnonzero(preds[rname][t])]
                       for rname, _, _ in fitted if rname != absent}
            rounds.append({"id": f"{name}-{part}-{t:05d}",
                           "context": [_num(v) for v in ctx[t]],
                           "reports": reports,
                           "truth": [labels[j] for j in np.flatnonzero(truth[t])]})
        out[part] = rounds
    return out, oos


def predict(model, x, one_hot, n_labels):
    if one_hot:
        return onehot(model.predict(x), n_labels)
    return (model.proba(x) > 0.5).astype(int)


def onehot(cls, n_labels):
    out = np.zeros((len(cls), n_labels), dtype=int)
    out[np.arange(len(cls)), cls] = 1
    return out


def micro_f1(pred, truth):
    tp = int((pred & truth).sum())
    fp = int((pred & (1 - truth)).sum())
    fn = int(((1 - pred) & truth).sum())
    return 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0


def river_file(name):
    """A data file river ships in its wheel (river.datasets), found without importing river."""
    import importlib.util
    spec = importlib.util.find_spec("river")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("river is not installed: pip install river==0.26.1 (see the docstring)")
    return os.path.join(list(spec.submodule_search_locations)[0], "datasets", name)


def set_digits():
    d = load_digits()
    x, y = d.data.astype(float), d.target.astype(int)
    labels = [f"digit_{i}" for i in range(10)]

    def region(rows, cols):
        return [r * 8 + c for r in rows for c in cols]
    reporters = [
        ("logreg", lambda: LogisticRegression(C=0.05, max_iter=3000), region(range(0, 5), range(8))),
        ("knn", lambda: KNeighborsClassifier(n_neighbors=9), region(range(3, 8), range(8))),
        ("nbayes", lambda: GaussianNB(var_smoothing=0.05), region(range(8), range(0, 5))),
        ("tree", lambda: DecisionTreeClassifier(max_depth=6, random_state=0),
         region(range(8), range(3, 8))),
    ]
    parts, oos = build_real("digits", x, y, labels, True, 597, 600, 600, reporters, 1797,
                            pca_dims=32)
    cfg = [(lab, f"digit {i}", f"handwritten digit {i} (8x8 image)") for i, lab in enumerate(labels)]
    return labels, parts, oos, cfg, "digits: scikit-learn load_digits, one-hot over 10 classes"


SEGMENT_CLASSES = ["brickface", "sky", "foliage", "cement", "window", "path", "grass"]


def set_segment():
    with zipfile.ZipFile(river_file("segment.csv.zip")) as z:
        text = z.read(z.namelist()[0]).decode("utf-8")
    rows = list(csv.DictReader(io.StringIO(text)))
    feats = [c for c in rows[0] if c != "category"]
    x = np.array([[float(r[c]) for c in feats] for r in rows])
    y = np.array([SEGMENT_CLASSES.index(r["category"]) for r in rows])
    # 0,1 position; 2,3 line densities; 4-7 edges; 8-14 colour means; 15-17 value/saturation/hue
    reporters = [
        ("logreg", lambda: LogisticRegression(C=0.1, max_iter=3000), [0, 1, 2, 3, 4, 5, 6, 7, 8]),
        ("knn", lambda: KNeighborsClassifier(n_neighbors=15), [9, 10, 11, 12]),
        ("nbayes", lambda: GaussianNB(), [4, 5, 6, 7, 15, 16, 17]),
        ("tree", lambda: DecisionTreeClassifier(max_depth=3, random_state=0), [0, 1, 13, 14, 16]),
    ]
    parts, oos = build_real("segment", x, y, SEGMENT_CLASSES, True, 710, 800, 800, reporters, 2310)
    cfg = [(c, c, f"an outdoor image region of {c}") for c in SEGMENT_CLASSES]
    return SEGMENT_CLASSES, parts, oos, cfg, "segment: UCI Statlog image segmentation (river), one-hot over 7 classes"


def set_yeast():
    with gzip.open(river_file("yeast.csv.gz"), "rt", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    feats = [f"Att{i}" for i in range(1, 104)]
    labs = [f"Class{i}" for i in range(1, 15)]
    x = np.array([[float(r[c]) for c in feats] for r in rows])
    y = np.array([[int(r[c] == "1") for c in labs] for r in rows])
    labels = [f"class{i}" for i in range(1, 15)]
    fr = random.Random(103)
    cols = [sorted(fr.sample(range(103), 40)) for _ in range(4)]
    reporters = [
        ("logreg", lambda: LogisticRegression(C=0.05, max_iter=3000), cols[0]),
        ("knn", lambda: KNeighborsClassifier(n_neighbors=15), cols[1]),
        ("nbayes", lambda: GaussianNB(), cols[2]),
        ("tree", lambda: DecisionTreeClassifier(max_depth=4, min_samples_leaf=5, random_state=0),
         cols[3]),
    ]
    parts, oos = build_real("yeast", x, y, labels, False, 1017, 700, 700, reporters, 2417,
                            pca_dims=32, missing=("knn", 0.04))
    cfg = [(lab, f"class {i}", f"yeast gene functional class {i} (MULAN yeast Class{i})")
           for i, lab in enumerate(labels, 1)]
    return labels, parts, oos, cfg, "yeast: MULAN yeast gene functions (river), 14 labels, multi-label"


def drift_of(name, parts, oos, labels):
    best = max(oos, key=lambda r: (oos[r], r))
    out = {}
    for part, rounds in parts.items():
        rng = random.Random(f"{name}-{part}-hallucination")
        new = []
        for t, r in enumerate(rounds):
            r = json.loads(json.dumps(r))
            r["id"] = f"{name}-{part}-{t:05d}"
            if t >= YEAST_DRIFT_AT and best in r["reports"]:
                r["reports"][best] = [lab for lab in labels if rng.random() < YEAST_DRIFT_RATE]
            new.append(r)
        out[part] = new
    return out, best


# ---------------------------------------------------------------------------------------------
# Generated sets (Python's `random` only: stable across versions).


def synth_world(rng, n_scenes, dim):
    centres = [[rng.gauss(0, 1) for _ in range(dim)] for _ in range(n_scenes)]
    rates = []
    for _ in range(n_scenes):
        typical = set(rng.sample(range(len(DRIVING)), 4))
        rates.append([rng.uniform(0.45, 0.85) if k in typical else rng.uniform(0.02, 0.10)
                      for k in range(len(DRIVING))])
    return centres, rates


def synth_rounds(name, part, seed, n_rounds, flip, n_scenes=6, dim=16, noise=0.8,
                 missing=None):
    """`flip(reporter_index, scene) -> probability each label's truth bit is flipped`."""
    rng = random.Random(seed)
    centres, rates = synth_world(rng, n_scenes, dim)
    n_rep = flip.n
    rounds = []
    for t in range(n_rounds):
        s = rng.randrange(n_scenes)
        ctx = [c + noise * rng.gauss(0, 1) for c in centres[s]]
        truth = [rng.random() < p for p in rates[s]]
        reports = {}
        for i in range(n_rep):
            name_i = flip.names[i]
            # Draw every reporter's bits even when absent (the other reporters' draws stay put).
            p = flip(i, s)
            bits = [b != (rng.random() < p) for b in truth]
            if missing and name_i == missing[0] and rng.random() < missing[1]:
                continue
            reports[name_i] = [DRIVING[k] for k, b in enumerate(bits) if b]
        rounds.append({"id": f"{name}-{part}-{t:05d}", "context": [_num(v) for v in ctx],
                       "reports": reports,
                       "truth": [DRIVING[k] for k, b in enumerate(truth) if b]})
    return rounds


class Flip:
    def __init__(self, names, fn):
        self.names, self.fn, self.n = names, fn, len(names)

    def __call__(self, i, s):
        return self.fn(i, s)


NEAR_ORACLE = Flip(["oracle", "fair", "weak"], lambda i, s: (0.02, 0.30, 0.45)[i])
# Three reporters, six scenes: each is reliable (95% per label) in its own two scenes, poor (58%)
# elsewhere.
SPECIALISTS = Flip(["alpha", "beta", "gamma"], lambda i, s: 0.05 if s // 2 == i else 0.42)


# ---------------------------------------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", default="all",
                    help="comma-separated: digits,segment,yeast,yeast-drift,near-oracle,"
                         "specialists,hard,drift (default all)")
    args = ap.parse_args()
    wanted = None if args.sets == "all" else set(args.sets.split(","))

    def want(s):
        return wanted is None or s in wanted

    print(f"numpy {np.__version__}, scikit-learn {sklearn.__version__}", file=sys.stderr)
    real = {"digits": set_digits, "segment": set_segment, "yeast": set_yeast}
    for sname, fn in real.items():
        if not (want(sname) or (sname == "yeast" and want("yeast-drift"))):
            continue
        labels, parts, oos, cfg, title = fn()
        print(f"{sname}: reporters' out-of-slice training micro-F1: "
              + ", ".join(f"{k} {v:.3f}" for k, v in oos.items()), file=sys.stderr)
        if want(sname):
            write_config(os.path.join(HERE, f"{sname}.toml"), title, cfg)
            for part, rounds in parts.items():
                write_rounds(os.path.join(HERE, f"{sname}.{part}.jsonl"), rounds)
                print("  " + summary(f"{sname}.{part}", rounds, labels), file=sys.stderr)
        if sname == "yeast" and want("yeast-drift"):
            dparts, best = drift_of("yeast-drift", parts, oos, labels)
            write_config(os.path.join(HERE, "yeast-drift.toml"),
                         f"yeast-drift: yeast with '{best}' hallucinating from round "
                         f"{YEAST_DRIFT_AT}", cfg)
            for part, rounds in dparts.items():
                write_rounds(os.path.join(HERE, f"yeast-drift.{part}.jsonl"), rounds)
                print(f"  yeast-drift.{part}: '{best}' hallucinates from round {YEAST_DRIFT_AT}; "
                      + summary("before", rounds[:YEAST_DRIFT_AT], labels) + "; "
                      + summary("after", rounds[YEAST_DRIFT_AT:], labels), file=sys.stderr)
    for sname, flip, miss in (("near-oracle", NEAR_ORACLE, ("weak", 0.05)),
                              ("specialists", SPECIALISTS, ("gamma", 0.03))):
        if not want(sname):
            continue
        for part, seed in zip(("dev", "heldout"), SEEDS[sname]):
            rounds = synth_rounds(sname, part, seed, 1000, flip, missing=miss)
            write_rounds(os.path.join(HERE, f"{sname}.{part}.jsonl"), rounds)
            print("  " + summary(f"{sname}.{part}", rounds, DRIVING), file=sys.stderr)
    for sname, mode, dev_file in (("hard", "hard", "rounds_hard.jsonl"),
                                  ("drift", "drift", "rounds_drift.jsonl")):
        if not want(sname):
            continue
        # dev: the committed file itself, by a relative symlink (no second copy).
        link = os.path.join(HERE, f"{sname}.dev.jsonl")
        if os.path.lexists(link):
            os.remove(link)
        os.symlink(os.path.join("..", dev_file), link)
        out = subprocess.run([sys.executable, os.path.join(DATA, "make_hard_rounds.py"), mode,
                              str(SEEDS[sname][1])], check=True, capture_output=True).stdout
        with open(os.path.join(HERE, f"{sname}.heldout.jsonl"), "wb") as f:
            f.write(out)
        print(f"  {sname}.dev -> ../{dev_file}; {sname}.heldout: make_hard_rounds.py {mode} "
              f"{SEEDS[sname][1]}", file=sys.stderr)


if __name__ == "__main__":
    main()
