#!/usr/bin/env python3
"""Prepare a lab for its first start: the compose file's one-shot ``setup`` service.

    labd-setup --config /etc/labd/labd.toml [--create-bucket] [--tokens DIR]
               [--worker NAME ...]

- ``--create-bucket``: make the bucket of the ``[serve]`` table's ``blobs`` (an
  ``s3://`` URL) at its ``endpoint_url`` unless it exists (the compose file's stand-in
  store starts empty; a real S3 service's bucket is the operator's to make);
- each ``--worker NAME``: a worker account and its token in ``DIR/NAME.token`` (mode
  0600), unless that file exists already, so a restart does not cut off running
  workers. A worker account whose token file was lost gets a new token (``labd users
  rotate``), the old one revoked.

Every ``labd`` command it runs reads the same ``--config`` as ``labd serve``, so none
can open another index. Runs with the image's Python (tomllib, and s3fs from labd's
``s3`` extra).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path


class SetupError(Exception):
    """A step failed; the message says which."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, required=True, help="the lab's TOML file")
    parser.add_argument("--create-bucket", action="store_true", help="make the blobs' bucket")
    parser.add_argument("--tokens", type=Path, default=Path("/run/labd-tokens"))
    parser.add_argument("--worker", action="append", default=[], metavar="NAME")
    args = parser.parse_args()
    try:
        serve = tomllib.loads(args.config.read_text()).get("serve", {})
        if args.create_bucket:
            create_bucket(serve)
        for name in args.worker:
            provision(args.config, args.tokens, name)
    except (OSError, tomllib.TOMLDecodeError, SetupError) as err:
        print(f"labd-setup: {err}", file=sys.stderr)
        return 1
    return 0


def create_bucket(serve: dict[str, object]) -> None:
    """Make the bucket that ``blobs`` names, at ``blobs_option``'s endpoint_url."""
    import s3fs  # type: ignore[import-untyped]  # noqa: PLC0415 - labd's s3 extra, needed here only

    blobs = str(serve.get("blobs", ""))
    if not blobs.startswith("s3://"):
        raise SetupError(f"--create-bucket: blobs is {blobs!r}, not an s3:// URL")
    listed = serve.get("blobs_option", [])
    pairs = (str(o).split("=", 1) for o in (listed if isinstance(listed, list) else []))
    options = {key: value for key, value in pairs}
    bucket = blobs.removeprefix("s3://").split("/", 1)[0]
    fs = s3fs.S3FileSystem(endpoint_url=options.get("endpoint_url"))
    if fs.exists(bucket):
        print(f"labd-setup: the bucket {bucket} is there", file=sys.stderr)
        return
    fs.mkdir(bucket)
    print(f"labd-setup: made the bucket {bucket}", file=sys.stderr)


def provision(config: Path, tokens: Path, name: str) -> None:
    """A worker account ``name`` and its token in ``tokens/NAME.token``."""
    path = tokens / f"{name}.token"
    if path.exists():
        print(f"labd-setup: {name} has its token in {path}", file=sys.stderr)
        return
    tokens.mkdir(parents=True, exist_ok=True)
    added = labd("users", "add", name, "--worker", config=config)
    if "error" in added:
        if "exists already" not in str(added["error"]):
            raise SetupError(f"labd users add {name}: {added['error']}")
        added = labd("users", "rotate", name, config=config)  # its token file was lost
        if "error" in added:
            raise SetupError(f"labd users rotate {name}: {added['error']}")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(f"{added['token']}\n")
    print(f"labd-setup: {name}'s token is in {path}", file=sys.stderr)


def labd(*command: str, config: Path) -> dict[str, object]:
    """Run ``labd COMMAND --config CONFIG --json``; its JSON answer (an error included)."""
    done = subprocess.run(  # noqa: S603 - the image's own labd
        ["labd", *command, "--config", str(config), "--json"],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    try:
        answer = json.loads(done.stdout)
    except ValueError:
        raise SetupError(
            f"labd {' '.join(command)} answered no JSON ({done.returncode}):"
            f" {done.stderr.strip() or done.stdout.strip()}"
        ) from None
    if not isinstance(answer, dict):
        raise SetupError(f"labd {' '.join(command)} answered {answer!r}")
    return answer


if __name__ == "__main__":
    sys.exit(main())
