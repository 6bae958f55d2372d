"""The content-addressed blob store: bytes named by their sha256, in a folder or a bucket.

A blob's name is its digest, ``"sha256:<64 hex digits>"``; it lives at
``ROOT/sha256/<first 2 hex>/<hex>``, where ROOT is a local folder (a path or a
``file://`` URL) or an object store prefix reached through fsspec (``s3://bucket/prefix``,
with s3fs options such as ``{"endpoint_url": ..., "key": ..., "secret": ...}``).

- Writing streams the bytes once, hashing them on the way, to a temporary name under
  ``ROOT/tmp/``, and only then moves them to their final name, so a crash never leaves
  part of a blob under a name that promises all of it. A blob that already exists is
  not written again: blobs are immutable. Local blobs are made read-only (0o444); on a
  local disk the move is a hard link, which never replaces an existing blob even when two
  writers race. An object store has no link: there, two writers of the same bytes at
  the same moment may both copy them into place, which leaves the same bytes.
- A blob found under the name is read and checked first, though: if it was damaged
  (its bytes no longer hash to its name), the bytes being stored, which do, take its
  place. So storing what a record should hold (a rerun that reproduced, say) heals it,
  and a name never keeps bytes that do not match it once the right ones came again.
- Reading checks the bytes against their name as they stream by (``iter_chunks``); a
  mismatch raises ``BlobCorrupt`` once the last chunk has been read, so a consumer that
  writes somewhere must be ready to throw it away (``copy_to`` does).
- A digest is checked before it names anything, so a malformed one is a ``BlobError``,
  never a path outside the store.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import io
import logging
import os
import re
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import fsspec  # type: ignore[import-untyped]
from fsspec.implementations.local import LocalFileSystem  # type: ignore[import-untyped]

from repository.errors import BlobCorrupt, BlobError, BlobNotFound
from repository.masking import mask_url
from repository.units import MiB

ALGORITHM = "sha256"
CHUNK_SIZE = MiB  # bytes read or written at a time
READ_ONLY = 0o444
TMP = "tmp"  # under the root: blobs being written
_DIGEST = re.compile(r"sha256:([0-9a-f]{64})")

log = logging.getLogger("repository.blobs")


def parse_digest(digest: object) -> str:
    """The hex part of a digest ``"sha256:<64 lowercase hex digits>"``; BlobError if not one."""
    if not isinstance(digest, str):
        raise BlobError(repr(digest), "a digest must be a string 'sha256:<64 hex digits>'")
    match = _DIGEST.fullmatch(digest)
    if match is None:
        shown = digest if len(digest) <= 80 else digest[:77] + "..."
        raise BlobError(repr(shown), "not a digest: expected 'sha256:' and 64 lowercase hex digits")
    return match.group(1)


def digest_of(data: bytes) -> str:
    """The digest that names ``data`` in a store."""
    return f"{ALGORITHM}:{hashlib.sha256(data).hexdigest()}"


class BlobStore:
    """Blobs under ``url``: a local folder, ``file://...`` or ``s3://bucket/prefix``.

    ``storage_options`` go to the fsspec filesystem (s3fs: ``endpoint_url``, ``key``,
    ``secret``, ...). Nothing is created until the first blob is written.
    """

    def __init__(self, url: str, storage_options: Mapping[str, Any] | None = None) -> None:
        self.url = url
        fs, root = fsspec.core.url_to_fs(url, **dict(storage_options or {}))
        self._fs: Any = fs
        self._root: str = root.rstrip("/")
        self.local = isinstance(fs, LocalFileSystem)
        # Operations that failed since the store was opened, by kind: ``read`` and
        # ``write`` (the disk or the object store), ``corrupt`` (a damaged blob found).
        # A blob that is not there is no error of the store. For the lab's metrics.
        self.errors: collections.Counter[str] = collections.Counter()

    def __repr__(self) -> str:
        return f"BlobStore({mask_url(self.url)!r})"  # logs show it: no credential

    def path(self, digest: str) -> str:
        """Where the blob named ``digest`` lives, in the store's filesystem."""
        hex_ = parse_digest(digest)
        return f"{self._root}/{ALGORITHM}/{hex_[:2]}/{hex_}"

    # -- writing -------------------------------------------------------------------------

    def put_file(self, path: str | Path) -> str:
        """Store the bytes of a local file; returns their digest."""
        with Path(path).open("rb") as stream:
            return self.put_stream(stream)

    def put_bytes(self, data: bytes) -> str:
        """Store ``data``; returns its digest."""
        return self.put_stream(io.BytesIO(data))

    def put_stream(self, stream: BinaryIO) -> str:
        """Store what ``stream`` yields until its end; returns the digest.

        If reading fails, the error propagates and nothing is stored.
        """
        tmp = f"{self._root}/{TMP}/{uuid.uuid4().hex}"
        with self._counting("write"):
            self._fs.makedirs(f"{self._root}/{TMP}", exist_ok=True)
        hasher = hashlib.sha256()
        size = 0
        try:
            with self._counting("write"), self._fs.open(tmp, "wb") as out:
                while chunk := stream.read(CHUNK_SIZE):
                    hasher.update(chunk)
                    out.write(chunk)
                    size += len(chunk)
            digest = f"{ALGORITHM}:{hasher.hexdigest()}"
            final = self.path(digest)
            with self._counting("write"):
                if self.local:
                    created = self._settle_local(tmp, final)
                else:
                    created = self._settle_remote(tmp, final)
        finally:
            self._discard(tmp)
        if created:
            log.debug("%s: stored %s, %d bytes", self, digest, size)
        return digest

    def _settle_local(self, tmp: str, final: str) -> bool:
        """Link ``tmp`` to its final name unless a blob is there; whether it was new."""
        os.chmod(tmp, READ_ONLY)
        os.makedirs(os.path.dirname(final), exist_ok=True)
        try:
            os.link(tmp, final)  # fails, atomically, if the blob exists
        except FileExistsError:
            return self._heal(tmp, final)
        except OSError:  # a filesystem without hard links: move it, if still absent
            if os.path.exists(final):
                return self._heal(tmp, final)
            os.replace(tmp, final)
        return True

    def _settle_remote(self, tmp: str, final: str) -> bool:
        if self._fs.exists(final):
            return self._heal(tmp, final)
        self._fs.mv(tmp, final)  # an object store copies it whole into place
        return True

    def _heal(self, tmp: str, final: str) -> bool:
        """A blob is at ``final`` already: keep it if whole, else put ``tmp``, whose bytes
        hash to the name, in its place. Whether the store's copy was replaced."""
        digest = f"{ALGORITHM}:{final.rsplit('/', 1)[1]}"
        try:
            self.verify(digest)
            return False
        except BlobCorrupt:
            log.error(
                "%s: blob %s was damaged; the same bytes, stored again, replace it", self, digest
            )
        except BlobNotFound:  # removed meanwhile: place it
            pass
        if self.local:
            os.replace(tmp, final)
        else:
            self._fs.mv(tmp, final)
        return True

    def _discard(self, tmp: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self._fs.rm_file(tmp)

    # -- reading -------------------------------------------------------------------------

    def exists(self, digest: str) -> bool:
        """Whether the store holds a blob named ``digest`` (its bytes are not checked)."""
        path = self.path(digest)
        with self._counting("read"):
            return bool(self._fs.exists(path))

    def size(self, digest: str) -> int:
        """The blob's length in bytes (BlobNotFound if absent)."""
        path = self.path(digest)
        try:
            with self._counting("read"):
                return int(self._fs.size(path))
        except FileNotFoundError:
            raise BlobNotFound(digest) from None

    def iter_chunks(self, digest: str, chunk_size: int = CHUNK_SIZE) -> Iterator[bytes]:
        """The blob's bytes, ``chunk_size`` at a time, checked against ``digest``.

        A malformed digest is refused at once; BlobNotFound comes with the first chunk
        asked for, and BlobCorrupt after the last one, when the bytes did not hash to
        their name.
        """
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        return self._chunks(digest, self.path(digest), chunk_size)

    def _chunks(self, digest: str, path: str, chunk_size: int) -> Iterator[bytes]:
        hasher = hashlib.sha256()
        try:
            with self._counting("read"):
                stream = self._fs.open(path, "rb")
        except FileNotFoundError:
            raise BlobNotFound(digest) from None
        with stream:
            while chunk := self._read(stream, chunk_size):
                hasher.update(chunk)
                yield chunk
        actual = f"{ALGORITHM}:{hasher.hexdigest()}"
        if actual != digest:
            log.error("%s: blob %s is damaged: its bytes hash to %s", self, digest, actual)
            self.errors["corrupt"] += 1
            raise BlobCorrupt(digest, actual)

    def _read(self, stream: BinaryIO, size: int) -> bytes:
        with self._counting("read"):
            return stream.read(size)

    @contextlib.contextmanager
    def _counting(self, kind: str) -> Iterator[None]:
        """Count an error of the store's filesystem as ``kind`` (and let it go on)."""
        try:
            yield
        except FileNotFoundError:  # no such blob: a question's answer, not a failure
            raise
        except Exception:  # counted, never swallowed: whatever the filesystem raised
            self.errors[kind] += 1
            raise

    # -- health --------------------------------------------------------------------------

    def check(self) -> None:
        """Raise what the store's filesystem raises if it does not answer (``/readyz``).

        Cheap: a local store's root, or the nearest folder above it while no blob has
        been written, must be a folder the lab may write in; an object store lists its
        root (one request), or its bucket while the root holds nothing yet.
        """
        if self.local:
            folder = Path(self._root)
            while not folder.exists() and folder != folder.parent:
                folder = folder.parent
            if not folder.is_dir():
                raise NotADirectoryError(f"{folder} is not a folder")
            if not os.access(folder, os.W_OK | os.X_OK):
                raise PermissionError(f"{folder} is not writable by the lab")
            return
        self._fs.invalidate_cache(self._root)
        try:
            self._fs.ls(self._root, detail=False)
        except FileNotFoundError:  # nothing stored yet: the bucket must answer
            self._fs.ls(self._root.split("/", 1)[0], detail=False)

    def read_bytes(self, digest: str) -> bytes:
        """The whole blob, checked (BlobNotFound, BlobCorrupt)."""
        return b"".join(self.iter_chunks(digest))

    def verify(self, digest: str) -> None:
        """Read the whole blob and check it (BlobNotFound, BlobCorrupt)."""
        for _ in self.iter_chunks(digest):
            pass

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        """Copy the blob to the local file ``dest``, which appears only once checked.

        The bytes go to a temporary file beside ``dest`` and are renamed to it after the
        last chunk matched the digest; on any error the temporary file is removed and
        ``dest`` is left as it was. Returns ``dest``.
        """
        dest = Path(dest)
        chunks = self.iter_chunks(digest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".{dest.name}.{uuid.uuid4().hex}.tmp")
        try:
            with tmp.open("xb") as out:
                for chunk in chunks:
                    out.write(chunk)
            tmp.replace(dest)
        finally:
            tmp.unlink(missing_ok=True)
        return dest
