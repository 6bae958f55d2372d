"""Exceptions of the scheduler.

TrialError                   a trial could not be prepared or run
├── RepositoryError          the repository could not be read, fetched or resolved
├── ControllerConfigError    lab.toml is missing or does not say what the lab needs
└── RequirementsError        the repository's requirements could not be installed
"""

from __future__ import annotations


class TrialError(Exception):
    """A trial could not be prepared or run; the message says what a person can do."""


class RepositoryError(TrialError):
    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(f"{source}: {reason}")


class ControllerConfigError(TrialError):
    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"lab.toml: {reason}")


class RequirementsError(TrialError):
    def __init__(self, reason: str, log: str = "") -> None:
        self.reason = reason
        self.log = log
        super().__init__(f"requirements: {reason}")
