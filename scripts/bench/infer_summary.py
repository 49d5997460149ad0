"""Medians of /v1/infer's per-stage timings (`timings_ms`) over the JSON responses given, for
`scripts/bench-infer.sh`. The first response is a warm-up and is left out."""
import json
import statistics
import sys

runs = [json.load(open(p)) for p in sys.argv[1:]][1:]
stages = {}
for r in runs:
    for clip in r.get("clips", [r]):
        for k, v in clip["timings_ms"].items():
            stages.setdefault(k, []).append(v)
local = ["decode", "embed", "label", "fuse"]
total = [sum(c["timings_ms"].get(s, 0.0) for s in local) for r in runs for c in r.get("clips", [r])]
print(f"{len(runs)} timed requests (one clip each); medians in ms:")
for k, v in stages.items():
    print(f"  {k:<10} {statistics.median(v):8.1f}   (min {min(v):.1f}, max {max(v):.1f})")
print(f"  {'decode+embed+label+fuse':<10} {statistics.median(total):8.1f}   (target <= 600)")
