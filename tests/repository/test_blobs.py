"""The content-addressed blob store: local folders and a real S3 server (moto)."""

from __future__ import annotations

import hashlib
import io
import os
import stat
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import s3fs
from moto.server import ThreadedMotoServer

from repository.blobs import BlobStore, digest_of, parse_digest
from repository.errors import ArchiveError, BlobCorrupt, BlobError, BlobNotFound

DATA = bytes(range(256)) * 5000  # 1.28 MB: more than one chunk
MISSING = "sha256:" + "0" * 64


def damage(store: BlobStore, digest: str) -> None:
    """Flip one byte of a local blob, as a failing disk would."""
    path = Path(store.path(digest))
    os.chmod(path, 0o644)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.fixture
def store(tmp_path: Path) -> BlobStore:
    return BlobStore(str(tmp_path / "blobs"))


# -- local ------------------------------------------------------------------------------------


def test_put_and_read_round_trip(store, tmp_path):
    """A stored file reads back whole, under its sha256, at the documented place."""
    source = tmp_path / "trial.mcap"
    source.write_bytes(DATA)
    digest = store.put_file(source)
    want = "sha256:" + hashlib.sha256(DATA).hexdigest()
    assert digest == want == digest_of(DATA)
    assert store.exists(digest) and store.size(digest) == len(DATA)
    assert store.read_bytes(digest) == DATA
    chunks = list(store.iter_chunks(digest, chunk_size=100_000))
    assert b"".join(chunks) == DATA and len(chunks) == 13
    assert store.path(digest) == f"{tmp_path}/blobs/sha256/{want[7:9]}/{want[7:]}"
    store.verify(digest)
    assert store.put_bytes(b"") == digest_of(b"") and store.read_bytes(digest_of(b"")) == b""


def test_local_blobs_are_read_only_and_no_temporary_file_stays(store):
    """A written blob has mode 0o444, and the temporary folder is empty afterwards."""
    digest = store.put_bytes(DATA)
    assert stat.S_IMODE(os.stat(store.path(digest)).st_mode) == 0o444
    assert os.listdir(Path(store.path(digest)).parents[2] / "tmp") == []


def test_file_url_names_the_same_folder(store, tmp_path):
    """A file:// URL and the plain path reach the same blobs."""
    digest = store.put_bytes(b"hello")
    assert BlobStore(f"file://{tmp_path}/blobs").read_bytes(digest) == b"hello"


def test_a_second_put_rewrites_nothing(store):
    """Putting existing content returns the same digest and leaves the blob untouched."""
    digest = store.put_bytes(DATA)
    before = os.stat(store.path(digest))
    assert store.put_bytes(DATA) == digest
    after = os.stat(store.path(digest))
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)


def test_a_flipped_byte_is_found_by_every_reader(store, tmp_path):
    """A damaged blob raises BlobCorrupt on read, iteration, verify and copy_to."""
    digest = store.put_bytes(DATA)
    damage(store, digest)
    with pytest.raises(BlobCorrupt) as caught:
        store.read_bytes(digest)
    assert caught.value.digest == digest and caught.value.actual != digest
    assert "damaged" in str(caught.value)
    chunks = store.iter_chunks(digest, chunk_size=1 << 16)
    got = []
    with pytest.raises(BlobCorrupt):
        for chunk in chunks:
            got.append(chunk)
    assert len(b"".join(got)) == len(DATA)  # every chunk came before the error
    with pytest.raises(BlobCorrupt):
        store.verify(digest)
    dest = tmp_path / "out" / "trial.mcap"
    with pytest.raises(BlobCorrupt):
        store.copy_to(digest, dest)
    assert list(dest.parent.iterdir()) == []


class FailingStream(io.RawIOBase):
    """A source that breaks after its first megabyte, as a dropped upload would."""

    def __init__(self) -> None:
        self.calls = 0

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        self.calls += 1
        if self.calls > 1:
            raise ConnectionResetError("the client went away")
        return DATA[: max(size, 0)]


def test_a_broken_source_leaves_no_blob_and_no_temporary_file(store):
    """A put whose source fails midway stores nothing, under any name."""
    with pytest.raises(ConnectionResetError):
        store.put_stream(FailingStream())
    root = Path(store.path(MISSING)).parents[2]
    assert os.listdir(root / "tmp") == []
    assert not (root / "sha256").exists()


