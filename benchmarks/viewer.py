"""Viewer benchmark: first render of a 100k-triangle Draco asset after navigation, and frame
times, in headless Chromium (software rendering here) on the WebGPU and WebGL2 paths.

Starts a real gateway and worker on a temporary data dir, stores the asset made by the
project's export, then opens `/?asset=ID` in a fresh browser profile per run and reads
`window.viewerStats.firstRenderMs` (ms from navigation start to the first frame drawn, GPU
work finished). Prints JSON.

    .venv/bin/python benchmarks/viewer.py [--runs 5] [--frames 60] [--backends webgpu,webgl2]

Wall times depend on the machine's load (the JSON gives the load average); the CPU time the
browser and gateway spend from navigation to the first frame does not.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.io.gltf_io import encode_glb  # noqa: E402
from tests.web.harness import bumpy_torus, live_gateway, viewer_page, wait_state  # noqa: E402

TARGET_FIRST_RENDER_MS = 1500.0


def _summary(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {"median": round(statistics.median(ordered), 1), "min": round(ordered[0], 1),
            "max": round(ordered[-1], 1),
            "p95": round(ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))], 1)}


def _cpu_s_of_descendants(skip: str = "-m workers") -> float:
    """CPU seconds used so far by this process's descendants (browser, driver, gateway), less
    those whose command line holds `skip` (the idle worker polling its broker), with theirs."""
    tick = os.sysconf("SC_CLK_TCK")
    stats: dict[int, tuple[int, float, str]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        cpu_s = (int(fields[11]) + int(fields[12])) / tick  # utime + stime
        stats[int(entry.name)] = (int(fields[1]), cpu_s, cmdline)
    total, parents = 0.0, {os.getpid()}
    while True:
        children = {pid for pid, (ppid, _, cmd) in stats.items()
                    if ppid in parents and pid not in parents and skip not in cmd}
        if not children:
            return total
        total += sum(stats[pid][1] for pid in children)
        parents |= children


def _marks(page: Any) -> dict[str, float]:
    """The page's timing marks and when its big downloads started and ended (ms)."""
    entries = page.evaluate("performance.getEntriesByType('mark').map(m => [m.name, m.startTime])")
    marks = {name.removeprefix("vm:"): round(start, 1) for name, start in entries}
    loads = page.evaluate("performance.getEntriesByType('resource').map("
                          "r => [r.name.split('/').pop(), r.startTime, r.responseEnd])")
    for name, start, end in loads:
        if name in ("mesh.glb", "three.webgpu.js", "draco_decoder.wasm"):
            marks[f"{name} fetch"] = round(start, 1)
            marks[f"{name} loaded"] = round(end, 1)
    return dict(sorted(marks.items(), key=lambda item: item[1]))


def measure(playwright: Any, url: str, backend: str, runs: int, frames: int) -> dict[str, Any]:
    first, wall, decode, cpu, marks = [], [], [], [], []
    frame_ms: list[float] = []
    stats: dict[str, Any] = {}
    for run in range(runs):
        with viewer_page(playwright, backend) as (page, log):
            cpu_before, started = _cpu_s_of_descendants(), time.perf_counter()
            page.goto(url)
            state = wait_state(page, 60_000)
            wall.append((time.perf_counter() - started) * 1000)
            cpu.append((_cpu_s_of_descendants() - cpu_before) * 1000)
            if state != "ready":
                raise RuntimeError(f"{backend}: page state {state}: {page.inner_text('#message')}")
            stats = page.evaluate("window.viewerStats")
            if stats["backend"] != backend:
                raise RuntimeError(f"asked for {backend}, the page runs {stats['backend']}")
            first.append(stats["firstRenderMs"])
            decode.append(stats["decodeMs"])
            marks.append(_marks(page))
            if run == runs - 1 and frames:
                frame_ms = page.evaluate(f"window.volumesh.viewer.measureFrames({frames})")
            if log.errors():
                raise RuntimeError(f"{backend}: console errors {log.errors()}")
    return {
        "backend": backend,
        "triangles": stats["triangles"],
        "bytes": stats["bytes"],
        "runs": runs,
        "first_render_ms": _summary(first),
        "goto_to_ready_wall_ms": _summary(wall),
        "load_and_decode_ms": _summary(decode),
        # CPU the browser, driver and gateway spent from navigation to ready, all cores: a
        # figure that does not depend on what else the machine runs (wall time does).
        "cpu_ms_navigation_to_ready": _summary(cpu),
        "marks_ms_of_median_run": marks[sorted(range(runs), key=lambda i: first[i])[runs // 2]],
        "frame_ms": _summary(frame_ms) if frame_ms else None,
        "fps_from_median_frame": round(1000 / statistics.median(frame_ms), 1) if frame_ms else None,
        "meets_first_render_target": statistics.median(first) <= TARGET_FIRST_RENDER_MS,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--backends", default="webgpu,webgl2")
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    mesh = bumpy_torus()  # 100,000 triangles with vertex colours
    glb = encode_glb(mesh)
    with tempfile.TemporaryDirectory(prefix="volumesh-bench-") as tmp, \
            live_gateway(Path(tmp)) as gateway, sync_playwright() as playwright:
        asset = gateway.store_asset(glb, {"mesh": {"triangles": mesh.face_count}})
        url = f"{gateway.url}/?asset={asset}"
        results = [measure(playwright, url, backend, args.runs, args.frames)
                   for backend in args.backends.split(",")]
    print(json.dumps({
        "benchmark": "viewer first render, headless Chromium (SwiftShader software rendering)",
        "cpu_cores": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "asset": {"triangles": mesh.face_count, "glb_bytes": len(glb), "draco": True},
        "target_first_render_ms": TARGET_FIRST_RENDER_MS,
        "results": results,
    }, indent=1))


if __name__ == "__main__":
    main()
