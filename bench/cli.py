"""How long the ``labd`` command takes to start, in CPU time, against a bare interpreter.

    .venv/bin/python bench/cli.py [--runs 5] [--json]

Runs each command ``--runs`` times in a fresh process and takes the median of its CPU
time (user + system, the process and its children, from ``getrusage``; wall time on a
shared machine says more about the neighbours). The baseline is ``python -c pass`` in
the same run, so the ratios compare across machines:

- ``labd --version``: the command line alone (no command's module is imported);
- ``labd trials --help``: a command that talks to a lab (``labd.commands.remote``);
- ``labd serve --help``: the lab itself (the simulator, the index, the web server).

Target (from the issue): a command that talks to a lab starts in well under 0.5 s of
CPU; the simulator is imported only by the commands that simulate.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys

TARGET = 0.5  # seconds of CPU, at most, for a command that talks to a lab
CASES = {
    "python -c pass": ["-c", "pass"],
    "labd --version": ["-m", "labd", "--version"],
    "labd trials --help": ["-m", "labd", "trials", "--help"],
    "labd serve --help": ["-m", "labd", "serve", "--help"],
}


def cpu_seconds(args: list[str]) -> float:
    """The CPU time (user + system) of one run of ``python ARGS``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, *args], check=True, stdout=subprocess.DEVNULL, timeout=120)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs of each (default: 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    runs: dict[str, list[float]] = {name: [] for name in CASES}
    for _ in range(args.runs):  # interleaved: a busy moment slows every case alike
        for name, command in CASES.items():
            runs[name].append(cpu_seconds(command))
    medians = {name: statistics.median(times) for name, times in runs.items()}
    base = medians["python -c pass"]
    result = {
        name: {"cpu_seconds": round(seconds, 3), "ratio": round(seconds / base, 1)}
        for name, seconds in medians.items()
    }
    client = medians["labd trials --help"]
    result["target"] = {"client_cpu_seconds": TARGET, "met": client < TARGET}
    if args.json:
        print(json.dumps(result))
        return
    print(f"CPU time, median of {args.runs} runs (user + system)")
    for name, seconds in medians.items():
        print(f"  {name:<22} {seconds:6.3f} s   {seconds / base:6.1f} x python -c pass")
    verdict = "met" if client < TARGET else "NOT met"
    print(f"target: labd trials --help under {TARGET} s of CPU: {verdict}")


if __name__ == "__main__":
    main()
