#!/usr/bin/env python3
"""Writes a second development instance of every suite set to target/suite-dev2 (not committed).

Tuning on one dev instance of each set can fit that instance's accidents. This one shares
nothing with the held-out part either:

- generated sets (hard, drift, near-oracle, specialists): other seeds of the same generators;
- real sets (yeast, digits, segment): the dev rows themselves in another order (seed 7), so
  that other rounds are history and others are scored; no held-out row and no new reporter;
- yeast-drift: its dev rows shuffled before and after the drift point separately (the drift
  stays at round 350).

    python3 tests/data/suite/make_dev2.py      # needs make_suite.py's numpy and scikit-learn
    scripts/fusion-suite --part dev2 --jobs 2
"""
import os
import random
import shutil
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
OUT = os.path.join(ROOT, "target", "suite-dev2")
sys.path.insert(0, HERE)
import make_suite as M  # noqa: E402

SEEDS = {"near-oracle": 20261411, "specialists": 20261511, "hard": 20261311, "drift": 20261312}
SHUFFLE_SEED = 7


def main():
    os.makedirs(OUT, exist_ok=True)
    for sname, flip, miss in (("near-oracle", M.NEAR_ORACLE, ("weak", 0.05)),
                              ("specialists", M.SPECIALISTS, ("gamma", 0.03))):
        rounds = M.synth_rounds(sname, "dev2", SEEDS[sname], 1000, flip, missing=miss)
        M.write_rounds(os.path.join(OUT, f"{sname}.dev2.jsonl"), rounds)
    for sname in ("hard", "drift"):
        out = subprocess.run([sys.executable, os.path.join(HERE, "..", "make_hard_rounds.py"),
                              sname, str(SEEDS[sname])], check=True, capture_output=True).stdout
        with open(os.path.join(OUT, f"{sname}.dev2.jsonl"), "wb") as f:
            f.write(out)
    rng = random.Random(SHUFFLE_SEED)
    for sname in ("yeast", "digits", "segment", "yeast-drift"):
        with open(os.path.join(HERE, f"{sname}.dev.jsonl"), encoding="utf-8") as f:
            lines = f.read().splitlines()
        if sname == "yeast-drift":
            before, after = lines[:M.YEAST_DRIFT_AT], lines[M.YEAST_DRIFT_AT:]
            rng.shuffle(before)
            rng.shuffle(after)
            lines = before + after
        else:
            rng.shuffle(lines)
        with open(os.path.join(OUT, f"{sname}.dev2.jsonl"), "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")
        shutil.copy(os.path.join(HERE, f"{sname}.toml"), os.path.join(OUT, f"{sname}.toml"))
    print(f"wrote {OUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
