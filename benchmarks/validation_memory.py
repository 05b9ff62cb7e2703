"""The validation worker's memory bound: hostile captures are refused within seconds, and a
valid one holds one view at a time, so peak memory stays under the process's baseline plus
16 bytes per pixel of the cap, plus a little working memory for the decoders.

Builds, in a temporary folder, a valid small capture, a zip with a damaged member, a PNG bomb
(a 12000x12000 16-bit PNG with matching intrinsics) and a capture with images at the pixel cap;
runs the worker's validation (`open_capture` and every view read, `workers.captures.read_whole`)
on each in a fresh child process and prints one JSON object: outcome, message, seconds, peak
RSS (MB) per capture, with the bound.
    .venv/bin/python benchmarks/validation_memory.py [--uncapped]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import queue
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.hostile_captures import (  # noqa: E402
    bomb_capture_zip,
    capture_json,
    damaged_member_zip,
)
from tests.integration.services import make_capture_zip  # noqa: E402
from workers.settings import Settings  # noqa: E402

# Reading a view's colour holds its float depth (4 B/px), the colour file (at most twice its
# decoded size, 6 B/px), the decoded colour (3 B/px, turned to RGB in place) and OpenCV's PNG
# decoder's own copy of it (3 B/px); the depth before it needs less (8 B/px).
BOUND_BYTES_PER_PIXEL = 16
WORKING_BYTES = 16 * 1024 * 1024  # the decoders' row buffers and tables, the file's slack
LENGTH_SLACK_BYTES = 1024 * 1024  # what an image file may hold beyond twice its pixels
CHILD_TIMEOUT_S = 300.0


def _peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss, not inherited from the
    parent across fork and exec), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _validate(path: str, max_image_pixels: int, results: Any) -> None:
    """Child process: the worker's imports, then its validation of one capture."""
    import pipeline.io.capture_io  # noqa: F401  (a worker process loads it before any task)
    from workers.captures import capture_limits, read_whole

    settings = Settings(max_image_pixels=max_image_pixels)
    baseline_mb = _peak_rss_mb()
    started = time.perf_counter()
    try:
        cameras, frames = read_whole(Path(path), capture_limits(settings))
        outcome, message = "accepted", f"{cameras} cameras, {len(frames)} frames"
    except ValueError as exc:
        outcome, message = "refused", str(exc)
    results.put({"outcome": outcome, "message": message,
                 "seconds": round(time.perf_counter() - started, 3),
                 "baseline_rss_mb": round(baseline_mb, 1),
                 "peak_rss_mb": round(_peak_rss_mb(), 1)})


def run_child(path: Path, max_image_pixels: int) -> dict[str, Any]:
    """Validates ``path`` in a fresh (spawned) process, so each peak is that capture's own."""
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    child = context.Process(target=_validate, args=(str(path), max_image_pixels, results))
    child.start()
    try:
        return dict(results.get(timeout=CHILD_TIMEOUT_S))
    except queue.Empty:
        child.kill()
        return {"outcome": "died", "message": f"no answer; exit code {child.exitcode}"}
    finally:
        child.join(10)


def _at_cap_capture(folder: Path, max_image_pixels: int) -> Path:
    """One camera whose depth and colour images are as large as the cap allows, in files as
    long as the reader accepts (noise, padded): the worst case the reader takes."""
    import cv2
    import numpy as np

    side = int(max_image_pixels ** 0.5)
    rng = np.random.default_rng(0)
    depth = rng.integers(500, 4000, (side, side), dtype=np.uint16)
    colour = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)
    path = folder / "at-cap.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("capture.json", capture_json(side, side))
        for name, image in (("depth", depth), ("color", colour)):
            png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes()
            longest = 2 * image.nbytes + LENGTH_SLACK_BYTES - 64
            # Bytes after the image's end: decoders ignore them, the reader still holds them.
            archive.writestr(f"cam0/{name}/000000.png", png + bytes(longest - len(png)))
    return path


def build(folder: Path, max_image_pixels: int) -> dict[str, Path]:
    """The captures, as zips in ``folder``."""
    valid = make_capture_zip(folder, cameras=8, width=320, height=288)
    with zipfile.ZipFile(valid) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    damaged = folder / "damaged-member.zip"
    damaged.write_bytes(damaged_member_zip(entries, "cam3/depth/000000.png", "deflate"))
    bomb = folder / "png-bomb.zip"
    bomb.write_bytes(bomb_capture_zip())
    return {"valid 8x320x288": valid, "damaged member": damaged, "png bomb 12000x12000": bomb,
            "images at the pixel cap, files at the length limit":
                _at_cap_capture(folder, max_image_pixels)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uncapped", action="store_true",
                        help="also read the PNG bomb with the cap lifted (needs about 1 GB)")
    args = parser.parse_args()
    cap = Settings().max_image_pixels
    report: dict[str, Any] = {"max_image_pixels": cap, "captures": {},
                              "load_average": round(os.getloadavg()[0], 2)}
    with tempfile.TemporaryDirectory() as tmp:
        paths = build(Path(tmp), cap)
        for name, path in paths.items():
            result = run_child(path, cap)
            result["zip_bytes"] = path.stat().st_size
            report["captures"][name] = result
        if args.uncapped:
            report["captures"]["png bomb, cap lifted"] = run_child(
                paths["png bomb 12000x12000"], 10**9)
    baseline = max(r.get("baseline_rss_mb", 0.0) for r in report["captures"].values())
    report["bound_rss_mb"] = round(
        baseline + (BOUND_BYTES_PER_PIXEL * cap + WORKING_BYTES) / 2**20, 1)
    report["within_bound"] = all(r.get("peak_rss_mb", 0.0) <= report["bound_rss_mb"]
                                 for name, r in report["captures"].items()
                                 if name != "png bomb, cap lifted")
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
