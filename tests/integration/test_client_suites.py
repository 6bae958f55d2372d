"""roslibpy's own ROS 2 test suite, unmodified, against a real ``labd serve``.

``tests/clients/suites.py`` downloads the installed roslibpy's sdist (which ships its
tests) from PyPI, starts ``labd serve`` on port 9090 in a network namespace of its own
with ``tests/clients/fixtures.py`` (an ordinary bridge client playing the tutorials'
nodes the suite expects), and runs the suite's ``tests/ros2`` with both transports.
roslibjs' suite is not in its npm package, so it is not run here (docs/protocol.md).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]


def namespaces_work() -> bool:
    unshare = shutil.which("unshare")
    if unshare is None:
        return False
    as_user = [] if os.geteuid() == 0 else ["--map-root-user"]
    probe = subprocess.run([unshare, "--net", *as_user, "true"], capture_output=True, check=False)
    return probe.returncode == 0


def test_roslibpys_own_ros2_suite_passes(request: pytest.FixtureRequest):
    """Every test of roslibpy's tests/ros2 passes against the lab, with either transport:
    /rosout listed on a fresh server, topics, headers, connections, the Fibonacci action
    and its cancellation."""
    if not namespaces_work():
        message = "unshare --net is not permitted here (the suite needs port 9090 of its own)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    assert request.config.cache is not None
    cache = request.config.cache.mkdir("roslibpy-sdist")
    proc = subprocess.run(
        [sys.executable, "-m", "tests.clients.suites", "roslibpy", "--cache", str(cache)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout)
    assert set(results) == {"twisted", "asyncio"}
    for transport, outcomes in results.items():
        assert len(outcomes) >= 25, (transport, outcomes)  # roslibpy 2.1.0 has 25
        failed = {name: o for name, o in outcomes.items() if o != "passed"}
        assert failed == {}, transport
        assert f"tests.ros2.test_rosapi::test_rosapi_topics[{transport}]" in outcomes
        assert f"tests.ros2.test_actions::test_cancel[{transport}]" in outcomes
