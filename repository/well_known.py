"""Well-known names: the topics, files and artifacts that more than one part of the lab names.

Written once here, as mcap's ``well_known.py`` does, so that the recorder that writes a
name, the worker that files it, the archive that keeps it, the API that serves it and
``labd verify`` that reads it cannot drift apart. They are data as much as code: records
and exports made long ago hold these names, so they never change.
"""

from __future__ import annotations

# -- topics every record holds beside its task's own, and what its channels say ----------

CLOCK = "/clock"  # rosgraph_msgs/msg/Clock: simulation time, each tick
EPISODE = "/lab/episode"  # lab_msgs/msg/Episode: the tick, its reward and status, after each
ROSOUT = "/rosout"  # rcl_interfaces/msg/Log: the lab's log lines, and its clients'
UX_EVENTS = "/ux/events"  # a page's user-experience events, in a demonstration's record
SIDE_KEY = "labd.side"  # channel metadata: which side of the bridge published, lab or client

# -- a record: its file, its manifest, its attachments ------------------------------------

RECORD_FILE = "trial.mcap"  # in a trial's folder, beside rosbag2's metadata.yaml
MANIFEST_RECORD = "manifest"  # the MCAP metadata record holding the manifest ...
MANIFEST_KEY = "json"  # ... as canonical JSON under this key (repository.digests)
MANIFEST = "manifest.json"  # attachment: the manifest, indented for people
OUTCOME = "outcome.json"  # attachment: its status, outcome, reason and metrics
MODEL = "model.xml"  # attachment: the task's compiled model (MJCF) ...
MODEL_ASSETS = "model/"  # ... and the files it names (textures), under this prefix
LOGS = {"stdout": "controller.stdout.log", "stderr": "controller.stderr.log"}  # attachments


def side_logs(side: str) -> dict[str, str]:
    """A match leg's logs of the team on ``side``, as its record's attachments and files
    name them (its trial's ``stdout`` and ``stderr`` are home's)."""
    return {"stdout": f"{side}.stdout.log", "stderr": f"{side}.stderr.log"}


# -- derived artifacts, kept beside a record in the archive (repository.index.Derived) ---

SUMMARY = "summary.json"  # the record's page summary ...
SUMMARY_MEDIA_TYPE = "application/gzip"  # ... as gzip'd JSON
REPLAY = "replay.json"  # the replay's verdict (labd.replay)
VIDEO = "video.mp4"  # the task's first camera, rendered during the replay
SIGNED = ".sig"  # an export artifact's signature is kept under its name and this suffix

# -- files given to people, and read back by ``labd verify`` -----------------------------

SIGNATURE_SIDECAR = ".sig.json"  # a downloaded record's signature: trial-12.mcap.sig.json
EXPORT_SIGNATURE = "labd-signature.json"  # an export's own signature, in its folder
PARQUET_FILE = "data.parquet"  # a Parquet export's one file
