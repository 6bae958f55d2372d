"""How labd's rosbridge server compares with a bare websockets relay, in one run.

Both servers run side by side, each in its own process, and get the same workload
from the same clients (``bench/clients.py``), one publisher process and one
subscriber process per measurement: geometry_msgs/msg/Twist publish frames on
``/cmd_vel``. Every figure of labd is printed with its ratio to the relay's, measured
moments before on the same machine, because this machine is noisy and a lone
absolute time means little.

- throughput: the publisher sends as fast as the server takes them; the figure is
  what the subscriber receives per second in steady state, and the fraction lost;
- latency: the publisher sends at 100 and at 1,000 messages per second, each stamped
  with ``time.perf_counter()``; p50 and p99 of receive minus send;
- memory (labd only): one subscriber to an Image topic that never reads and one that
  does, while 640x480 rgb8 images arrive at about 20 MB/s; the server's peak RSS,
  and how much of the publish rate the reading subscriber still gets.

Each measurement runs ``--rounds`` times per server, relay and labd alternating, so
that load from other jobs on the host falls on both; the table also says how much
CPU the rest of the machine used meanwhile.

    .venv/bin/python bench/bridge.py [--quick] [--seconds S] [--rounds N]
                                     [--phases throughput,latency_100,...] [--json [FILE]]

``--json`` prints one JSON object with every figure instead of the table (``--json
FILE`` writes it to FILE and prints the table). Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import platform
import re
import resource
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import websockets

HERE = Path(__file__).resolve().parent
PYTHON = sys.executable
MB = 1_000_000
MiB = 1024 * 1024

# Targets for labd (b) against the relay (a), from the issue.
THROUGHPUT_RATIO = 0.60  # b/a at least
LATENCY_RATIO = 1.5  # b/a at most, p50 and p99
PEAK_RSS = 300 * MB  # at most
KEPT_RATE = 0.90  # share of the publish rate the reading subscriber keeps, at least

# Figures the issue gives for this kind of machine; printed, never measured here.
REFERENCE = {
    "rosbridge 0.11.17 (ROS 1)": {"msg_per_s": 2800, "p50_ms": 2.4, "p99_ms": 10.0},
    "bare relay": {"msg_per_s": 31000, "p50_ms": 1.0, "p99_ms": 4.0},
}


PHASES = ("throughput", "latency_100", "latency_1000", "memory")


class BenchError(Exception):
    """A server or client did not behave; the message says which and why."""


# -- child processes --------------------------------------------------------------------


def _die_with_parent() -> None:
    """Runs in the child: get SIGTERM if the benchmark dies without cleaning up."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Child:
    """One process of the benchmark, its stdout read line by line, its stderr to a log."""

    def __init__(self, name: str, cmd: list[str], logs: Path) -> None:
        self.name = name
        self.log = logs / f"{name}.log"
        with self.log.open("ab") as err:
            self.proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=err,
                preexec_fn=_die_with_parent if sys.platform == "linux" else None,  # noqa: PLW1509
            )
        self.pid = self.proc.pid
        self._buf = b""

    def _read(self, deadline: float) -> bool | None:
        """Read what stdout has: False at end of file, None if nothing came by ``deadline``."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            return None
        chunk = os.read(fd, 1 << 20)
        self._buf += chunk
        return bool(chunk)

    def _silent(self) -> BenchError:
        return BenchError(f"{self.name} said nothing in time{self._tail()}")

    def expect(self, pattern: str, timeout: float) -> re.Match[str]:
        """Wait for a stdout line matching ``pattern``."""
        deadline = time.monotonic() + timeout
        while True:
            while b"\n" in self._buf:
                line, self._buf = self._buf.split(b"\n", 1)
                match = re.search(pattern, line.decode(errors="replace"))
                if match:
                    return match
            got = self._read(deadline)
            if got is None:
                raise self._silent()
            if not got:
                raise BenchError(f"{self.name} exited before saying {pattern!r}{self._tail()}")

    def result(self, timeout: float, idle: Callable[[], None] | None = None) -> dict[str, Any]:
        """Wait for the process to end and return the JSON of its last line."""
        deadline = time.monotonic() + timeout
        while True:
            step = min(deadline, time.monotonic() + 0.5) if idle else deadline
            got = self._read(step)
            if got is False:
                break
            if got is None and time.monotonic() >= deadline:
                raise self._silent()
            if idle:
                idle()
        self.proc.wait(timeout=10)
        lines = self._buf.strip().splitlines()
        if self.proc.returncode != 0 or not lines:
            raise BenchError(f"{self.name} failed ({self.proc.returncode}){self._tail()}")
        return dict(json.loads(lines[-1]))

    def signal_result(self, timeout: float) -> dict[str, Any]:
        """SIGTERM, then the result it prints on its way out."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.result(timeout)

    def _tail(self) -> str:
        text = self.log.read_text(errors="replace").strip() if self.log.exists() else ""
        return f"; its log ends:\n{text[-2000:]}" if text else ""

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@dataclass
class Bench:
    logs: Path
    children: list[Child] = field(default_factory=list)

    def spawn(self, name: str, cmd: list[str]) -> Child:
        child = Child(name, cmd, self.logs)
        self.children.append(child)
        return child

    def client(self, name: str, role: str, url: str, **options: object) -> Child:
        cmd = [PYTHON, str(HERE / "clients.py"), role, "--url", url]
        for key, value in options.items():
            cmd += [f"--{key}", str(value)]
        return self.spawn(name, cmd)

    def retire(self, child: Child) -> None:
        """Stop a finished client; its CPU time joins ``resource.RUSAGE_CHILDREN``."""
        self.children.remove(child)
        child.stop()

    def close(self) -> None:
        for child in reversed(self.children):
            with contextlib.suppress(Exception):
                child.stop()
        self.children.clear()


