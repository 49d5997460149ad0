#!/usr/bin/env python3
"""Writes the suite's **stress** part to target/suite-stress (not committed): six generated
worlds whose reporters break the assumptions the other sets share.

The dev, dev2 and held-out sets all have reporters that err independently and symmetrically
(or are real classifiers). A method tuned on them can still fail where that does not hold, so
these worlds are built to differ from all of them, and are scored like a third development
instance (`scripts/fusion-suite --part stress`):

- `five`: five reporters, 90/85/80/70/60% right per label, the worst absent from 10% of rounds;
- `asym`: errors of one kind each: `cons` misses 45% of true labels and almost never invents
  one, `hallu` invents 20% of false labels and rarely misses, `mid` a bit of both;
- `adversary`: `good` 85%, `ok` 75% and `anti` 35% right (worse than chance: its reports carry
  information, inverted; the vote is misled by it);
- `copycats`: `twin1` and `twin2` share the same errors (70% right, the same flips), `solo` is
  85% right: agreement says the twins are right, labels say otherwise;
- `sparse`: rarer labels (a scene's typical labels true 10-35% of the time);
- `scenehallu`: `p` hallucinates in scenes 0-2 only, `q` in scenes 3-5 only, `r` is 80% right
  everywhere.

Scenes, contexts and truths come as in make_suite.py's generated sets (six scenes, 16-d
contexts, 14 driving labels, 1,000 rounds); Python's `random` only, so the files are the same
on every machine.

    python3 tests/data/suite/make_stress.py
    scripts/fusion-suite --part stress --seeds 5 --jobs 2   # writes them first when missing
"""
import json
import os
import random
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
OUT = os.path.join(ROOT, "target", "suite-stress")
# make_suite.py's label set (not imported: that module needs numpy and scikit-learn).
DRIVING = ["turn_left", "turn_right", "brake", "accelerate", "stop", "traffic_light_ahead",
           "junction_ahead", "pedestrian_crossing_ahead", "merge", "maintain_safe_distance",
           "check_blind_spot", "adjust_speed_due_to_weather", "yield_to_traffic",
           "drive_as_normal"]
N_ROUNDS = 1000


def flips(p):
    """Each label's truth flipped with probability p."""
    return lambda scene, truth, rng, shared: [b != (rng.random() < p) for b in truth]


def one_sided(miss, false_alarm):
    """A true label missed with probability `miss`, a false one reported with `false_alarm`."""
    return lambda scene, truth, rng, shared: [
        (rng.random() >= miss) if b else (rng.random() < false_alarm) for b in truth]


def twin(p):
    """Flips drawn from the round's shared uniforms: every twin makes the same errors."""
    return lambda scene, truth, rng, shared: [b != (u < p) for b, u in zip(truth, shared)]


def by_scene(bad_scenes, good, bad):
    return lambda scene, truth, rng, shared: (bad if scene in bad_scenes else good)(
        scene, truth, rng, shared)


# name -> (seed, reporters [(name, report fn)], absent {name: share}, typical-label rate range)
WORLDS = {
    "five": (20261701, [(n, flips(p)) for n, p in
                        zip("abcde", (0.10, 0.15, 0.20, 0.30, 0.40))], {"e": 0.10}, (0.45, 0.85)),
    "asym": (20261702, [("cons", one_sided(0.45, 0.01)), ("hallu", one_sided(0.05, 0.20)),
                        ("mid", one_sided(0.25, 0.08))], {}, (0.45, 0.85)),
    "adversary": (20261703, [("good", flips(0.15)), ("ok", flips(0.25)),
                             ("anti", flips(0.65))], {}, (0.45, 0.85)),
    "copycats": (20261704, [("twin1", twin(0.30)), ("twin2", twin(0.30)),
                            ("solo", flips(0.15))], {}, (0.45, 0.85)),
    "sparse": (20261705, [("x", flips(0.08)), ("y", flips(0.15)), ("z", flips(0.25))], {},
               (0.10, 0.35)),
    "scenehallu": (20261706, [
        ("p", by_scene({0, 1, 2}, one_sided(0.10, 0.02), one_sided(0.10, 0.30))),
        ("q", by_scene({3, 4, 5}, one_sided(0.10, 0.02), one_sided(0.10, 0.30))),
        ("r", flips(0.20))], {}, (0.45, 0.85)),
}


def world(name, seed, reporters, absent, typical, n_scenes=6, dim=16, noise=0.8):
    rng = random.Random(seed)
    centres = [[rng.gauss(0, 1) for _ in range(dim)] for _ in range(n_scenes)]
    rates = []
    for _ in range(n_scenes):
        typ = set(rng.sample(range(len(DRIVING)), 4))
        rates.append([rng.uniform(*typical) if k in typ else rng.uniform(0.02, 0.10)
                      for k in range(len(DRIVING))])
    rounds = []
    for t in range(N_ROUNDS):
        s = rng.randrange(n_scenes)
        ctx = [c + noise * rng.gauss(0, 1) for c in centres[s]]
        truth = [rng.random() < p for p in rates[s]]
        shared = [rng.random() for _ in truth]
        reports = {}
        for rep, fn in reporters:
            # Every reporter's bits are drawn even when it is absent (the others stay put).
            bits = fn(s, truth, rng, shared)
            if rep in absent and rng.random() < absent[rep]:
                continue
            reports[rep] = [DRIVING[k] for k, b in enumerate(bits) if b]
        rounds.append({"id": f"{name}-stress-{t:05d}",
                       "context": [0.0 if round(v, 4) == 0 else round(v, 4) for v in ctx],
                       "reports": reports,
                       "truth": [DRIVING[k] for k, b in enumerate(truth) if b]})
    return rounds


def main():
    os.makedirs(OUT, exist_ok=True)
    for name, (seed, reporters, absent, typical) in WORLDS.items():
        path = os.path.join(OUT, f"{name}.stress.jsonl")
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            for r in world(name, seed, reporters, absent, typical):
                f.write(json.dumps(r, separators=(",", ":")) + "\n")
    print(f"wrote {OUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
