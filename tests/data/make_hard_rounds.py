#!/usr/bin/env python3
"""Generates the hard rounds files (PAPER-METHOD.md §8, JSON Lines) for the learning-curve and drift
targets of issue 9. Deterministic: the same command writes the same bytes.

    python3 tests/data/make_hard_rounds.py hard  > tests/data/rounds_hard.jsonl
    python3 tests/data/make_hard_rounds.py drift > tests/data/rounds_drift.jsonl
    python3 tests/data/make_hard_rounds.py hard 7 > /tmp/hard-7.jsonl   # another world, same shape

`rounds.jsonl` (make_rounds.py) is easy: the paper method gets Hamming 0.057 on it. Real data are
much harder, and a method tuned on an easy file fails there. The `hard` file is shaped after the
statistics of a real 14-label set with three real classifiers as reporters (1,813 rounds, 1,269
history / 544 scored; there the paper method gets Hamming 0.196 / micro-F1 0.668 with every round
labelled, majority vote 0.211 / 0.589, the best reporter alone ~0.69 micro-F1, and the paper's
posteriors are under-confident, ECE 0.147):

- imbalanced label frequencies, from ~40% of rounds down to three rare labels under 3%;
- eight scenes whose contexts are noisy: every context is its scene's sub-centre plus heavy
  noise, and one round in six carries the context of another scene (the embedding was fooled), so
  neighbours are only partly informative;
- three reporters of different quality with scene-dependent strengths and label biases; the best
  one is not the best everywhere;
- correlated errors: a latent "subtle" flag per true label lowers every reporter's recall at once,
  two reporters share a confusion (junction -> traffic light), two share hallucination bursts;
- about 4% of rounds miss one reporter.

The `drift` file uses the same world with another seed, 1,800 rounds, and swaps the best
reporter (same name) at round 900 for a model that hallucinates: it reports each label with a
fixed probability whatever the truth, i.e. chance level. `DRIFT_AT` below is the swap round.
"""
import json
import math
import random
import sys

LABELS = ["turn_left", "turn_right", "brake", "accelerate", "stop", "traffic_light_ahead",
          "junction_ahead", "pedestrian_crossing_ahead", "merge", "maintain_safe_distance",
          "check_blind_spot", "adjust_speed_due_to_weather", "yield_to_traffic", "drive_as_normal"]

# Per scene: label -> probability that it is true (absent labels: BACKGROUND).
BACKGROUND = 0.07
RARE = {"merge", "adjust_speed_due_to_weather", "check_blind_spot"}
RARE_BACKGROUND = 0.004
RATE_SCALE = 1.45
SCENES = {
    "city_intersection": {"traffic_light_ahead": 0.85, "junction_ahead": 0.8, "stop": 0.45,
                          "brake": 0.6, "turn_left": 0.25, "turn_right": 0.25,
                          "pedestrian_crossing_ahead": 0.3, "accelerate": 0.15},
    "suburban_junction": {"junction_ahead": 0.85, "yield_to_traffic": 0.55, "turn_left": 0.3,
                          "turn_right": 0.3, "brake": 0.45, "stop": 0.2,
                          "check_blind_spot": 0.08},
    "highway_cruise": {"maintain_safe_distance": 0.75, "drive_as_normal": 0.65,
                       "accelerate": 0.3, "brake": 0.15},
    "highway_merge": {"merge": 0.35, "maintain_safe_distance": 0.6, "accelerate": 0.45,
                      "check_blind_spot": 0.3, "yield_to_traffic": 0.25},
    "stop_and_go": {"brake": 0.8, "maintain_safe_distance": 0.7, "stop": 0.5, "accelerate": 0.35,
                    "drive_as_normal": 0.2},
    "pedestrian_zone": {"pedestrian_crossing_ahead": 0.8, "brake": 0.65, "stop": 0.4,
                        "yield_to_traffic": 0.35},
    "rain_night": {"adjust_speed_due_to_weather": 0.3, "maintain_safe_distance": 0.6,
                   "brake": 0.4, "drive_as_normal": 0.35},
    "open_road": {"drive_as_normal": 0.8, "accelerate": 0.3, "maintain_safe_distance": 0.3},
}
SCENE_WEIGHTS = {"city_intersection": 1.2, "suburban_junction": 1.0, "highway_cruise": 1.3,
                 "highway_merge": 0.45, "stop_and_go": 0.9, "pedestrian_zone": 0.7,
                 "rain_night": 0.4, "open_road": 1.1}