@dataclass
class Server:
    label: str  # "relay" or "labd"
    url: str
    child: Child

    def cpu_seconds(self) -> float:
        times = psutil.Process(self.child.pid).cpu_times()
        return float(times.user + times.system)

    def rss(self) -> int:
        return int(psutil.Process(self.child.pid).memory_info().rss)


def start_relay(bench: Bench) -> Server:
    child = bench.spawn("relay", [PYTHON, str(HERE / "relay.py"), "--port", "0"])
    match = child.expect(r"relay on (ws://\S+)", 30)
    return Server("relay", match.group(1), child)


def start_labd(bench: Bench) -> Server:
    cmd = [PYTHON, "-m", "labd", "--log-level", "WARNING", "serve", "--bridge-port", "0"]
    child = bench.spawn("labd", [*cmd, "--data", str(bench.logs / "lab-data")])
    match = child.expect(r"rosbridge v2 on (ws://\S+)", 30)
    return Server("labd", match.group(1), child)


# -- statistics -------------------------------------------------------------------------


def percentile(values: list[float], q: float) -> float:
    """Nearest-rank percentile of sorted ``values``."""
    if not values:
        return math.nan
    return values[min(len(values) - 1, max(0, math.ceil(q * len(values)) - 1))]


def steady_rate(hist: list[int], step: float) -> float:
    """Messages per second from first to last arrival, less a tenth (at most 1 s) each end."""
    busy = [i for i, n in enumerate(hist) if n]
    if len(busy) < 3:
        return math.nan
    first, last = busy[0], busy[-1]
    trim = max(1, min(round(1.0 / step), (last - first) // 10))
    lo, hi = first + trim, last - trim
    if hi <= lo:
        return math.nan
    return sum(hist[lo:hi]) / ((hi - lo) * step)


# -- phases -----------------------------------------------------------------------------


def run_twist(
    bench: Bench, server: Server, rate: float, seconds: float, tag: str
) -> dict[str, Any]:
    """One publisher and one subscriber of Twist on ``server``; rate 0 means unpaced.

    Paced runs return their latencies (seconds, sorted, first second left out) under
    ``"latencies"``; the caller pools them over rounds.
    """
    mode = "count" if rate <= 0 else "latency"
    sub = bench.client(f"{tag}-sub", "sub", server.url, kind="twist", mode=mode)
    sub.expect("^ready$", 30)
    pub = bench.client(f"{tag}-pub", "pub", server.url, kind="twist", rate=rate, seconds=seconds)
    pub.expect("^go$", 30)
    cpu0, wall0 = server.cpu_seconds(), time.perf_counter()
    sent = pub.result(seconds + 120)
    try:
        got = sub.result(60)
    except BenchError:
        got = sub.signal_result(10)  # the end marker never came: take what arrived
    cpu1, wall1 = server.cpu_seconds(), time.perf_counter()
    for child in (pub, sub):
        bench.retire(child)

    active = max(1e-9, sent["end"] - sent["start"])
    out: dict[str, Any] = {
        "sent": sent["sent"],
        "received": got["received"],
        "end_seen": got["end_seen"],
        "offered_msg_per_s": sent["sent"] / active,
        "cpu": {
            "server": (cpu1 - cpu0) / (wall1 - wall0),
            "publisher": sent["cpu"] / active,
            "subscriber": got["cpu"] / max(1e-9, got["wall"]),
        },
    }
    if rate <= 0:
        out["msg_per_s"] = steady_rate(got["hist"], got["hist_step"])
    else:
        warm = min(1.0, 0.1 * seconds)
        out["latencies"] = sorted(lat for t, lat in got["samples"] if t >= sent["start"] + warm)
    return out


def summarize(rounds: list[dict[str, Any]], paced: bool) -> dict[str, Any]:
    """One server's figures over its rounds: medians, or pooled latencies."""
    sent = sum(r["sent"] for r in rounds)
    out: dict[str, Any] = {
        "rounds": len(rounds),
        "sent": sent,
        "received": sum(r["received"] for r in rounds),
        "lost": 1.0 - sum(r["received"] for r in rounds) / sent if sent else math.nan,
        "offered_msg_per_s": statistics.median(r["offered_msg_per_s"] for r in rounds),
        "cpu": {k: statistics.median(r["cpu"][k] for r in rounds) for k in rounds[0]["cpu"]},
    }
    if not paced:
        out["msg_per_s"] = statistics.median(r["msg_per_s"] for r in rounds)
        out["msg_per_s_rounds"] = [r["msg_per_s"] for r in rounds]
        return out
    lat = sorted(x for r in rounds for x in r["latencies"])
    out.update(
        samples=len(lat),
        p50_ms=percentile(lat, 0.50) * 1e3,
        p99_ms=percentile(lat, 0.99) * 1e3,
        max_ms=(lat[-1] if lat else math.nan) * 1e3,
        p50_ms_rounds=[percentile(r["latencies"], 0.50) * 1e3 for r in rounds],
        p99_ms_rounds=[percentile(r["latencies"], 0.99) * 1e3 for r in rounds],
    )
    return out


def run_memory(
    bench: Bench, server: Server, seconds: float, mb_per_s: float, width: int, height: int
) -> dict[str, Any]:
    """A stalled and a reading Image subscriber on labd; RSS sampled every 0.5 s."""
    topic = "/camera/image_raw"
    image_bytes = width * height * 3
    rate = mb_per_s * MB / image_bytes
    size = {"width": width, "height": height, "topic": topic, "kind": "image"}
    rss: list[tuple[float, int]] = []
    t0 = time.perf_counter()

    def sample() -> None:
        rss.append((time.perf_counter() - t0, server.rss()))

    sample()
    stalled = bench.client("memory-stalled-sub", "sub", server.url, mode="stall", **size)
    stalled.expect("^ready$", 30)
    reader = bench.client("memory-reading-sub", "sub", server.url, mode="latency", **size)
    reader.expect("^ready$", 30)
    before = server.rss()
    pub = bench.client("memory-pub", "pub", server.url, rate=f"{rate:.6f}", seconds=seconds, **size)
    pub.expect("^go$", 30)
    cpu0, wall0 = server.cpu_seconds(), time.perf_counter()
    sample()
    go = len(rss)
    sent = pub.result(seconds + 120, idle=sample)
    during = [r for t, r in rss[go:] if t0 + t <= sent["end"]] or [rss[-1][1]]
    try:
        got = reader.result(60, idle=sample)
    except BenchError:
        got = reader.signal_result(10)
    cpu1, wall1 = server.cpu_seconds(), time.perf_counter()
    stall = stalled.signal_result(10)
    settle = time.perf_counter() + 2.0
    while time.perf_counter() < settle:
        time.sleep(0.5)
        sample()
    for child in (pub, reader, stalled):
        bench.retire(child)

    active = max(1e-9, sent["end"] - sent["start"])
    warm = min(1.0, 0.1 * seconds)
    lat = sorted(lat for t, lat in got["samples"] if t >= sent["start"] + warm)
    return {
        "seconds": seconds,
        "image": f"{width}x{height} rgb8",
        "image_bytes": image_bytes,
        "publish_hz": sent["sent"] / active,
        "publish_mb_per_s": sent["sent"] * image_bytes / active / MB,
        "sent": sent["sent"],
        "received": got["received"],
        "kept": got["received"] / sent["sent"] if sent["sent"] else math.nan,
        "received_hz": got["received"] / active,
        "latency_p50_ms": percentile(lat, 0.50) * 1e3,
        "latency_p99_ms": percentile(lat, 0.99) * 1e3,
        "rss_before_bytes": before,
        "rss_peak_bytes": max(r for _, r in rss),
        "rss_after_bytes": rss[-1][1],
        "rss_samples": [(round(t, 2), r) for t, r in rss],
        "rss_tenths_bytes": [
            during[min(len(during) - 1, len(during) * k // 10)] for k in range(1, 11)
        ],
        "stalled_closed_by_server": stall.get("closed_by_server", False),
        "server_cpu": (cpu1 - cpu0) / (wall1 - wall0),
    }


# -- the run ----------------------------------------------------------------------------


def finite(value: Any) -> Any:
    """``value`` with NaN replaced by None, so that the JSON is standard."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def progress(text: str) -> None:
    print(f"[bench] {text}", file=sys.stderr, flush=True)


class Machine:
    """CPU time the rest of the machine used while we ran (other jobs share this host)."""

    def __init__(self, servers: tuple[Server, ...]) -> None:
        self.servers = servers
        self.start = self._sample()

    def _sample(self) -> tuple[float, float, float]:
        total = psutil.cpu_times()
        busy = sum(total) - total.idle - getattr(total, "iowait", 0.0)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        ours = kids.ru_utime + kids.ru_stime + time.process_time()
        ours += sum(s.cpu_seconds() for s in self.servers)
        return time.monotonic(), busy, ours

    def others(self) -> float:
        """CPU cores used on average by processes not of this benchmark, so far."""
        t1, busy1, ours1 = self._sample()
        t0, busy0, ours0 = self.start
        return max(0.0, (busy1 - busy0) - (ours1 - ours0)) / (t1 - t0)


def measure(args: argparse.Namespace, bench: Bench) -> dict[str, Any]:
    relay, labd = start_relay(bench), start_labd(bench)
    servers = (relay, labd)
    machine = Machine(servers)
    results: dict[str, Any] = {
        "config": {
            "seconds": args.seconds,
            "rounds": args.rounds,
            "memory_seconds": args.memory_seconds,
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "websockets": websockets.__version__,
            "platform": platform.platform(),
        },
    }
    phases = [("throughput", 0.0)] + [(f"latency_{r:g}", r) for r in (100.0, 1000.0)]
    for name, rate in phases:
        if name not in args.phases:
            continue
        runs: dict[str, list[dict[str, Any]]] = {"relay": [], "labd": []}
        for n in range(args.rounds):
            for server in servers:  # the baseline, then labd, moments apart
                progress(f"{name}: {server.label}, round {n + 1} of {args.rounds}")
                tag = f"{name}-{server.label}-{n + 1}"
                runs[server.label].append(run_twist(bench, server, rate, args.seconds, tag))
        a, b = (summarize(runs[s.label], rate > 0) for s in servers)
        row: dict[str, Any] = {"relay": a, "labd": b}
        if rate <= 0:
            # Each round's labd figure against the relay's of the same round.
            pairs = zip(a["msg_per_s_rounds"], b["msg_per_s_rounds"], strict=True)
            row["ratio"] = statistics.median(y / x for x, y in pairs)
            row["pass"] = row["ratio"] >= THROUGHPUT_RATIO
        else:
            row["ratio_p50"] = b["p50_ms"] / a["p50_ms"]
            row["ratio_p99"] = b["p99_ms"] / a["p99_ms"]
            row["pass_p50"] = row["ratio_p50"] <= LATENCY_RATIO
            row["pass_p99"] = row["ratio_p99"] <= LATENCY_RATIO
        results[name] = row
    if "memory" in args.phases and args.memory_seconds > 0:
        progress(f"memory: labd, {args.memory_seconds:g} s of images at {args.mb_per_s:g} MB/s")
        mem = run_memory(bench, labd, args.memory_seconds, args.mb_per_s, 640, 480)
        mem["pass_rss"] = mem["rss_peak_bytes"] < PEAK_RSS
        mem["pass_kept"] = mem["kept"] >= KEPT_RATE
        results["memory"] = mem
    results["config"]["other_processes_cpu_cores"] = machine.others()
    results["reference_not_measured"] = REFERENCE
    verdicts = list(iter_verdicts(results))
    results["targets"] = [{"target": t, "pass": ok} for t, ok in verdicts]
    results["pass"] = all(ok for _, ok in verdicts)
    return results


def iter_verdicts(results: dict[str, Any]) -> Iterator[tuple[str, bool]]:
    if "throughput" in results:
        yield f"throughput b/a >= {THROUGHPUT_RATIO}", results["throughput"]["pass"]
    for rate in ("100", "1000"):
        row = results.get(f"latency_{rate}")
        if row:
            for q in ("p50", "p99"):
                yield f"latency @{rate}/s {q} b/a <= {LATENCY_RATIO}", row[f"pass_{q}"]
    mem = results.get("memory")
    if mem:
        yield f"peak RSS < {PEAK_RSS // MB} MB", mem["pass_rss"]
        yield f"reading subscriber >= {KEPT_RATE:.0%} of publish rate", mem["pass_kept"]


# -- the table --------------------------------------------------------------------------


def verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def row(label: str, a: str = "", b: str = "", ratio: str = "", target: str = "") -> str:
    return f"  {label:<28}{a:>14}{b:>14}{ratio:>8}   {target}".rstrip()


def rounds(what: str, a: list[float], b: list[float], fmt: str) -> str:
    if len(a) < 2:
        return ""
    each = "  ".join(
        f"{label}: {' '.join(format(x, fmt) for x in xs)}" for label, xs in (("a", a), ("b", b))
    )
    return f"    {what}, each round: {each}"


def table(r: dict[str, Any]) -> str:
    c = r["config"]
    out = [
        "labd rosbridge server (b) against a bare websockets+orjson relay (a)",
        f"  same run, same clients; server, publisher and subscriber in separate processes; "
        f"{c['cpus']} CPUs, Python {c['python']}, websockets {c['websockets']}",
        f"  workload: geometry_msgs/msg/Twist publish frames on /cmd_vel; each figure from "
        f"{c['rounds']} round(s) of {c['seconds']:g} s per server, relay and labd alternating",
        "  throughput: median of rounds, b/a the median of same-round ratios; "
        "latency: rounds pooled",
        f"  other processes on this machine used {c['other_processes_cpu_cores']:.2f} CPU cores "
        "on average during the run",
        "",
        row("", "(a) relay", "(b) labd", "b/a", "target"),
    ]
    if "throughput" in r:
        out += throughput_lines(r["throughput"])
    for rate in ("100", "1000"):
        if f"latency_{rate}" in r:
            out += latency_lines(rate, r[f"latency_{rate}"])
    if "memory" in r:
        out += memory_lines(r["memory"])
    out += ["", "  reference figures from the issue, NOT measured here (separate processes):"]
    for name, ref in r["reference_not_measured"].items():
        out.append(
            f"    {name:<28}{ref['msg_per_s']:>8,} msg/s unpaced; at 100/s "
            f"p50 {ref['p50_ms']} ms, p99 {ref['p99_ms']} ms"
        )
    passed = sum(t["pass"] for t in r["targets"])
    out += ["", f"  targets: {passed} of {len(r['targets'])} pass"]
    out += [f"    {verdict(t['pass'])}  {t['target']}" for t in r["targets"]]
    return "\n".join(out)


def throughput_lines(tp: dict[str, Any]) -> list[str]:
    a, b = tp["relay"], tp["labd"]
    lines = [
        row(
            "throughput, unpaced (msg/s)",
            f"{a['msg_per_s']:,.0f}",
            f"{b['msg_per_s']:,.0f}",
            f"{tp['ratio']:.2f}",
            f">= {THROUGHPUT_RATIO:.2f}  {verdict(tp['pass'])}",
        ),
        rounds("msg/s", a["msg_per_s_rounds"], b["msg_per_s_rounds"], ",.0f"),
        row("  lost", f"{a['lost']:.2%}", f"{b['lost']:.2%}"),
        row(
            "  offered by publisher",
            f"{a['offered_msg_per_s']:,.0f}",
            f"{b['offered_msg_per_s']:,.0f}",
        ),
    ]
    lines += [
        row(f"  CPU {who}", f"{a['cpu'][who]:.0%}", f"{b['cpu'][who]:.0%}")
        for who in ("server", "publisher", "subscriber")
    ]
    return [line for line in lines if line]


def latency_lines(rate: str, r: dict[str, Any]) -> list[str]:
    a, b = r["relay"], r["labd"]
    lines = []
    for q in ("p50", "p99"):
        lines += [
            row(
                f"latency @{rate}/s {q} (ms)",
                f"{a[f'{q}_ms']:.3f}",
                f"{b[f'{q}_ms']:.3f}",
                f"{r[f'ratio_{q}']:.2f}",
                f"<= {LATENCY_RATIO:.2f}  {verdict(r[f'pass_{q}'])}",
            ),
            rounds(f"{q} ms", a[f"{q}_ms_rounds"], b[f"{q}_ms_rounds"], ".2f"),
        ]
    lines += [
        row("  max (ms)", f"{a['max_ms']:.3f}", f"{b['max_ms']:.3f}"),
        row("  lost", f"{a['lost']:.2%}", f"{b['lost']:.2%}"),
    ]
    return [line for line in lines if line]


def memory_lines(mem: dict[str, Any]) -> list[str]:
    trend = " ".join(f"{b / MB:.0f}" for b in mem["rss_tenths_bytes"])
    return [
        "",
        f"  memory (labd only): {mem['image']} Image at {mem['publish_hz']:.1f}/s "
        f"({mem['publish_mb_per_s']:.1f} MB/s of pixels) for {mem['seconds']:g} s,",
        "  one subscriber that never reads and one that reads",
        f"  {'server RSS peak':<40}{mem['rss_peak_bytes'] / MB:>8.1f} MB   "
        f"< {PEAK_RSS // MB} MB  {verdict(mem['pass_rss'])}",
        f"  {'  before / after the run':<40}{mem['rss_before_bytes'] / MB:>8.0f} MB / "
        f"{mem['rss_after_bytes'] / MB:.0f} MB",
        f"  {'  at each tenth of the run (MB)':<40}{trend}",
        f"  {'reading subscriber got':<40}{mem['kept']:>8.1%}      "
        f">= {KEPT_RATE:.0%}  {verdict(mem['pass_kept'])}",
        f"  {'  received / published':<40}{mem['received_hz']:>8.1f} /s  of "
        f"{mem['publish_hz']:.1f} /s ({mem['received']} of {mem['sent']})",
        f"  {'  image latency p50 / p99':<40}{mem['latency_p50_ms']:>8.1f} ms / "
        f"{mem['latency_p99_ms']:.1f} ms",
        f"  {'  stalled client cut off by the server':<40}"
        f"{'yes' if mem['stalled_closed_by_server'] else 'no':>8}",
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run of a few seconds each")
    parser.add_argument("--seconds", type=float, help="per throughput and latency measurement")
    parser.add_argument("--rounds", type=int, help="relay/labd alternations per measurement")
    parser.add_argument("--memory-seconds", type=float, help="of the memory phase (0: skip it)")
    parser.add_argument("--mb-per-s", type=float, default=20.0, help="image data, memory phase")
    parser.add_argument(
        "--phases",
        type=lambda text: set(text.split(",")),
        default=set(PHASES),
        help=f"a comma-separated subset of {','.join(PHASES)}",
    )
    parser.add_argument("--json", nargs="?", const="-", metavar="FILE", help="JSON ('-': stdout)")
    args = parser.parse_args(argv)
    if not args.phases <= set(PHASES):
        parser.error(f"--phases: choose among {', '.join(PHASES)}")
    if args.seconds is None:
        args.seconds = 2.0 if args.quick else 10.0
    if args.rounds is None:
        args.rounds = 1 if args.quick else 2
    if args.memory_seconds is None:
        args.memory_seconds = 6.0 if args.quick else 30.0

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so that `finally` runs
    with tempfile.TemporaryDirectory(prefix="labd-bench-") as tmp:
        bench = Bench(Path(tmp))
        try:
            results = measure(args, bench)
        except BenchError as err:
            print(f"bench/bridge.py: {err}", file=sys.stderr)
            return 1
        finally:
            bench.close()
    if args.json == "-":
        print(json.dumps(finite(results), indent=1))
    else:
        print(table(results))
        if args.json:
            Path(args.json).write_text(json.dumps(finite(results), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
