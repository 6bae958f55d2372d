"""``lab.toml``: what a controller repository tells the lab.

[controller]
command = ["python", "controller.py"]   # run from the repository root
task = "icreate-maze"                    # default task
requirements = "requirements.txt"        # optional: installed in the build step
realtime = false                         # optional: true = wall clock, no lockstep

Both files are read through ``scheduler.files.RepositoryFiles``: as regular files of
the repository, never through a symbolic link (which would be read on the lab's host).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from scheduler.errors import ControllerConfigError, RepositoryFileError
from scheduler.files import RepositoryFiles

FILE = "lab.toml"
KEYS = ("command", "task", "requirements", "realtime")


@dataclass(frozen=True)
class ControllerConfig:
    command: tuple[str, ...]
    task: str | None
    requirements: str | None
    realtime: bool
    text: str  # the file as written, for the trial record


def load(code: Path | RepositoryFiles) -> ControllerConfig:
    """Read and check ``lab.toml`` at the root of the checkout ``code``.

    ``RepositoryFileError`` when lab.toml or the requirements file is a symbolic link
    (or passes through one), ``ControllerConfigError`` for anything else amiss.
    """
    files = code if isinstance(code, RepositoryFiles) else RepositoryFiles(code)
    if not files.is_file(FILE):
        raise ControllerConfigError(
            f"the repository has no {FILE} at its root; add one with a [controller] table "
            'naming the command, e.g. command = ["python", "controller.py"]'
        )
    try:
        text = files.read_text(FILE)
        data = tomllib.loads(text)
    except RepositoryFileError as err:
        raise ControllerConfigError(err.reason) from None
    except tomllib.TOMLDecodeError as err:
        raise ControllerConfigError(f"it is not valid TOML: {err}") from None
    table = data.get("controller")
    if not isinstance(table, dict):
        raise ControllerConfigError("it needs a [controller] table")
    unknown = sorted(set(table) - set(KEYS))
    if unknown:
        raise ControllerConfigError(
            f"[controller] has no key {unknown[0]!r}; the keys are {', '.join(KEYS)}"
        )
    return ControllerConfig(
        command=_command(table.get("command")),
        task=_optional_str(table, "task"),
        requirements=_requirements(files, table),
        realtime=_bool(table, "realtime"),
        text=text,
    )


def _command(value: Any) -> tuple[str, ...]:
    if value is None:
        raise ControllerConfigError('[controller] needs command, e.g. ["python", "controller.py"]')
    if isinstance(value, str):
        raise ControllerConfigError(
            f'command must be a list of strings, e.g. ["python", "controller.py"], not {value!r}'
        )
    if not isinstance(value, list) or not value:
        raise ControllerConfigError("command must be a non-empty list of strings")
    if not all(isinstance(part, str) and part for part in value):
        raise ControllerConfigError("every item of command must be a non-empty string")
    return tuple(value)


def _optional_str(table: dict[str, Any], key: str) -> str | None:
    value = table.get(key)
    if value is not None and not isinstance(value, str):
        raise ControllerConfigError(f"{key} must be a string, not {value!r}")
    return value


def _bool(table: dict[str, Any], key: str) -> bool:
    value = table.get(key, False)
    if not isinstance(value, bool):
        raise ControllerConfigError(f"{key} must be true or false, not {value!r}")
    return value


def _requirements(files: RepositoryFiles, table: dict[str, Any]) -> str | None:
    """The requirements file's name, once it is known to be a regular UTF-8 file of
    the repository (so the install step may be handed it, and its hash taken)."""
    name = _optional_str(table, "requirements")
    if name is None:
        return None
    relative = PurePosixPath(name)
    if relative.is_absolute() or ".." in relative.parts:
        raise ControllerConfigError(f"requirements must be a path inside the repository: {name!r}")
    if not files.is_file(name):
        raise ControllerConfigError(f"requirements names {name!r}, which is not in the repository")
    files.read_text(name)  # refused here if it is not text, before anything is installed
    return name