# Per reporter: base (tpr, fpr); per-scene overrides; per-label (tpr, fpr) multipliers/overrides.
REPORTERS = {
    # The best reporter alone: decent recall and precision; blind in rain and to rare manoeuvres.
    "vlaad": {"base": (0.82, 0.11),
              "scene": {"rain_night": (0.40, 0.12), "highway_merge": (0.50, 0.10),
                        "stop_and_go": (0.55, 0.20)},
              "label": {"merge": (0.35, 0.02), "adjust_speed_due_to_weather": (0.3, 0.02),
                        "check_blind_spot": (0.35, 0.03)}},
    # Liberal: high recall, many false positives (poor alone, informative when fused); good in
    # rain and at pedestrians; over-reports braking.
    "videollama2": {"base": (0.90, 0.30),
                    "scene": {"rain_night": (0.90, 0.12), "pedestrian_zone": (0.90, 0.15)},
                    "label": {"brake": (0.9, 0.55), "drive_as_normal": (0.8, 0.4)}},
    # Conservative: precise but misses a lot; strong on highways; hallucinates traffic lights at
    # junctions.
    "videollava": {"base": (0.45, 0.05),
                   "scene": {"highway_cruise": (0.80, 0.04), "highway_merge": (0.80, 0.04),
                             "open_road": (0.75, 0.05)},
                   "label": {"traffic_light_ahead": (0.5, 0.25), "turn_left": (0.3, 0.06),
                             "turn_right": (0.3, 0.06)}},
}

D = 96
SUBTLE = 0.30          # share of true labels that are hard to see (recall x SUBTLE_FACTOR)
SUBTLE_FACTOR = 0.45
FOOLED = 1 / 6         # share of rounds whose context belongs to another scene
BURST = 0.20           # share of rounds with a shared hallucination (videollama2 + videollava)
MISSING = 0.04
WEAK_BLIND = 0.3       # share of true labels that both weaker reporters miss together
WEAK_BLIND_FACTOR = 0.25
NOISE = 1.8           # per-coordinate context noise (the scene centres have unit scale)

DRIFT_AT = 900


def main():
    mode = sys.argv[1] if len(sys.argv) > 1 else "hard"
    if mode not in ("hard", "drift"):
        sys.exit("usage: make_hard_rounds.py hard|drift [SEED]")
    seed, n_rounds = (20261201, 1813) if mode == "hard" else (20261202, 1800)
    # Another seed draws another world of the same shape (for robustness checks, not committed).
    if len(sys.argv) > 2:
        seed = int(sys.argv[2])
    rng = random.Random(seed)
    names = list(SCENES)
    # Two sub-centres per scene around a scene centre: scenes are clusters with inner structure.
    centres = {}
    for s in names:
        c = [rng.gauss(0, 1) for _ in range(D)]
        centres[s] = [[ci + 0.6 * rng.gauss(0, 1) for ci in c] for _ in range(2)]
    slow = [rng.gauss(0, 1) for _ in range(D)]
    weights = [SCENE_WEIGHTS[s] for s in names]
    for t in range(n_rounds):
        scene = rng.choices(names, weights=weights)[0]
        shown = scene if rng.random() >= FOOLED else rng.choice(names)
        sub = rng.choice(centres[shown])
        ctx = [c + NOISE * rng.gauss(0, 1) + 0.3 * math.sin(t / 150) * s
               for c, s in zip(sub, slow)]
        rates = SCENES[scene]
        truth = [lab for lab in LABELS
                 if rng.random() < min(0.95, RATE_SCALE * rates.get(
                     lab, RARE_BACKGROUND if lab in RARE else BACKGROUND))]
        subtle = {lab for lab in truth if rng.random() < SUBTLE}
        # Hidden from the two weaker reporters at once (same blind spot): correlated misses.
        hidden = {lab for lab in truth if rng.random() < WEAK_BLIND}
        burst = rng.choice(LABELS) if rng.random() < BURST else None
        missing = rng.choice(list(REPORTERS)) if rng.random() < MISSING else None
        reports = {}
        for name, spec in REPORTERS.items():
            if name == missing:
                continue
            drifted = mode == "drift" and name == "vlaad" and t >= DRIFT_AT
            tpr0, fpr0 = spec["scene"].get(scene, spec["base"])
            out = []
            for lab in LABELS:
                if drifted:
                    p = 0.22
                else:
                    tpr, fpr = spec["label"].get(lab, (tpr0, fpr0))
                    # A scene override keeps its strength on every label.
                    if scene in spec["scene"]:
                        tpr, fpr = (tpr + tpr0) / 2, (fpr + fpr0) / 2
                    if lab in truth:
                        p = tpr * (SUBTLE_FACTOR if lab in subtle else 1.0)
                        if lab in hidden and name in ("videollama2", "videollava"):
                            p *= WEAK_BLIND_FACTOR
                    else:
                        p = fpr
                        if (lab == "traffic_light_ahead" and "junction_ahead" in truth
                                and name in ("vlaad", "videollava")):
                            p = max(p, 0.35)
                    if burst == lab and name in ("videollama2", "videollava"):
                        p = max(p, 0.8)
                if rng.random() < p:
                    out.append(lab)
            reports[name] = out
        line = {"id": f"{mode}-{t:06d}", "context": [round(v, 3) for v in ctx],
                "reports": reports, "truth": truth}
        print(json.dumps(line, separators=(",", ":")))


if __name__ == "__main__":
    main()
