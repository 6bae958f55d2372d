"""What the sandbox costs a trial: the same controller and task, unsandboxed and sandboxed.

The maze example controller (``controllers/examples/icreate-maze``) runs the same
trials (same seeds, so the same ticks) three ways, through the same trial runner,
recorder and bridge:

- **unsandboxed**: the controller as a plain child process of the lab, reaching the
  bridge through a relay in the lab's process (the runner's bridge is a unix socket,
  as for the sandboxes, whose launcher relays likewise);
- **bwrap** and **docker**: ``labd run --sandbox bwrap|docker``.

For each: the start latency (from starting the controller to its first
``/lab/step``: the process, the runtime, imports, connecting) and the time per control
tick while it runs, with the ratio to the unsandboxed run. Targets (from the issue):
per tick at most 1.5 times the unsandboxed loop; start under 1 s with bubblewrap and
under 2 s with Docker (image already built). For scale it also prints the physics
alone: the same number of ticks stepped in-process.

    .venv/bin/python bench/trial.py [--seeds 0,1,2] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import sandbox
from labd.sim.simulation import Simulation
from labd.trial import LabHost, client_library
from repository.trial import Order, Outcome
from sandbox.api import Exit, Job
from scheduler.runner import RunOptions, run_trial

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "controllers" / "examples" / "icreate-maze"
TICK_RATIO = 1.5
START = {"bwrap": 1.0, "docker": 2.0}


class Unsandboxed:
    """A Backend that runs the controller as a plain child process (for comparison only)."""

    name = "unsandboxed"

    def __init__(self, runtime_digest: str) -> None:
        self._digest = runtime_digest

    def runtime_digest(self) -> str:
        return self._digest

    async def install(self, requirements: Path, target: Path) -> None:
        raise NotImplementedError("the benchmark's controller has no requirements")

    async def install_node(self, package: Path, lock: Path, target: Path) -> None:
        raise NotImplementedError("the benchmark's controller has no npm packages")

    async def start(self, job: Job) -> _Plain:
        assert job.bridge_socket is not None
        relay = await _relay(job.bridge_socket)
        port = relay.sockets[0].getsockname()[1]
        env = {
            **os.environ,
            **job.env,
            "LAB_BRIDGE_URL": f"ws://127.0.0.1:{port}",
            "PYTHONPATH": str(client_library().parent),
        }
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            *job.command[1:],
            cwd=job.code,
            env=env,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        return _Plain(process, relay)


class _Plain:
    def __init__(self, process: asyncio.subprocess.Process, relay: asyncio.Server) -> None:
        self.process = process
        self.relay = relay

    async def wait(self) -> Exit:
        out, err = await self.process.communicate()
        self.relay.close()
        return Exit(self.process.returncode, stdout=out, stderr=err)

    async def stop(self, grace: float = 2.0) -> Exit:
        with contextlib.suppress(ProcessLookupError):
            self.process.terminate()
        return await self.wait()


async def _relay(socket: Path) -> asyncio.Server:
    async def pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.close()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_unix_connection(str(socket))
        await asyncio.gather(pipe(reader, up_writer), pipe(up_reader, writer))

    return await asyncio.start_server(handle, "127.0.0.1", 0)


def trials(
    backend: Any, seeds: Sequence[int], cache: Path, example: Path = EXAMPLE
) -> list[dict[str, float]]:
    """One trial of ``example`` per seed: its ticks, start, time per tick, data digest."""
    host = LabHost()
    out = []
    with tempfile.TemporaryDirectory(prefix="labd-bench-") as folder:
        for seed in seeds:
            result = asyncio.run(
                run_trial(
                    Order(repository=str(example), seed=seed),
                    backend=backend,
                    out=Path(folder) / f"{backend.name}-{seed}",
                    cache=cache,
                    host=host,
                    options=RunOptions(),
                )
            )
            if result.outcome is not Outcome.SUCCESS:
                raise SystemExit(f"{backend.name} seed {seed}: {result.outcome}: {result.reason}")
            ticks = int(result.metrics["ticks"])
            assert result.start_seconds is not None and result.run_seconds is not None
            out.append(
                {
                    "seed": seed,
                    "ticks": ticks,
                    "start": result.start_seconds,
                    "per_tick_ms": 1000 * result.run_seconds / ticks,
                    "digest": result.data_digest,
                }
            )
    return out


def physics_alone(seeds: Sequence[int], ticks: Sequence[int]) -> float:
    """Milliseconds per tick of the physics stepped in-process, for the same ticks."""
    total_ticks, total = 0, 0.0
    for seed, count in zip(seeds, ticks, strict=True):
        sim = Simulation("icreate-maze", {}, seed)
        started = time.perf_counter()
        for _ in range(count):
            sim.env.step(sim.task.action(sim.physics))
        total += time.perf_counter() - started
        total_ticks += count
    return 1000 * total / total_ticks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    args.cache.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"backends": {}}
    backends: list[Any] = []
    for name in ("bwrap", "docker"):
        try:
            backends.append(sandbox.backend(name, args.cache, extra_packages=[client_library()]))
        except sandbox.BackendUnavailable as err:
            print(f"[bench] {name}: {err}", file=sys.stderr)
    digest = backends[0].runtime_digest() if backends else "none"
    for backend in [Unsandboxed(digest), *backends]:
        print(f"[bench] {backend.name}", file=sys.stderr)
        runs = trials(backend, seeds, args.cache)
        results["backends"][backend.name] = {
            "start_s_median": statistics.median(r["start"] for r in runs),
            "per_tick_ms_median": statistics.median(r["per_tick_ms"] for r in runs),
            "runs": runs,
        }
    base = results["backends"]["unsandboxed"]
    ticks = [r["ticks"] for r in base["runs"]]
    results["physics_ms_per_tick"] = physics_alone(seeds, ticks)
    for figures in results["backends"].values():
        figures["tick_ratio"] = figures["per_tick_ms_median"] / base["per_tick_ms_median"]
        figures["same_data"] = [r["digest"] for r in figures["runs"]] == [
            r["digest"] for r in base["runs"]
        ]
    if args.json:
        print(json.dumps(results, indent=2))
        return
    report(results, seeds)


def report(results: dict[str, Any], seeds: Sequence[int]) -> None:
    print("Trials of the maze example controller, unsandboxed and in each sandbox")
    print(f"  seeds {','.join(map(str, seeds))}; medians over the seeds; 2 CPUs\n")
    print(f"  {'':12} {'start':>9} {'per tick':>10} {'ratio':>7}  same data")
    for name, f in results["backends"].items():
        print(
            f"  {name:12} {f['start_s_median']:8.2f}s {f['per_tick_ms_median']:8.2f}ms"
            f" {f['tick_ratio']:7.2f}  {'yes' if f['same_data'] else 'NO'}"
        )
    print(f"  {'physics only':12} {'':9} {results['physics_ms_per_tick']:8.2f}ms\n")
    for name, limit in START.items():
        f = results["backends"].get(name)
        if f is None:
            print(f"  SKIP  {name}: not available")
            continue
        ok_tick = f["tick_ratio"] <= TICK_RATIO
        ok_start = f["start_s_median"] < limit
        print(f"  {'PASS' if ok_tick else 'FAIL'}  {name} per tick <= {TICK_RATIO}x unsandboxed")
        print(f"  {'PASS' if ok_start else 'FAIL'}  {name} start < {limit:g} s")


if __name__ == "__main__":
    main()
