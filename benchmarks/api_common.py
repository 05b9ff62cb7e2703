"""Shared parts of the service benchmarks: a gateway (and workers) as real processes, a raw
keep-alive HTTP client light enough not to steal the server's two cores, and figures."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def service_env(**settings: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOLUMESH_")}
    env["PYTHONPATH"] = str(ROOT)
    env.update({f"VOLUMESH_{k.upper()}": v for k, v in settings.items()})
    return env


def wait_http(port: int, path: str = "/healthz", timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with (contextlib.suppress(OSError),
              socket.create_connection(("127.0.0.1", port), timeout=1) as sock):
            sock.sendall(f"GET {path} HTTP/1.1\r\nHost: b\r\nConnection: close\r\n\r\n"
                         .encode())
            if sock.recv(64).startswith(b"HTTP/1.1 200"):
                return
        time.sleep(0.1)
    raise TimeoutError(f"nothing answered {path} on port {port}")


@contextlib.contextmanager
def process(cmd: list[str], env: dict[str, str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def gateway_cmd(port: int, workers: int) -> list[str]:
    return [sys.executable, "-m", "uvicorn", "--factory", "app.main:app_from_env", "--host",
            "127.0.0.1", "--port", str(port), "--workers", str(workers), "--log-level",
            "warning", "--no-access-log"]


def worker_cmd(queues: str) -> list[str]:
    return [sys.executable, "-m", "workers", "--queues", queues, "--loglevel", "INFO"]


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


async def _client(port: int, path: str, key: str, deadline: float, latencies: list[float],
                  statuses: dict[int, int], interval_s: float | None = None,
                  offset_s: float = 0.0) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    request = (f"GET {path} HTTP/1.1\r\nHost: bench\r\nAuthorization: Bearer {key}\r\n\r\n"
               .encode())
    scheduled = time.perf_counter() + offset_s
    try:
        while time.perf_counter() < deadline:
            started = time.perf_counter()
            if interval_s is not None:
                # Paced: latency counts from the scheduled send time, so a slow reply that
                # delays the next request is charged to it (no coordinated omission).
                await asyncio.sleep(max(0.0, scheduled - started))
                started = scheduled
                scheduled += interval_s
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            length = 0
            for line in head.split(b"\r\n"):
                if line[:15].lower() == b"content-length:":
                    length = int(line[15:])
            await reader.readexactly(length)
            latencies.append(time.perf_counter() - started)
            status = int(head[9:12])
            statuses[status] = statuses.get(status, 0) + 1
    finally:
        writer.close()


def load(port: int, path: str, key: str, clients: int, seconds: float,
         rate_per_s: float | None = None) -> tuple[list[float], dict[int, int]]:
    """``clients`` keep-alive connections each sending GET ``path`` with the API key ``key``:
    back to back, or together at ``rate_per_s`` requests per second (each client paced, start
    times staggered)."""
    latencies: list[float] = []
    statuses: dict[int, int] = {}
    interval_s = None if rate_per_s is None else clients / rate_per_s

    async def run() -> None:
        deadline = time.perf_counter() + seconds
        await asyncio.gather(*(
            _client(port, path, key, deadline, latencies, statuses, interval_s,
                    0.0 if interval_s is None else interval_s * i / clients)
            for i in range(clients)))

    asyncio.run(run())
    return latencies, statuses


def peak_rss_mb(pid: int) -> float:
    """Peak resident memory (VmHWM) of a process, MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time used so far by these processes and their children, seconds."""
    total = 0.0
    ticks = os.sysconf("SC_CLK_TCK")
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        # utime, stime, cutime, cstime are fields 14..17 (1-based) of /proc/PID/stat.
        total += sum(int(v) for v in fields[11:15]) / ticks
    return total


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants."""
    found, frontier = [pid], [pid]
    while frontier:
        parent = frontier.pop()
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == parent:
                    child = int(stat.parent.name)
                    found.append(child)
                    frontier.append(child)
            except (OSError, ValueError, IndexError):
                continue
    return found


def load_average() -> float:
    return round(os.getloadavg()[0], 2)
