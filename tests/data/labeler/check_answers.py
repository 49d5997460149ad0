#!/usr/bin/env python3
"""Validates answers.jsonl and prints its statistics.

Checks (exit status 1 with every problem listed when one fails):
- every line is a JSON object with id, split ("train" | "test"), text, labels, source
  ("template" | "handwritten") and style; voice, tags and traps are optional;
- ids and texts (whitespace-normalised, case-folded) are unique;
- labels and traps are ontology ids (config/default.toml), without repeats, and no trap is also
  a label (a trap is a label the text mentions that must NOT count);
- the template lines are exactly what gen_answers.py prints (the generator and the file cannot
  drift apart), and every test answer is hand-written.

Statistics: positives per label and split (and per source within train), label-set sizes, styles,
voices, tags and traps per label.

Usage: python3 tests/data/labeler/check_answers.py [--quiet] [--file answers_styles.jsonl]
(--file: the second set, other answer styles; it has no template lines, and no text of it may
repeat one of the first set.)
Standard library only (Python >= 3.11 for tomllib).
"""
import json
import re
import subprocess
import sys
import tomllib
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
REQUIRED = ("id", "split", "text", "labels", "source", "style")
OPTIONAL = ("voice", "tags", "traps", "author")
SETS = ("answers.jsonl", "answers_styles.jsonl")


def ontology():
    cfg = tomllib.loads((ROOT / "config" / "default.toml").read_text(encoding="utf-8"))
    return [o["id"] for o in cfg["ontology"]]


def norm(text):
    return re.sub(r"\s+", " ", text).strip().casefold()


def main():
    quiet = "--quiet" in sys.argv
    name = sys.argv[sys.argv.index("--file") + 1] if "--file" in sys.argv else SETS[0]
    onto = ontology()
    errors = []
    rows = []
    for n, line in enumerate((HERE / name).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
        except json.JSONDecodeError as e:
            errors.append(f"line {n}: not JSON: {e}")
            continue
        missing = [k for k in REQUIRED if k not in r]
        extra = [k for k in r if k not in REQUIRED + OPTIONAL]
        if missing or extra:
            errors.append(f"line {n}: missing fields {missing}, unknown fields {extra}")
            continue
        if r["split"] not in ("train", "test"):
            errors.append(f"{r['id']}: split {r['split']!r}")
        if r["source"] not in ("template", "handwritten"):
            errors.append(f"{r['id']}: source {r['source']!r}")
        if not r["text"].strip():
            errors.append(f"{r['id']}: empty text")
        for field in ("labels", "traps"):
            xs = r.get(field, [])
            bad = [x for x in xs if x not in onto]
            if bad:
                errors.append(f"{r['id']}: {field} not in the ontology: {bad}")
            if len(set(xs)) != len(xs):
                errors.append(f"{r['id']}: repeated {field}")
        both = set(r["labels"]) & set(r.get("traps", []))
        if both:
            errors.append(f"{r['id']}: both label and trap: {sorted(both)}")
        if r["split"] == "test" and r["source"] != "handwritten":
            errors.append(f"{r['id']}: the test split must be hand-written")
        r["_line"] = n
        rows.append(r)

    for key, what in ((lambda r: r["id"], "id"), (lambda r: norm(r["text"]), "text")):
        seen = {}
        for r in rows:
            k = key(r)
            if k in seen:
                errors.append(f"{r['id']}: duplicate {what} of {seen[k]}")
            seen.setdefault(k, r["id"])

    others = {norm(json.loads(l)["text"]): o for o in SETS if o != name
              for l in (HERE / o).read_text(encoding="utf-8").splitlines() if l.strip()}
    for r in rows:
        if norm(r["text"]) in others:
            errors.append(f"{r['id']}: the same text is in {others[norm(r['text'])]}")

    gen = subprocess.run([sys.executable, str(HERE / "gen_answers.py")], capture_output=True,
                         text=True, check=True).stdout.splitlines()
    templ = [{k: v for k, v in r.items() if k != "_line"} for r in rows if r["source"] == "template"]
    gen_rows = [json.loads(l) for l in gen] if name == SETS[0] else []
    if templ != gen_rows:
        diff = next((a["id"] for a, b in zip(templ, gen_rows) if a != b), "count")
        errors.append(f"template lines differ from gen_answers.py output (first at {diff}; "
                      f"{len(templ)} in file, {len(gen_rows)} generated)")

    if errors:
        print(f"{name}: FAILED", file=sys.stderr)
        for e in errors:
            print("  " + e, file=sys.stderr)
        sys.exit(1)

    splits = {"train": [r for r in rows if r["split"] == "train"],
              "test": [r for r in rows if r["split"] == "test"]}
    hand_tr = [r for r in splits["train"] if r["source"] == "handwritten"]
    tmpl_tr = [r for r in splits["train"] if r["source"] == "template"]
    hand = [r for r in rows if r["source"] == "handwritten"]
    print(f"{name}: OK, {len(rows)} answers: train {len(splits['train'])} "
          f"({len(tmpl_tr)} template + {len(hand_tr)} hand-written), test {len(splits['test'])} "
          f"(hand-written)")
    if quiet:
        return

    def count(rs, field="labels"):
        return Counter(x for r in rs for x in r.get(field, []))

    cols = [("train:tmpl", count(tmpl_tr)), ("train:hand", count(hand_tr)),
            ("train", count(splits["train"])), ("test", count(splits["test"])),
            ("all", count(rows)), ("traps:hand", count(hand, "traps")),
            ("traps:test", count(splits["test"], "traps"))]
    print("\npositives per label (traps: mentions that must not count)\n")
    print(f"| label | " + " | ".join(c for c, _ in cols) + " |")
    print("|---|" + "---:|" * len(cols))
    for l in onto:
        print(f"| {l} | " + " | ".join(str(c[l]) for _, c in cols) + " |")
    print(f"| **total** | " + " | ".join(str(sum(c.values())) for _, c in cols) + " |")

    for name, rs in (("train", splits["train"]), ("test", splits["test"])):
        sizes = Counter(len(r["labels"]) for r in rs)
        print(f"\n{name}: label-set sizes " + ", ".join(f"{k}: {sizes[k]}" for k in sorted(sizes)))
    for field in ("style", "voice"):
        for name, rs in (("hand-written train", hand_tr), ("test", splits["test"])):
            c = Counter(r.get(field) for r in rs)
            print(f"\n{field}s, {name}: " + ", ".join(f"{k} {v}" for k, v in c.most_common()))
    for name, rs in (("hand-written train", hand_tr), ("test", splits["test"])):
        c = count(rs, "tags")
        print(f"\ntags, {name}: " + ", ".join(f"{k} {v}" for k, v in c.most_common()))


if __name__ == "__main__":
    main()
