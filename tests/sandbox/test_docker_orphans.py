"""A Docker backend starting (a lab starting) removes the containers a dead lab of this
host left behind, and leaves those of labs still running."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import uuid

import docker.errors
import pytest

from sandbox.docker import LABEL, OWNER, DockerBackend
from tests.helpers.sandboxes import make_backend

pytestmark = pytest.mark.integration


def test_containers_of_a_dead_lab_are_removed_and_a_living_labs_are_kept(cache) -> None:
    first = make_backend("docker", cache)
    assert isinstance(first, DockerBackend)
    dead = subprocess.Popen(["true"])  # a process that has ended: no lab has its pid
    dead.wait()
    host = socket.gethostname()
    made = {}
    for whose, pid in (("dead", dead.pid), ("alive", os.getpid())):
        made[whose] = first.client.containers.create(
            first.image,
            command=["true"],
            labels={LABEL: f"orphan-test-{uuid.uuid4().hex[:8]}", OWNER: f"{host}:{pid}"},
        )
    try:
        make_backend("docker", cache)  # another lab starts on this host
        with pytest.raises(docker.errors.NotFound):
            first.client.containers.get(made["dead"].id)
        assert first.client.containers.get(made["alive"].id).id == made["alive"].id
    finally:
        for container in made.values():
            with contextlib.suppress(docker.errors.NotFound):
                container.remove(force=True)
