"""Keys on a bridge session, with a manual clock: the key-optional policy (watchers
connect without one), whose key it is, the warning before the time runs out, and the
time changing while connected (a slot extended or released)."""

from __future__ import annotations

from labd.config import BridgeConfig


def status_client(connect, config=None, **kwargs):
    client = connect(config, **kwargs)
    client.send({"op": "set_level", "level": "warning"})
    return client


def test_with_a_key_optional_a_client_without_one_is_served(connect):
    """Where a key is optional, a client that presents none is served at once, as
    nobody in particular; it is never closed for lack of a key."""
    client = connect(auth_optional=True)
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/get_ros_version"})
    assert client.frames()[0]["result"] is True
    assert client.session.node.user is None
    assert client.transport.keys == []


def test_with_a_key_optional_a_late_key_makes_the_client_someone(connect, timers):
    """An auth frame, even after other frames, is checked; frames after it wait for the
    answer; the grant names the user on the client's node, and its time runs out."""
    client = connect(auth_optional=True)
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/nodes"})
    client.send({"op": "auth", "key": "k"})
    client.send({"op": "call_service", "id": 2, "service": "/rosapi/get_ros_version"})
    assert [f["id"] for f in client.frames()] == [1]
    assert client.transport.keys == ["k"]
    client.session.grant(30, user="alice", ref="reservation:3")
    assert [f["id"] for f in client.frames()] == [2]
    assert client.session.node.user == "alice"
    assert client.session.grant_ref == "reservation:3"
    client.send({"op": "auth", "key": "another"})  # one key per connection
    assert client.transport.keys == ["k"]
    timers.advance(30)
    assert client.transport.closed == (1008, "the authorization has expired")


def test_with_a_key_optional_a_refused_key_closes_saying_why(connect):
    """A key presented and refused closes the connection with the authorizer's reason."""
    client = connect(auth_optional=True, url_key="old")
    assert client.transport.keys == ["old"]
    client.session.refuse("this key's slot on icreate-1 ended at 10:00")
    assert client.transport.closed == (
        1008,
        "authorization refused: this key's slot on icreate-1 ended at 10:00",
    )


def test_a_warning_comes_before_the_time_runs_out(connect, timers):
    """A client that asked for warnings gets one status, expiry_warning seconds before
    its key's time ends; then the connection closes."""
    client = status_client(connect, BridgeConfig(expiry_warning=60), auth_optional=True)
    client.send({"op": "auth", "key": "k"})
    client.session.grant(300, user="alice")
    timers.advance(239)
    assert client.frames() == []
    timers.advance(1)
    (warning,) = client.frames()
    assert warning["level"] == "warning"
    assert warning["msg"].startswith("the time of your key ends in 60 s")
    assert client.transport.closed is None
    timers.advance(60)
    assert client.transport.closed == (1008, "the authorization has expired")


def test_no_warning_for_a_key_shorter_than_the_warning(connect, timers):
    """A key granted for less than the warning's lead gets no warning, only the end."""
    client = connect(BridgeConfig(expiry_warning=60), auth_required=True)
    client.send({"op": "auth", "key": "k"})
    client.send({"op": "set_level", "level": "warning"})
    client.session.grant(30)
    timers.advance(30)
    assert client.frames() == []
    assert client.transport.closed == (1008, "the authorization has expired")


def test_the_time_of_a_key_changes_while_connected(connect, timers):
    """Extended, the key's end (and its warning) move later; with no time left the
    connection closes with the reason given."""
    client = status_client(connect, BridgeConfig(expiry_warning=10), auth_optional=True)
    client.send({"op": "auth", "key": "k"})
    client.session.grant(20, user="alice", ref="reservation:1")
    timers.advance(5)
    client.session.reauthorize(100, "unused")
    timers.advance(20)
    assert client.transport.closed is None and client.frames() == []
    timers.advance(75)  # 95 s after the extension: its warning
    assert "ends in 10 s" in client.frames()[0]["msg"]
    client.session.reauthorize(0, "the reservation was released")
    assert client.transport.closed == (1008, "the reservation was released")
    assert timers.pending == 0
