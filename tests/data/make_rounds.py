#!/usr/bin/env python3
"""Generates tests/data/rounds.jsonl: a realistic, deterministic rounds file (PAPER-METHOD.md §8).

Six driving scenes give the contexts cluster structure (a 64-d "scene embedding": scene centre +
noise, unit-normalised by the engine). Ground truth comes from per-scene label rates. Three
reporters named like the paper's models differ in quality and label bias, and their quality
depends on the scene, so context-aware reliabilities matter:

- vlaad: precise on intersections and free road, poor in rain, hallucinates traffic lights at
  unsignalised junctions.
- videollama2: balanced; best on pedestrians and rain.
- videollava: weak overall, over-reports "drive_as_normal" and "brake", but strong on highway merges.

vlaad and videollava share a hallucination source (they err together on some rounds), which the
correlation guardrail should catch. About 5% of rounds miss one reporter (a failed model) and 10%
carry no truth (unlabelled). Run: python3 tests/data/make_rounds.py > tests/data/rounds.jsonl
"""
import json
import math
import random

LABELS = ["turn_left", "turn_right", "brake", "accelerate", "stop", "traffic_light_ahead",
          "junction_ahead", "pedestrian_crossing_ahead", "merge", "maintain_safe_distance",
          "check_blind_spot", "adjust_speed_due_to_weather", "yield_to_traffic", "drive_as_normal"]

# Per scene: label -> probability that it is true.
SCENES = {
    "signalised_intersection": {"traffic_light_ahead": 0.95, "junction_ahead": 0.9, "stop": 0.45,
                                "brake": 0.55, "turn_left": 0.25, "turn_right": 0.25,
                                "accelerate": 0.15},
    "highway_merge": {"merge": 0.9, "check_blind_spot": 0.7, "accelerate": 0.55,
                      "maintain_safe_distance": 0.6, "yield_to_traffic": 0.2},
    "pedestrian_crossing": {"pedestrian_crossing_ahead": 0.95, "brake": 0.7, "stop": 0.5,
                            "yield_to_traffic": 0.4},
    "rain": {"adjust_speed_due_to_weather": 0.9, "maintain_safe_distance": 0.7, "brake": 0.35,
             "drive_as_normal": 0.1},
    "free_road": {"drive_as_normal": 0.85, "accelerate": 0.3, "maintain_safe_distance": 0.25},
    "unsignalised_junction": {"junction_ahead": 0.95, "yield_to_traffic": 0.7,
                              "turn_left": 0.35, "turn_right": 0.35, "check_blind_spot": 0.5,
                              "brake": 0.3},
}

# Per reporter: default (tpr, fpr), per-scene overrides, and label biases (extra false positives).
REPORTERS = {
    "vlaad": {"base": (0.80, 0.03),
              "scene": {"rain": (0.40, 0.12), "free_road": (0.9, 0.02)},
              "bias": {("unsignalised_junction", "traffic_light_ahead"): 0.55}},
    "videollama2": {"base": (0.70, 0.05),
                    "scene": {"pedestrian_crossing": (0.9, 0.03), "rain": (0.85, 0.03)},
                    "bias": {}},
    "videollava": {"base": (0.50, 0.08),
                   "scene": {"highway_merge": (0.9, 0.03)},
                   "bias": {(None, "drive_as_normal"): 0.3, (None, "brake"): 0.2}},
}

D = 64
N_ROUNDS = 900


def main():
    rng = random.Random(20261122)
    names = list(SCENES)
    centres = {s: [rng.gauss(0, 1) for _ in range(D)] for s in names}
    drift = [rng.gauss(0, 1) for _ in range(D)]
    for t in range(N_ROUNDS):
        # Scene mix shifts over time (more rain late in the file): reliabilities must track context.
        weights = [1, 1, 1, 0.6 + 1.2 * t / N_ROUNDS, 1, 1]
        scene = rng.choices(names, weights=weights)[0]
        ctx = [c + 0.55 * rng.gauss(0, 1) + 0.2 * math.sin(t / 90) * dr
               for c, dr in zip(centres[scene], drift)]
        truth = [lab for lab in LABELS if rng.random() < SCENES[scene].get(lab, 0.02)]
        shared_hallucination = rng.random() < 0.12
        hallucinated = rng.choice(LABELS)
        reports = {}
        missing = rng.choice(list(REPORTERS)) if rng.random() < 0.05 else None
        for name, spec in REPORTERS.items():
            if name == missing:
                continue
            tpr, fpr = spec["scene"].get(scene, spec["base"])
            out = []
            for lab in LABELS:
                p = tpr if lab in truth else fpr
                for (s, l), extra in spec["bias"].items():
                    if l == lab and (s is None or s == scene) and lab not in truth:
                        p = max(p, extra)
                if shared_hallucination and name in ("vlaad", "videollava") and lab == hallucinated:
                    p = 0.9
                if rng.random() < p:
                    out.append(lab)
            reports[name] = out
        line = {"id": f"r-{t:06d}", "context": [round(v, 5) for v in ctx], "reports": reports}
        if rng.random() < 0.9:
            line["truth"] = truth
        else:
            line["truth"] = None
        print(json.dumps(line, separators=(",", ":")))


if __name__ == "__main__":
    main()
