"""A damaged blob is healed by storing its bytes again, and by nothing else.

A record's bytes can come again: a rerun that reproduced writes the same MCAP, byte for
byte. Before, the store saw the name taken and kept the damaged copy, so the rerun's
record could never be served either. Now the copy under the name is checked first and,
if damaged, replaced by the bytes being stored, which hash to the name.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import s3fs
from moto.server import ThreadedMotoServer

from repository.blobs import BlobStore, digest_of
from repository.errors import BlobCorrupt

DATA = bytes(range(256)) * 5000  # more than one chunk


def flip(path: Path) -> None:
    os.chmod(path, 0o644)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def test_storing_the_same_bytes_heals_a_damaged_local_blob(tmp_path: Path) -> None:
    """The same bytes stored again replace a flipped copy; the blob reads back whole and
    read-only, and no temporary file stays."""
    store = BlobStore(str(tmp_path / "blobs"))
    digest = store.put_bytes(DATA)
    flip(Path(store.path(digest)))
    with pytest.raises(BlobCorrupt):
        store.verify(digest)
    assert store.put_bytes(DATA) == digest
    assert store.read_bytes(digest) == DATA
    assert oct(os.stat(store.path(digest)).st_mode & 0o777) == "0o444"
    assert os.listdir(tmp_path / "blobs" / "tmp") == []


def test_a_whole_blob_is_left_alone_and_a_truncated_one_healed(tmp_path: Path) -> None:
    """A whole blob is not rewritten when its bytes come again; a truncated one is."""
    store = BlobStore(str(tmp_path / "blobs"))
    digest = store.put_bytes(DATA)
    before = os.stat(store.path(digest))
    store.put_bytes(DATA)
    assert os.stat(store.path(digest)).st_ino == before.st_ino
    path = Path(store.path(digest))
    os.chmod(path, 0o644)
    path.write_bytes(DATA[:1000])
    store.put_bytes(DATA)
    assert store.read_bytes(digest) == DATA and os.stat(path).st_ino != before.st_ino


@pytest.fixture
def s3_store() -> Iterator[BlobStore]:
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    options = {"endpoint_url": f"http://{host}:{port}", "key": "testing", "secret": "testing"}
    bucket = f"lab-{uuid.uuid4().hex[:12]}"  # moto keeps buckets per process, across servers
    s3fs.S3FileSystem(**options).mkdir(bucket)
    yield BlobStore(f"s3://{bucket}/archive", options)
    server.stop()


@pytest.mark.integration
def test_storing_the_same_bytes_heals_a_damaged_s3_blob(s3_store: BlobStore) -> None:
    """On S3 too, an object overwritten behind the lab's back is replaced by its bytes."""
    digest = s3_store.put_bytes(DATA)
    s3_store._fs.pipe_file(s3_store.path(digest), DATA[:-1] + b"x")
    s3_store._fs.invalidate_cache()
    with pytest.raises(BlobCorrupt):
        s3_store.verify(digest)
    assert s3_store.put_bytes(DATA) == digest == digest_of(DATA)
    s3_store._fs.invalidate_cache()
    assert hashlib.sha256(s3_store.read_bytes(digest)).hexdigest() == digest[7:]
