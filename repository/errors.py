"""Exceptions of the archive.

ArchiveError                 the archive could not do what was asked
├── BlobError                a blob of the content-addressed store
│   ├── BlobNotFound         no blob has that digest
│   └── BlobCorrupt          a blob's bytes no longer match its digest
├── RecordNotFound           no trial, commit or user by that name
├── HeldOut                  an episode of a held-out suite: its seed and record are
│                            the operator's until the suite version is retired
├── SchemaMismatch           the index was written by another version of labd
├── IndexUnreachable         the index's database did not answer when opened
├── IndexLost                the index's files changed under the running lab (its WAL
│                            deleted): writes are refused until the lab restarts
├── ManifestError            a manifest that is not one the lab writes (a key missing,
│                            unknown or of another type): it names the key
├── ExportError              a record could not be exported (format, content)
├── BackupError              a backup could not be made or restored (repository.backup)
│   ├── BackupDamaged        a backup is incomplete or its files were changed
│   │   └── BackupForged     it says other than the lab's signatures, or holds a link
│   ├── UnsafeFolder         a backup's folder others could have prepared or may reach
│   └── TargetNotEmpty       a restore's target already holds an archive
├── AccountError             an account could not be made or changed (name, password)
│   └── BadCredentials       a wrong user name or password
└── ReservationError         a booking the lab's rules refuse (the message names the rule)
    ├── SlotTaken            the slot overlaps someone's booking of that robot
    ├── OverLimit            over the operator's limits per day or per week
    ├── NotYourReservation   only the person who booked it may change it or read its key
    └── KeyRefused           a key that does not open this robot now (expired, not yet
        │                    valid, released, another robot's)
        └── UnknownKey       a key the lab never made (forged, mistyped, guessed, or
            │                one its owner's revocation replaced)
            └── MalformedKey not even shaped like a key (non-ASCII, wrong length)
"""

from __future__ import annotations


class ArchiveError(Exception):
    """The archive could not do what was asked; the message says what and why."""


class BlobError(ArchiveError):
    def __init__(self, digest: str, reason: str) -> None:
        self.digest = digest
        self.reason = reason
        super().__init__(f"blob {digest}: {reason}")


class BlobNotFound(BlobError):
    def __init__(self, digest: str) -> None:
        super().__init__(digest, "not in the store")


class BlobCorrupt(BlobError):
    def __init__(self, digest: str, actual: str) -> None:
        self.actual = actual
        super().__init__(digest, f"its bytes hash to {actual}; the copy in the store is damaged")


class RecordNotFound(ArchiveError):
    def __init__(self, kind: str, name: str) -> None:
        self.kind = kind
        self.name = name
        super().__init__(f"no {kind} {name!r}")


class HeldOut(ArchiveError):
    def __init__(self, trial_id: int) -> None:
        self.trial_id = trial_id
        super().__init__(
            f"trial {trial_id} is an episode of a held-out suite: its seed and record stay"
            " private until the operator retires that suite version (its evaluation shows"
            " how it ended)"
        )


class ManifestError(ArchiveError):
    """A manifest the lab would not have written: ``where`` is the dotted key
    (``manifest.seed``), ``problem`` what is wrong with it."""

    def __init__(self, where: str, problem: str) -> None:
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}")


class SchemaMismatch(ArchiveError):
    """The index has another schema than this labd reads: older (``labd migrate``
    upgrades it in place) or newer (this labd is too old for it)."""

    def __init__(self, found: int, expected: int) -> None:
        self.found = found
        self.expected = expected
        if found < expected:
            what = (
                f"the archive's index has schema {found}, from an older labd; this labd"
                f" reads schema {expected}: upgrade it in place with `labd migrate`"
                " (nothing is lost)"
            )
        else:
            what = (
                f"the archive's index has schema {found}, from a newer labd; this labd"
                f" reads schema {expected}: run the newer labd"
            )
        super().__init__(what)


class IndexUnreachable(ArchiveError):
    """The index's database did not answer when it was opened (a wrong address, a server
    that is down, a refused password); ``where`` is its URL without a password."""

    def __init__(self, where: str, reason: str) -> None:
        self.where = where
        self.reason = reason
        super().__init__(f"cannot reach the index at {where}: {reason}")


class IndexLost(ArchiveError):
    """The files of the index were deleted or replaced while the lab had them open
    (``repository.wal``): the lab refuses writes until it is restarted."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class ExportError(ArchiveError):
    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"export: {reason}")


class BackupError(ArchiveError):
    """A backup could not be made or restored; the message says why and what to do."""


class BackupDamaged(BackupError):
    """A backup that did not finish (no manifest), or whose files changed since."""

    def __init__(self, folder: str, reason: str) -> None:
        self.folder = folder
        self.reason = reason
        super().__init__(f"{folder} is not a whole backup: {reason}")


class BackupForged(BackupDamaged):
    """A backup that is not as the lab made it: its manifest or an index row says other
    than the lab's signature of it, or it holds a link (which labd never makes)."""

    def __init__(self, folder: str, reason: str) -> None:
        self.folder = folder
        self.reason = reason
        BackupError.__init__(self, f"{folder} is not the lab's backup as it made it: {reason}")


class UnsafeFolder(BackupError):
    """A folder ``labd backup`` will not write into, or through: one reached through a
    link another user could have made, one others may write to, one holding files that
    are not an earlier backup of this lab's."""

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class TargetNotEmpty(BackupError):
    """A restore's target already holds an archive (rows, or hosted repositories)."""

    def __init__(self, where: str, holds: str) -> None:
        self.where = where
        self.holds = holds
        super().__init__(
            f"{where} already holds {holds}; restore only into a new lab (an empty index,"
            " no hosted repositories)"
        )


class AccountError(ArchiveError):
    """An account could not be made or changed; the message says what to do."""


class BadCredentials(AccountError):
    def __init__(self) -> None:
        super().__init__("the user name or the password is wrong")


class ReservationError(ArchiveError):
    """A booking the lab's rules refuse; the message names the rule and what to do."""


class SlotTaken(ReservationError):
    def __init__(self, robot: str, message: str) -> None:
        self.robot = robot
        super().__init__(message)


class OverLimit(ReservationError):
    """Over a limit per day or per week that the operator set."""


class NotYourReservation(ReservationError):
    def __init__(self, reservation: int, owner: str, action: str) -> None:
        self.reservation = reservation
        self.owner = owner
        super().__init__(f"reservation {reservation} is {owner}'s; only they may {action}")


class KeyRefused(ReservationError):
    """A key that does not open this robot now; ``reason`` says why, for its holder."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class UnknownKey(KeyRefused):
    def __init__(
        self, reason: str = "the lab knows no such key; fetch your slot's key again"
    ) -> None:
        super().__init__(reason)


class MalformedKey(UnknownKey):
    """Not a key's shape: ``labd_rk_``, the reservation's number and 43 characters of
    URL-safe base64, all ASCII. Refused before anything is looked up."""

    def __init__(self) -> None:
        super().__init__(
            "this is not a key of this lab (labd_rk_, a number, _, 43 ASCII characters);"
            " copy it again"
        )
