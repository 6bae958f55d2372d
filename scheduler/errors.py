"""Exceptions of the scheduler.

TrialError                      a trial could not be prepared or run
├── RepositoryError             the repository could not be read, fetched or resolved
│   ├── SchemeNotAllowed        its kind of URL is not one this lab accepts
│   ├── Unreachable             no such host or path, refused, or it needs a credential
│   ├── HostNotAllowed          its host is a loopback, private or other non-public address
│   ├── RefNotFound             the ref is no branch, tag or commit of it
│   ├── TooLarge                it is over the lab's size limit
│   │   └── CheckoutTooLarge    a commit's files add up to more than the lab checks out
│   ├── FetchTimeout            fetching it took longer than the lab's time limit
│   └── SubmoduleNotAllowed     a submodule's URL is outside the lab's allow-list
├── RepositoryFileError         a file the lab reads from a checkout is a link, or no file
│   └── FileNotInRepository     there is nothing at that name
├── ControllerConfigError       lab.toml is missing or does not say what the lab needs
├── RequirementsError           the repository's requirements could not be installed
├── NodePackagesError           its npm packages (package-lock.json) could not be installed
└── DataUnavailable             a pinned record is gone, damaged, or no longer its digest
QueueError                      a queue operation was refused
├── InvalidRequest              a submission names an unknown task, a bad parameter or seed
│   └── InvalidData             lab.toml's [data] matches nothing, too much, or what is not public
├── QuotaExceeded               a submitter is over a limit the operator set
├── Busy                        the lab has as many submissions in hand as it takes
├── NotYours                    a trial may be changed only by its submitter
├── EpisodeOfEvaluation         an evaluation's episode is cancelled with its evaluation only
├── LegOfMatch                  a match's leg is cancelled with its match only
├── OverBudget                  a held-out suite takes only so many evaluations a commit, a day
│   └── OverLadderBudget        a user enters only so many commits on ladders a day
├── FilingRefused               a worker's filing says what its record does not hold
└── RemoteError                 talking to a lab's HTTP API went wrong
    ├── LabUnreachable          no lab answered at that address
    └── ApiRefused              the lab answered with an error (its status and words)

Each says what a person can do about it. None shows a credential: the URLs in their
messages are masked (``repository.masking``: passwords, query values), and a fetch's
network failure is said in the same words whatever git said (``Unreachable``).
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence

from repository.masking import mask_text, mask_url
from repository.units import MiB


class TrialError(Exception):
    """A trial could not be prepared or run; the message says what a person can do."""


class RepositoryError(TrialError):
    def __init__(self, source: str, reason: str, *, message: str | None = None) -> None:
        self.source = source
        self.reason = reason
        super().__init__(message or f"{mask_url(source)}: {reason}")


class SchemeNotAllowed(RepositoryError):
    """The URL's scheme (or a local path, ``file``) is not in the operator's list."""

    def __init__(self, source: str, scheme: str, allowed: Iterable[str]) -> None:
        self.scheme = scheme
        self.allowed = tuple(sorted(allowed))
        if scheme == "file":
            # The same words whatever is at that path: a refusal tells nothing of the host.
            what = (
                "local paths and file:// URLs are not allowed here (a lab's operator allows"
                " them with --allow-local-repos)"
            )
        else:
            what = f"scheme {scheme!r} is not allowed here"
        super().__init__(source, f"{what}; this lab accepts {accepted(self.allowed)}")


class Unreachable(RepositoryError):
    """Fetching failed: no such host or repository, refused, or authentication needed.

    Every network failure is said in the same words: git's own (``detail``, for the
    lab's log) tell a closed port from an HTTP, a TLS or a WebSocket one, and quoted to
    the submitter they would map the ports the lab reaches. ``auth``: the server asked
    for a credential the lab does not have. ``local``: a folder on the lab's machine
    (allowed by its operator), whose ``detail`` is said.
    """

    def __init__(
        self, source: str, detail: str, *, auth: bool = False, local: bool = False
    ) -> None:
        self.detail = detail
        self.auth = auth
        if auth:
            hint = (
                "the repository is private and this lab has no credential for it: make it"
                " public, or ask the lab's operator to add a deploy key or token"
            )
        else:
            hint = "check the URL, and that the repository exists and is public"
        what = "the repository could not be fetched"
        if local:  # a folder of the lab's machine, which its operator opened to submitters
            what = f"could not be fetched ({detail})"
        super().__init__(source, f"{what}; {hint}")


class HostNotAllowed(RepositoryError):
    """The repository's host is, or its name resolves to, an address that is not public
    (loopback, link-local, private, unspecified, multicast, reserved): refused before any
    connection, unless the operator allows private hosts. ``kind`` is the address's;
    ``name``: the host is a name that resolves to it."""

    def __init__(self, source: str, host: str, kind: str, *, name: bool = False) -> None:
        self.host = host
        self.kind = kind
        what = "resolves to" if name else "is"
        super().__init__(
            source,
            f"its host {host} {what} a {kind} address, and this lab fetches only from public"
            " ones; give the repository's public URL (a lab's operator allows private hosts"
            " with --allow-private-hosts)",
        )


class RefNotFound(RepositoryError):
    """The ref names no branch, tag or commit of the repository (or is ambiguous)."""

    def __init__(self, source: str, ref: str | None, *, ambiguous: bool = False) -> None:
        self.ref = ref
        shown = mask_url(source)
        if ref is None:
            reason = "has no commits on its default branch; push one, or name a branch or tag"
            message = None
        elif ambiguous:
            reason = f"{ref!r} is the start of more than one commit; give more of its digits"
            message = f"{ref!r} is the start of more than one commit of {shown}; give more digits"
        else:
            reason = f"{ref!r} is not a branch, tag or commit of it"
            message = (
                f"{ref!r} is not a branch, tag or commit of {shown}; check the name, and"
                " that it has been pushed"
            )
        super().__init__(source, reason, message=message)


class TooLarge(RepositoryError):
    """The repository (its mirror, all branches and tags) is over the size limit."""

    def __init__(self, source: str, limit: int, size: int) -> None:
        self.limit = limit
        self.size = size
        super().__init__(
            source,
            f"is larger than this lab's limit of {_mib(limit)} (at least {_mib(size)},"
            " all branches and tags); keep large files out of the repository, or ask the"
            " lab's operator for a higher limit",
        )


class CheckoutTooLarge(TooLarge):
    """A commit whose files (its submodules' included) add up to more bytes, or more
    files, than the lab writes out for a trial: found from git's trees, before anything
    is expanded. A repository compresses well (1 GiB of zeros is 1 MiB in git), so this
    is apart from its size. Counting stops past the limit, so ``size`` is a lower bound."""

    def __init__(
        self, source: str, commit: str, limit: int, size: int, *, files: bool = False
    ) -> None:
        self.commit = commit
        self.limit = limit
        self.size = size
        self.files = files
        if files:
            what = f"{limit:,} files"
            counted = f"{size:,} files"
        else:
            what = f"{_mib(limit)} (--max-checkout-mb)"
            counted = _mib(size)
        # Counting stopped past the limit: the count says more only when it is well past.
        more = f" (at least {counted})" if counted != what.split(" (")[0] else ""
        RepositoryError.__init__(
            self,
            source,
            f"commit {commit[:12]} checks out to more than this lab's limit of {what}{more};"
            " keep large files, or many, out of the commit, or ask the lab's operator for a"
            " higher limit",
        )


class FetchTimeout(RepositoryError):
    """Fetching took longer than the time limit (a slow or stalled server, or a big repo)."""

    def __init__(self, source: str, seconds: float) -> None:
        self.seconds = seconds
        super().__init__(
            source,
            f"took longer than this lab's limit of {seconds:g} s to fetch; try again later"
            " (the server may be slow), or make the repository smaller",
        )


class SubmoduleNotAllowed(RepositoryError):
    """A submodule's URL does not start with any prefix of the operator's allow-list."""

    def __init__(self, source: str, path: str, url: str, allowed: Iterable[str]) -> None:
        self.path = path
        self.url = mask_url(url)
        self.allowed = tuple(allowed)
        if self.allowed:
            where = "follows submodules only from " + ", ".join(self.allowed)
        else:
            where = "follows no submodules"
        super().__init__(
            source,
            f"submodule {path!r} ({self.url}) is not allowed here; this lab {where}. Copy that"
            " code into the repository instead, or ask the lab's operator",
        )


class RepositoryFileError(TrialError):
    """A file the lab reads from a checkout (``lab.toml``, the requirements...) is a
    symbolic link, passes through one, or is no regular file; ``name`` is its path in
    the repository. The message tells nothing of what a link points at on the host."""

    def __init__(self, name: str, reason: str) -> None:
        self.name = name
        self.reason = reason
        super().__init__(f"{name}: {reason}")


class FileNotInRepository(RepositoryFileError):
    def __init__(self, name: str, reason: str = "it is not in the repository") -> None:
        super().__init__(name, reason)


class ControllerConfigError(TrialError):
    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"lab.toml: {reason}")


class RequirementsError(TrialError):
    def __init__(self, reason: str, log: str = "") -> None:
        self.reason = reason
        self.log = log
        super().__init__(f"requirements: {reason}")


class NodePackagesError(TrialError):
    def __init__(self, reason: str, log: str = "") -> None:
        self.reason = reason
        self.log = log
        super().__init__(f"npm packages: {reason}")


class DataUnavailable(TrialError):
    """A record the trial pinned cannot be given to the controller as it was pinned."""

    def __init__(self, trial: int, reason: str) -> None:
        self.trial = trial
        self.reason = reason
        super().__init__(f"the data the trial learns from: trial {trial}'s record {reason}")


class QueueError(Exception):
    """A queue operation was refused (no such trial, not yours to cancel...)."""


class QuotaExceeded(QueueError):
    """A submitter is over a limit the operator set."""


class Busy(QueueError):
    """The lab is resolving as many submissions as it takes at once, and as many wait:
    try again in ``retry_after`` seconds."""

    def __init__(self, in_hand: int, retry_after: float) -> None:
        self.in_hand = in_hand
        self.retry_after = retry_after
        super().__init__(
            f"the lab has {in_hand} submissions in hand already, as many as it takes;"
            f" try again in {retry_after:g} s"
        )


def accepted(schemes: Collection[str]) -> str:
    """``https, ssh, git URLs and local paths``: what a lab with these schemes accepts."""
    order = ["https", "http", "ssh", "git"]
    rank = {name: i for i, name in enumerate(order)}
    names = sorted((s for s in schemes if s != "file"), key=lambda s: (rank.get(s, 9), s))
    urls = f"{', '.join(names)} URLs" if names else ""
    local = "local paths" if "file" in schemes else ""
    return " and ".join(part for part in (urls, local) if part) or "no repositories at all"


def _mib(size: int) -> str:
    return f"{size / MiB:.1f} MiB"


class NotYours(QueueError):
    """Only a trial's (or an evaluation's) submitter may cancel it, or otherwise change it."""

    def __init__(self, trial_id: int, owner: str, action: str, *, what: str = "trial") -> None:
        self.trial_id = trial_id
        self.owner = owner
        self.action = action
        super().__init__(f"{what} {trial_id} is {owner}'s; only they may {action} it")


class EpisodeOfEvaluation(QueueError):
    """An episode of an evaluation is cancelled with its evaluation, never alone: an
    evaluation counts every episode, so cancelling the ones it would fail buys nothing."""

    def __init__(self, trial_id: int, evaluation_id: int) -> None:
        self.trial_id = trial_id
        self.evaluation_id = evaluation_id
        super().__init__(
            f"trial {trial_id} is an episode of evaluation {evaluation_id}: an evaluation"
            f" counts every episode, so cancel the whole evaluation"
            f" (POST /api/evaluations/{evaluation_id}/cancel), which makes it partial"
        )


class LegOfMatch(QueueError):
    """A match's leg is cancelled with its match, never alone: cancelling the legs it
    would lose would buy a better score."""

    def __init__(self, trial_id: int, match_id: int) -> None:
        self.trial_id = trial_id
        self.match_id = match_id
        super().__init__(
            f"trial {trial_id} is a leg of match {match_id}: cancel the whole match"
            f" (POST /api/matches/{match_id}/cancel), which then counts for no one"
        )


class OverBudget(QueueError):
    """A held-out suite takes only so many evaluations of one commit, and of one user a
    day, so that nobody can probe its episodes evaluation by evaluation."""

    def __init__(self, what: str, used: int, limit: int, when: str) -> None:
        self.used = used
        self.limit = limit
        super().__init__(
            f"{what} has used {used} of its {limit} held-out evaluation"
            f"{'' if limit == 1 else 's'} {when} (the operator's budget: a held-out suite is"
            " scored, not probed); evaluate on the public dev suite instead"
        )


class OverLadderBudget(OverBudget):
    """A user enters only so many commits on ladders a day: each entry queues matches."""

    def __init__(self, who: str, used: int, limit: int) -> None:
        self.used = used
        self.limit = limit
        QueueError.__init__(
            self,
            f"{who} has entered {used} commit{'' if used == 1 else 's'} on ladders in the last"
            f" 24 hours, the operator's budget of {limit}; try again later",
        )


class FilingRefused(QueueError):
    """A worker filed a trial with what its record does not hold (``scheduler.filing``):
    nothing was filed or signed; ``problems`` say each difference."""

    def __init__(self, trial_id: int, problems: Sequence[str]) -> None:
        self.trial_id = trial_id
        self.problems = tuple(problems)
        super().__init__(
            f"trial {trial_id} was not filed (nor signed): the filing does not say what"
            f" its record holds: {'; '.join(self.problems)}"
        )


class InvalidRequest(QueueError):
    """The request itself is wrong (an unknown task, a bad parameter or seed)."""


class InvalidData(InvalidRequest):
    """lab.toml's ``[data]`` cannot be pinned: it matches nothing or too much, names a
    trial that is not public, has no readable record, or is over the size limit."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"lab.toml's [data]: {reason}")


class RemoteError(QueueError):
    """Talking to a lab's HTTP API went wrong (the message says how)."""


class LabUnreachable(RemoteError):
    """Nothing answered at the lab's address, after a few tries."""

    def __init__(self, server: str, detail: str) -> None:
        self.server = server
        self.detail = detail
        super().__init__(
            f"cannot reach the lab at {mask_url(server)} ({mask_text(detail)}); is `labd serve`"
            " running there? Give its address with --server URL or LABD_SERVER"
        )


class ApiRefused(RemoteError):
    """The lab answered a request with an error status."""

    def __init__(self, status: int, message: str, method: str = "", path: str = "") -> None:
        self.status = status
        self.message = message
        self.method = method
        self.path = path
        super().__init__(f"{message} (HTTP {status})")
