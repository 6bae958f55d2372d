"""What makes a record folder a rosbag2 bag: ``metadata.yaml`` and the MCAP's ROS 2 extras.

rosbag2 (ROS 2 Jazzy) and rosbags 0.11 open a folder that holds MCAP files and a
``metadata.yaml`` in rosbag2's format 9: storage ``mcap``, the files' names, start and
duration, and per topic its type, ``cdr``, the offered QoS profiles (a YAML list, with
enum names) and the RIHS01 type hash, laid out as rosbags' own writer does. rosbags
matches each topic there to the MCAP channel of the same name, type and QoS, so the
channel carries the same profiles (``offered_qos_profiles``, as one YAML text) and type
hash (``topic_type_hash``) in its metadata, as rosbag2's MCAP storage writes them. The
same bag information, stored in the MCAP as the ``rosbag2`` metadata record, lets a file
that travelled alone become a bag again (``write_bag_metadata``).
"""

from __future__ import annotations

import functools
import io
import re
import textwrap
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2.metadata import dump_qos_v9
from ruamel.yaml import YAML

from repository.mcapfile import seeking
from repository.well_known import RECORD_FILE

BAG_METADATA = "metadata.yaml"
BAG_RECORD = "rosbag2"  # the MCAP metadata record rosbag2's storage writes, and its key:
BAG_RECORD_KEY = "serialized_metadata"
BAG_VERSION = 9  # rosbag2's metadata format since Jazzy
ROS_DISTRO = "jazzy"  # whose type definitions and hashes the record holds

_INFINITE = QosTime(9_223_372_036, 854_775_807)  # how rosbag2 records an unbounded duration


class BagTopic(NamedTuple):
    """One recorded topic, as the bag metadata describes it."""

    name: str
    type_name: str
    type_hash: str  # RIHS01
    latched: bool  # offered as transient local
    message_count: int


def qos(latched: bool) -> Qos:
    """The QoS a lab publisher offers, as rosbag2 records offered ones (history unknown).

    Latched topics are transient local, so ``ros2 bag play`` gives late subscribers the
    last ``/tf_static`` or ``/goal`` as the lab did.
    """
    durability = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
    return Qos(
        QosHistory.UNKNOWN,
        0,
        QosReliability.RELIABLE,
        durability,
        _INFINITE,
        _INFINITE,
        QosLiveliness.AUTOMATIC,
        _INFINITE,
        False,
    )


def channel_metadata(type_hash: str, latched: bool) -> dict[str, str]:
    """The metadata of a topic's MCAP channel, as rosbag2's MCAP storage writes it."""
    return {"offered_qos_profiles": _qos_text(latched), "topic_type_hash": type_hash}


@functools.cache
def _qos_text(latched: bool) -> str:
    return to_yaml(dump_qos_v9([qos(latched)]))


def bag_info(topics: Iterable[BagTopic], start: int, end: int) -> dict[str, Any]:
    """rosbag2's ``rosbag2_bagfile_information`` for one MCAP file (times in ns)."""
    topics = list(topics)
    count = sum(t.message_count for t in topics)
    if not count:
        start = end = 0
    return {
        "version": BAG_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": end - start},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.type_name,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": dump_qos_v9([qos(t.latched)]),
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.message_count,
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [RECORD_FILE],
        "files": [
            {
                "path": RECORD_FILE,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": end - start},
                "message_count": count,
            }
        ],
        "custom_data": None,
        "ros_distro": ROS_DISTRO,
    }


def to_yaml(value: Any) -> str:
    """Block-style YAML in the mappings' own order (rosbag2's), each hash on one line.

    The bag information is made at the end of every trial, and the YAML library takes
    about 13 ms for it; so what holds only mappings, lists, integers, booleans, None
    and plain words is written here, as the library writes it (a test holds the two
    to the same text), and anything else by the library.
    """
    fast: list[str] = []
    if _plain(value, 0, fast, in_list=False):
        return "\n".join(fast).strip()
    return _library_yaml(value)


_WORD = re.compile(r"[A-Za-z/_][A-Za-z0-9_/.\-]*")
_NOT_WORDS = frozenset(
    {"true", "false", "null", "yes", "no", "on", "off", "y", "n", "nan", "inf"}
)  # (any case): what a reader would take for something else


def _scalar(value: Any) -> str | None:
    """``value`` as the YAML library writes it in block style; None if not simple."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        if value == "":
            return "''"
        if _WORD.fullmatch(value) and value.lower() not in _NOT_WORDS:
            return value
    return None


def _plain(value: Any, indent: int, out: list[str], *, in_list: bool) -> bool:
    """Append ``value`` (a mapping or a list) as block YAML lines at ``indent``; False
    if any part of it is not simple (nothing usable is appended then)."""
    pad = " " * indent
    if isinstance(value, dict):
        if not value:
            return False
        first = True
        for key, item in value.items():
            if not isinstance(key, str) or _scalar(key) != key:
                return False
            lead = (pad[:-2] + "- ") if in_list and first else pad
            first = False
            if isinstance(item, dict | list):
                if not item:
                    out.append(f"{lead}{key}: {'{}' if isinstance(item, dict) else '[]'}")
                    continue
                out.append(f"{lead}{key}:")
                nested = indent + 2 if isinstance(item, dict) else indent
                if not _plain(item, nested, out, in_list=False):
                    return False
            else:
                text = _scalar(item)
                if text is None:
                    return False
                out.append(f"{lead}{key}: {text}")
        return True
    if isinstance(value, list):
        for item in value:
            if isinstance(item, dict):
                if not _plain(item, indent + 2, out, in_list=True):
                    return False
            elif isinstance(item, list):
                return False
            else:
                text = _scalar(item)
                if text is None:
                    return False
                out.append(f"{pad}- {text}")
        return True
    return False


def _library_yaml(value: Any) -> str:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.width = 4096
    yaml.representer.sort_base_mapping_type_on_output = False
    out = io.StringIO()
    yaml.dump(value, out)
    return out.getvalue().strip()


def write_bag_yaml(folder: Path, info: str) -> Path:
    """Write ``folder/metadata.yaml`` from the bag information's YAML (``to_yaml``).

    The file is written whole or not at all (renamed into place).
    """
    path = folder / BAG_METADATA
    tmp = path.with_suffix(".yaml.tmp")
    try:
        tmp.write_text(f"rosbag2_bagfile_information:\n{textwrap.indent(info, '  ')}\n", "utf-8")
        return tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bag_metadata(mcap: str | Path) -> Path:
    """Write ``metadata.yaml`` next to a record's MCAP file, making its folder a bag again.

    For a file that travelled alone (a download, a blob store): the bag information comes
    from the file's own ``rosbag2`` record, with the file's present name. Returns the path.
    """
    mcap = Path(mcap)
    with mcap.open("rb") as stream:
        records = [m for m in seeking(stream).iter_metadata() if m.name == BAG_RECORD]
    if not records:
        raise ValueError(f"{mcap} has no {BAG_RECORD} metadata record: labd did not write it")
    info = YAML(typ="safe").load(records[-1].metadata[BAG_RECORD_KEY])
    info["relative_file_paths"] = [mcap.name]
    for entry in info.get("files", []):
        entry["path"] = mcap.name
    return write_bag_yaml(mcap.parent, to_yaml(info))


def mcap_path(path: str | Path) -> Path:
    """The MCAP file of a record given as its folder or as the file itself."""
    path = Path(path)
    return path / RECORD_FILE if path.is_dir() else path
