"""How the archive's records look in the HTTP API: JSON a person and a script can read."""

from __future__ import annotations

import datetime as dt
from typing import Any

from labd.sim import registry

LIST_FIELDS = (
    "id",
    "status",
    "reason",
    "repository",
    "ref",
    "commit",
    "task",
    "params",
    "seed",
    "submitter",
    "public",
    "rerun_of",
    "attempts",
    "manifest_digest",
    "data_digest",
    "metrics",
    "backend",
    "wall_seconds",
    "reproduced",
    "divergence",
)


def iso(seconds: float | None) -> str | None:
    if seconds is None:
        return None
    moment = dt.datetime.fromtimestamp(seconds, dt.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def verdict(row: dict[str, Any]) -> str | None:
    """A rerun's verdict in words: "reproduced", "diverged at ...", or None."""
    if row["rerun_of"] is None or row["status"] not in ("succeeded", "failed"):
        return None
    if row["reproduced"]:
        return "reproduced"
    return row["divergence"] or "not compared"


def trial(row: dict[str, Any], *, base: str = "", full: bool = False) -> dict[str, Any]:
    """One trial; ``full`` adds its manifest."""
    out = {name: row[name] for name in LIST_FIELDS}
    out["created"] = iso(row["created"])
    out["started"] = iso(row["started"])
    out["finished"] = iso(row["finished"])
    out["verdict"] = verdict(row)
    link = f"{base}/api/trials/{row['id']}"
    out["url"] = link
    out["mcap"] = (
        {"digest": row["mcap"], "size": row["mcap_size"], "url": f"{link}/data.mcap"}
        if row["mcap"]
        else None
    )
    out["logs"] = {
        stream: f"{link}/logs/{stream}" for stream in ("stdout", "stderr") if row[stream]
    }
    if full:
        out["manifest"] = row["manifest"]
        out["digest_topics"] = row["digest_topics"]
        out["worker"] = row["worker"]
    return out


def task(name: str) -> dict[str, Any]:
    spec = registry.get(name)
    return {
        "name": spec.name,
        "version": spec.version,
        "doc": spec.doc,
        "params": {
            p.name: {
                "type": p.kind.__name__,
                "default": p.default,
                "doc": p.doc,
                "minimum": p.minimum,
                "maximum": p.maximum,
                "choices": list(p.choices) or None,
                "describe": p.describe(),
            }
            for p in spec.params.declared.values()
        },
    }
