"""What a controller cannot reach: the network, the host's files, anything but its scratch."""

from __future__ import annotations

import asyncio
import fcntl
import json
import socket
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from sandbox.api import Limits, MiB
from tests.sandbox.conftest import Controllers

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

SIOCGIFADDR = 0x8915  # ioctl: an interface's IPv4 address


def host_addresses() -> list[str]:
    """This machine's own IPv4 addresses, one per interface that has one."""
    found = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        for _, name in socket.if_nameindex():
            request = struct.pack("256s", name[:15].encode())
            try:
                answer = fcntl.ioctl(probe.fileno(), SIOCGIFADDR, request)
            except OSError:  # no IPv4 address on it
                continue
            found.append(socket.inet_ntoa(answer[20:24]))
    assert "127.0.0.1" in found
    return found


@pytest.fixture
async def host_server() -> AsyncIterator[tuple[int, list[str]]]:
    """A TCP server on all of the host's addresses; the list of peers that reached it."""
    reached: list[str] = []

    async def accept(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        reached.append(str(writer.get_extra_info("peername")))
        writer.close()

    server = await asyncio.start_server(accept, "0.0.0.0", 0)
    async with server:
        yield server.sockets[0].getsockname()[1], reached


async def test_no_tcp_connection_to_the_host(
    controllers: Controllers, host_server: tuple[int, list[str]]
) -> None:
    """Connecting to a server on any of the host's addresses fails at once."""
    port, reached = host_server
    addresses = host_addresses()
    ended = await controllers.run(
        f"""
        import json, socket, time
        results = {{}}
        for address in {addresses!r}:
            started = time.monotonic()
            try:
                socket.create_connection((address, {port}), timeout=5).close()
                outcome = "connected"
            except OSError as err:
                outcome = type(err).__name__
            results[address] = [outcome, time.monotonic() - started]
        print(json.dumps(results))
        """
    )
    assert ended.code == 0, ended.stderr
    results = json.loads(ended.stdout)
    assert set(results) == set(addresses)
    for address, (outcome, seconds) in results.items():
        assert outcome != "connected", address
        assert seconds < 1.0, (address, outcome)
    assert reached == []


async def test_no_name_resolution(controllers: Controllers) -> None:
    """Resolving a name fails at once: there is no DNS server to ask."""
    ended = await controllers.run(
        """
        import socket, time
        started = time.monotonic()
        try:
            socket.getaddrinfo("pypi.org", 443)
            print("resolved")
        except socket.gaierror as err:
            print("gaierror", time.monotonic() - started < 2.0)
        print(socket.gethostbyname("localhost"))
        """
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"gaierror True\n127.0.0.1\n"


async def test_only_the_loopback_interface(controllers: Controllers) -> None:
    """The sandbox's network namespace has the loopback interface and nothing else."""
    ended = await controllers.run(
        """
        import socket
        print(sorted(name for _, name in socket.if_nameindex()))
        """
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"['lo']\n"


async def test_writes_only_in_scratch(controllers: Controllers) -> None:
    """/, /code, /etc, the runtime and /tmp's target outside scratch are read-only."""
    ended = await controllers.run(
        """
        import json, os
        results = {}
        for path in ["/x", "/code/x", "/etc/x", "/etc/passwd", "/opt/labd/x",
                     "/opt/labd/site-packages/numpy/x", "/usr/x", "/root/x", "/dev/x",
                     "/mnt/x", "/scratch/x", "/scratch/home/x", "/tmp/x", "/dev/shm/x"]:
            try:
                with open(path, "a") as f:
                    f.write("x")
                results[path] = "written"
            except OSError as err:
                results[path] = type(err).__name__
        print(json.dumps(results))
        """
    )
    assert ended.code == 0, ended.stderr
    results = json.loads(ended.stdout)
    writable = {"/scratch/x", "/scratch/home/x", "/tmp/x", "/dev/shm/x"}
    assert {path for path, outcome in results.items() if outcome == "written"} == writable


async def test_scratch_is_bounded(controllers: Controllers) -> None:
    """Writing past limits.scratch in the scratch folder fails with a full disk or too big."""
    ended = await controllers.run(
        """
        import errno
        written = 0
        try:
            with open("/scratch/big", "wb") as f:
                while written < 64 * 1024 * 1024:
                    f.write(b"x" * 1024 * 1024)
                    f.flush()
                    written += 1024 * 1024
            print("wrote all", written)
        except OSError as err:
            print(errno.errorcode[err.errno], written // (1024 * 1024))
        """,
        limits=Limits(scratch=16 * MiB, wall=60),
    )
    assert ended.code == 0, ended.stderr
    error, mebibytes = ended.stdout.decode().split()
    assert error in ("ENOSPC", "EFBIG")
    assert 8 <= int(mebibytes) <= 16


async def test_the_labs_files_are_not_there(controllers: Controllers, workdir: Path) -> None:
    """Host files (a test's tmp folder, the lab's tree, root's home) do not exist inside."""
    secret = workdir / "secret.txt"
    secret.write_text("the lab's token")
    secret.chmod(0o644)
    paths = [
        str(secret),
        str(workdir),
        "/work/main",
        "/work",
        "/root/.bashrc",
        "/root/.pyenv/versions/3.11.7/lib/python3.11/site-packages",
        "/etc/shadow",
        "/var/run/docker.sock",
        "/run/docker.sock",
        "/home",
    ]
    ended = await controllers.run(
        f"""
        import os
        for path in {paths!r}:
            print(os.path.exists(path))
        """
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout.decode().split() == ["False"] * len(paths)
