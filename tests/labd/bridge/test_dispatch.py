"""The session's one dispatch: a table from op type to handler, made from what each
capability declares."""

from __future__ import annotations

import pytest

from labd.bridge.frames import OPS, Auth
from labd.bridge.ops import CAPABILITIES
from labd.bridge.ops.fragments import Fragments
from labd.bridge.ops.status import Status
from labd.bridge.ops.topics import Topics
from labd.bridge.session import Session
from labd.config import BridgeConfig
from tests.fakes import RecordingTransport, drain


@pytest.fixture
def session_of(graph, timers):
    """Make a session of ``graph`` with only the capabilities given."""
    made = []

    def make(*capabilities):
        session = Session(
            graph,
            BridgeConfig(),
            timers,
            RecordingTransport(),
            client_id=len(made) + 1,
            capabilities=list(capabilities),
        )
        made.append(session)
        return session

    yield make
    for session in made:
        session.close()


def test_every_op_but_auth_has_one_handler(connect):
    """Each op the parser knows is declared by exactly one capability, except auth,
    which the session answers itself."""
    session = connect().session
    declared = [h.op for make in CAPABILITIES for h in session.capability(make).handlers()]
    assert len(declared) == len(set(declared))
    assert set(declared) == set(OPS) - {Auth}


def test_a_session_reaches_its_capabilities_by_class(session_of):
    """``capability(Kind)`` is the session's own instance of that class; one the session
    was not made with is a LookupError."""
    session = session_of(Topics, Status)
    assert isinstance(session.capability(Topics), Topics)
    assert session.capability(Topics).session is session
    with pytest.raises(LookupError, match="no Fragments capability"):
        session.capability(Fragments)


def test_an_op_without_a_capability_is_refused_with_a_warning(session_of):
    """A session made without a family of ops says an op of it is not available here."""
    session = session_of(Topics, Status)
    session.receive('{"op": "set_level", "level": "warning"}')
    session.receive('{"op": "fragment", "id": "f", "data": "{}", "num": 0, "total": 1}')
    assert drain(session) == [
        {"op": "status", "level": "warning", "msg": "fragment is not available here", "id": "f"}
    ]


def test_two_capabilities_may_not_handle_one_op(session_of):
    """Two capabilities declaring the same op are a bug, found when a client connects."""
    with pytest.raises(ValueError, match="two capabilities handle Advertise"):
        session_of(Topics, Topics)
