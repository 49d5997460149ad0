"""Unsupervised Dawid-Skene from crowd-kit (`BinaryRelevance(DawidSkene)`) on a rounds file,
scored like `vlmfuse eval`'s baselines: fitted without truth on every round, scored on the
rounds after the history split (default 0.7) that have truth. Issue 9 compares the adaptive
method at N = 50 labels with it; this is the independent implementation of that baseline.

    pip install crowd-kit pandas     # outside the repository (not needed by CI)
    python scripts/baselines/crowdkit_ds.py tests/data/rounds_hard.jsonl [--split 0.7]
"""

import argparse
import json

import pandas as pd
from crowdkit.aggregation import BinaryRelevance, DawidSkene


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("rounds")
    ap.add_argument("--split", type=float, default=0.7)
    a = ap.parse_args()
    rows = [json.loads(l) for l in open(a.rounds) if l.strip()]
    labels = sorted({x for r in rows for rep in r["reports"].values() for x in rep}
                    | {x for r in rows for x in (r.get("truth") or [])})
    records = []
    for t, r in enumerate(rows):
        for worker, rep in r["reports"].items():
            records.append({"task": t, "worker": worker, "label": list(rep)})
    df = pd.DataFrame(records)
    agg = BinaryRelevance(DawidSkene(n_iter=100)).fit_predict(df)
    n_hist = int(len(rows) * a.split)
    tp = fp = fn = 0
    per = {k: [0, 0, 0] for k in labels}
    ham = []
    for t in range(n_hist, len(rows)):
        truth = rows[t].get("truth")
        if truth is None:
            continue
        pred = set(agg.loc[t]) if t in agg.index else set()
        truth = set(truth)
        ham.append(len(pred ^ truth) / len(labels))
        for k in labels:
            p, y = k in pred, k in truth
            per[k][0] += p and y
            per[k][1] += p and not y
            per[k][2] += y and not p
    tp, fp, fn = (sum(v[i] for v in per.values()) for i in range(3))
    micro = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0
    macro = sum((2 * v[0] / (2 * v[0] + v[1] + v[2])) if sum(v) else 1.0 for v in per.values()) / len(labels)
    print(f"crowd-kit BinaryRelevance(DawidSkene) on {a.rounds}: {len(ham)} scored rounds")
    print(f"Hamming {sum(ham) / len(ham):.4f}  micro-F1 {micro:.4f}  macro-F1 {macro:.4f}")


if __name__ == "__main__":
    main()
