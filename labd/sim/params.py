"""Task parameters: declared with defaults and limits, validated before a task is built.

A trial's parameters are part of its manifest, so a task never reads a value that
was not declared here: an unknown name, a value of the wrong kind or out of range is
refused with the list of valid parameters.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from labd.errors import ParamError

Value = int | float | bool | str


@dataclass(frozen=True)
class Param:
    """One declared parameter."""

    name: str
    default: Value
    doc: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Value, ...] = ()
    odd: bool = False  # maze sizes must be odd

    @property
    def kind(self) -> type:
        return type(self.default)

    def describe(self) -> str:
        """``maze_size (odd int, 5..31, default 9): the maze's side in cells``."""
        kind = ("odd " if self.odd else "") + self.kind.__name__
        limits = ""
        if self.choices:
            limits = ", one of " + "/".join(str(c) for c in self.choices)
        elif self.minimum is not None or self.maximum is not None:
            limits = f", {_fmt(self.minimum)}..{_fmt(self.maximum)}"
        return f"{self.name} ({kind}{limits}, default {self.default}): {self.doc}"

    def convert(self, value: Any) -> Value:
        """``value`` as this parameter's kind (strings from the command line are parsed)."""
        kind = self.kind
        if isinstance(value, str) and kind is not str:
            value = _parse(value, kind)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not kind:
            raise ParamError(self.name, f"must be a {kind.__name__}, got {value!r}")
        if self.choices and value not in self.choices:
            raise ParamError(self.name, f"must be one of {', '.join(map(str, self.choices))}")
        if isinstance(value, int | float) and not isinstance(value, bool):
            if self.minimum is not None and value < self.minimum:
                raise ParamError(self.name, f"must be at least {_fmt(self.minimum)}, got {value}")
            if self.maximum is not None and value > self.maximum:
                raise ParamError(self.name, f"must be at most {_fmt(self.maximum)}, got {value}")
            if isinstance(value, float) and not math.isfinite(value):
                raise ParamError(self.name, f"must be a finite number, got {value}")
        if self.odd and isinstance(value, int) and value % 2 == 0:
            raise ParamError(self.name, f"must be odd, got {value}")
        assert isinstance(value, int | float | bool | str)
        return value


class Params:
    """The declared parameters of one task."""

    def __init__(self, params: Iterable[Param]) -> None:
        self.declared = {p.name: p for p in params}

    def defaults(self) -> dict[str, Value]:
        return {name: p.default for name, p in self.declared.items()}

    def validate(self, given: Mapping[str, Any]) -> dict[str, Value]:
        """Every declared parameter, from ``given`` or its default; ParamError otherwise."""
        unknown = sorted(set(given) - set(self.declared))
        if unknown:
            raise ParamError(unknown[0], "is not a parameter of this task", valid=self.help_lines())
        values = self.defaults()
        for name, value in given.items():
            try:
                values[name] = self.declared[name].convert(value)
            except ParamError as err:
                raise ParamError(err.name, err.reason, valid=self.help_lines()) from None
        return values

    def help_lines(self) -> list[str]:
        return [p.describe() for p in self.declared.values()]


def _parse(text: str, kind: type) -> Value:
    if kind is bool:
        lowered = text.lower()
        if lowered in ("true", "1", "yes", "on"):
            return True
        if lowered in ("false", "0", "no", "off"):
            return False
        raise ValueError(text)
    try:
        return kind(text)  # type: ignore[no-any-return]
    except ValueError:
        return text  # convert() then says what kind it must be


def _fmt(value: float | None) -> str:
    if value is None:
        return ""
    return str(int(value)) if float(value).is_integer() else str(value)
