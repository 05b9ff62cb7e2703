"""`volumesh import-mkv` speed: eight 10 s Azure Kinect recordings to one capture.

Usage: .venv/bin/python benchmarks/import_mkv.py [--cameras 8] [--seconds 10] [--zip]
       [--workdir DIR] [--out-parent DIR]
Writes, untimed, one recording per device as k4arecorder lays them out (tests/k4a_recordings):
NFOV_UNBINNED 640x576 depth and IR, 1280x720 MJPG colour, 30 fps, a master and subordinates
160 us apart; depth a noisy surface with holes (so that its PNGs cost what real depth's do),
colour noisy JPEGs of real-world size. Then times the command itself, `python -m app import-mkv
... --out OUT`, in a child process, and prints one JSON object: wall seconds per recorded
second (target <= 1, real time), its CPU seconds per recorded second (two cores reach real time
only where this is below 2), the command's start-up alone (`--help`, untimed), the child's peak
memory, sizes and the load average before and after: the machine's other work takes cores from
the run. The recordings are read from the page cache, as right after they were copied or
written. The capture goes to a new folder, removed afterwards: on ext4, files created where
thousands were deleted in the last minutes cost several times the CPU (the inode allocator
skips recently freed inodes one by one), so a rerun that deleted the previous capture in its
place measures the file system, not the command; keep --out-parent away from such places.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.k4a_recordings import rig_recordings  # noqa: E402

# The command as `python -m app` runs it, reporting its own peak memory when it ends (VmHWM:
# unlike ru_maxrss, not inherited from this process, which holds the synthesis).
_COMMAND = ("import atexit, sys\n"
            "def peak():\n"
            "    status = open('/proc/self/status').read()\n"
            "    print('VmHWM', status.split('VmHWM:')[1].split()[0], file=sys.stderr)\n"
            "atexit.register(peak)\n"
            "from app.cli import main\n"
            "main()\n")
def _startup_s() -> float:
    """Wall seconds of the command doing nothing (`import-mkv --help`): the part of the timed
    run that does not depend on the recordings."""
    started = time.perf_counter()
    subprocess.run([sys.executable, "-c", _COMMAND, "import-mkv", "--help"], cwd=ROOT,
                   capture_output=True, check=True)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--seconds", type=int, default=10)
    parser.add_argument("--zip", action="store_true", help="write OUT as a .zip")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="keep the recordings here (reused when present)")
    parser.add_argument("--out-parent", type=Path, default=None,
                        help="write the capture in a new folder here, removed afterwards "
                        "(default: the system's temporary folder)")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="volumesh-mkv-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    paths = sorted(workdir.glob("device*.mkv"))[: args.cameras]
    if len(paths) < args.cameras:
        paths = rig_recordings(workdir, args.cameras, args.seconds)
    synth_s = time.perf_counter() - started
    out_parent = Path(tempfile.mkdtemp(prefix="volumesh-mkv-out-", dir=args.out_parent))
    out = out_parent / ("capture.zip" if args.zip else "capture")
    startup_s = _startup_s()
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-c", _COMMAND, "import-mkv", *map(str, paths),
                             "--out", str(out)], cwd=ROOT, capture_output=True, text=True)
    wall_s = time.perf_counter() - started
    child = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (child.ru_utime + child.ru_stime) - (before.ru_utime + before.ru_stime)
    if result.returncode != 0:
        raise SystemExit(result.stderr)
    peak_kb = int(result.stderr.rsplit("VmHWM", 1)[1].split()[0])
    out_bytes = (out.stat().st_size if out.is_file()
                 else sum(p.stat().st_size for p in out.rglob("*") if p.is_file()))
    print(json.dumps({
        "cameras": args.cameras, "recorded_s": args.seconds, "frames_per_camera": 30 * args.seconds,
        "input_mb": round(sum(p.stat().st_size for p in paths) / 2**20),
        "output_mb": round(out_bytes / 2**20), "zip": args.zip,
        "wall_s": round(wall_s, 2), "cpu_s": round(cpu_s, 2),
        "seconds_per_recorded_second": round(wall_s / args.seconds, 3),
        "target_seconds_per_recorded_second": 1.0,
        "cpu_seconds_per_recorded_second": round(cpu_s / args.seconds, 3),
        "startup_s": round(startup_s, 2),
        "peak_rss_mb": round(peak_kb / 1024),
        "synth_s": round(synth_s, 1), "summary": result.stdout.strip().splitlines()[0],
        "load_average_before": round(load, 2),
        "load_average_after": round(os.getloadavg()[0], 2), "cpus": os.cpu_count(),
        "python": platform.python_version(),
    }, indent=1))
    shutil.rmtree(out_parent, ignore_errors=True)
    if args.workdir is None:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
