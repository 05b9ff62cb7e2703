"""The device runs' JSON lines (`ab.sh`'s ab.jsonl, `run.sh`'s perf.jsonl) summed up: for each
variant (code, mesh, method, warm-up, networks, kernel pieces, light remesh rounds,
self-check, profiled) the runs' seconds, min / median / max, and the median of each stage and
of the light remesh's wait for its kernel; prints JSON.

    python3 benchmarks/device/summary.py ab.jsonl
"""

from __future__ import annotations

import json
import statistics
import sys
from collections import defaultdict

VARIANT_KEYS = ("code", "mesh", "method", "warm_up", "networks", "kernel_pieces",
                "remesh_iterations", "self_checked", "profiled")


def summary(lines: list[str]) -> list[dict]:
    """One entry per variant, in the order each first appears."""
    runs: dict[tuple, list[dict]] = defaultdict(list)
    for line in lines:
        if line.strip().startswith("{"):
            run = json.loads(line)
            runs[tuple(run.get(key) for key in VARIANT_KEYS)].append(run)
    out = []
    for variant, group in runs.items():
        seconds = [r["seconds"] for r in group]
        stages = {stage: round(statistics.median(r["stage_seconds"].get(stage, 0.0)
                                                 for r in group), 3)
                  for stage in group[0]["stage_seconds"]}
        waits = [r["kernel_wait_seconds"] for r in group
                 if r.get("kernel_wait_seconds") is not None]
        out.append({**dict(zip(VARIANT_KEYS, variant, strict=True)), "runs": len(group),
                    "seconds": [round(min(seconds), 3), round(statistics.median(seconds), 3),
                                round(max(seconds), 3)],
                    "stage_medians": stages,
                    "kernel_wait_median": round(statistics.median(waits), 3) if waits else None})
    return out


if __name__ == "__main__":
    with open(sys.argv[1]) as f:
        print(json.dumps(summary(f.readlines()), indent=1))