def test_copy_to_writes_a_checked_copy(store, tmp_path):
    """copy_to leaves exactly the blob's bytes at dest, replacing what was there."""
    digest = store.put_bytes(DATA)
    dest = tmp_path / "out.mcap"
    dest.write_bytes(b"old")
    assert store.copy_to(digest, dest) == dest
    assert dest.read_bytes() == DATA
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_missing_blobs_are_not_found(store, tmp_path):
    """Every reader raises BlobNotFound for a digest the store does not hold."""
    assert not store.exists(MISSING)
    for read in (store.read_bytes, store.verify, store.size, lambda d: list(store.iter_chunks(d))):
        with pytest.raises(BlobNotFound, match="not in the store"):
            read(MISSING)
    with pytest.raises(BlobNotFound):
        store.copy_to(MISSING, tmp_path / "x")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "sha256:",
        "sha256:" + "0" * 63,
        "sha256:" + "0" * 65,
        "sha256:" + "A" * 64,
        "md5:" + "0" * 64,
        "0" * 64,
        "sha256:../../../../etc/passwd",
        "sha256:" + "0" * 62 + "/.",
        "sha256:" + "0" * 64 + "\n",
    ],
)
def test_malformed_digests_are_refused(store, bad):
    """A string that is not 'sha256:' and 64 lowercase hex digits never names a path."""
    with pytest.raises(BlobError, match="not a digest"):
        parse_digest(bad)
    for use in (store.exists, store.read_bytes, store.size, store.path, store.iter_chunks):
        with pytest.raises(ArchiveError, match="not a digest"):
            use(bad)


def test_a_digest_must_be_a_string(store):
    """A non-string digest is refused with the same error family."""
    with pytest.raises(BlobError, match="must be a string"):
        store.exists(b"sha256:" + b"0" * 64)  # type: ignore[arg-type]


def test_two_threads_putting_the_same_bytes(store):
    """Concurrent puts of one content both succeed, and one intact blob remains."""
    barrier = threading.Barrier(2)
    results: list[str] = []
    errors: list[BaseException] = []

    def put() -> None:
        try:
            barrier.wait(5)
            results.append(store.put_bytes(DATA))
        except BaseException as err:
            errors.append(err)

    threads = [threading.Thread(target=put) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert errors == [] and results == [digest_of(DATA)] * 2
    store.verify(results[0])
    assert os.listdir(Path(store.path(results[0])).parent) == [results[0][7:]]


# -- S3 (a real moto server on 127.0.0.1) -------------------------------------------------------


@pytest.fixture(scope="module")
def s3_endpoint() -> Iterator[str]:
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture
def s3_store(s3_endpoint: str, request: pytest.FixtureRequest) -> BlobStore:
    options = {"endpoint_url": s3_endpoint, "key": "testing", "secret": "testing"}
    bucket = "lab-" + hashlib.sha256(request.node.name.encode()).hexdigest()[:12]
    s3fs.S3FileSystem(**options).mkdir(bucket)
    return BlobStore(f"s3://{bucket}/archive", options)


@pytest.mark.integration
def test_s3_round_trip(s3_store, tmp_path):
    """On S3, a put file reads back, idempotently, with its size, under the same key layout."""
    source = tmp_path / "trial.mcap"
    source.write_bytes(DATA)
    digest = s3_store.put_file(source)
    assert digest == digest_of(DATA)
    assert s3_store.put_bytes(DATA) == digest
    assert s3_store.exists(digest) and s3_store.size(digest) == len(DATA)
    assert s3_store.read_bytes(digest) == DATA
    assert s3_store.path(digest).endswith(f"/archive/sha256/{digest[7:9]}/{digest[7:]}")
    dest = tmp_path / "copy.mcap"
    s3_store.copy_to(digest, dest)
    assert dest.read_bytes() == DATA
    fs = s3_store._fs
    fs.invalidate_cache()
    assert fs.find(s3_store.path(digest).split("/sha256/")[0] + "/tmp") == []  # nothing half-done


@pytest.mark.integration
def test_s3_missing_and_damaged_blobs(s3_store, tmp_path):
    """On S3, an absent blob is BlobNotFound and an overwritten one is BlobCorrupt."""
    with pytest.raises(BlobNotFound):
        s3_store.read_bytes(MISSING)
    with pytest.raises(BlobNotFound):
        s3_store.size(MISSING)
    digest = s3_store.put_bytes(b"the original bytes")
    s3_store._fs.pipe_file(s3_store.path(digest), b"the original bytez")
    with pytest.raises(BlobCorrupt):
        s3_store.verify(digest)
    with pytest.raises(BlobCorrupt):
        s3_store.copy_to(digest, tmp_path / "x")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.integration
def test_s3_two_threads_putting_the_same_bytes(s3_store):
    """Concurrent puts to S3 both return the digest of one intact blob."""
    barrier = threading.Barrier(2)
    results: list[str] = []
    errors: list[BaseException] = []

    def put() -> None:
        try:
            barrier.wait(5)
            results.append(s3_store.put_bytes(DATA))
        except BaseException as err:
            errors.append(err)

    threads = [threading.Thread(target=put) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert errors == [] and results == [digest_of(DATA)] * 2
    s3_store.verify(results[0])
