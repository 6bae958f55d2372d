"""The controller-side client library against a real lab with a lockstep maze robot."""

from __future__ import annotations

import contextlib
import http.server
import math
import socket
import threading
from urllib.parse import parse_qs, urlsplit

import pytest

from controllers.client import (
    ConnectionLost,
    EpisodeOver,
    Lab,
    LabTimeout,
    ServiceError,
    StatusError,
    Tick,
    _nulls,
)
from labd.config import BridgeConfig, RobotConfig

ODOM = "nav_msgs/msg/Odometry"
TWIST = "geometry_msgs/msg/Twist"
PERIOD_NS = 100_000_000  # the maze's control tick at its default 10 Hz


def stamp_ns(message):
    stamp = message["header"]["stamp"]
    return stamp["sec"] * 1_000_000_000 + stamp["nanosec"]


@pytest.fixture
def maze_server(make_server):
    """A lab hosting one lockstep maze robot, with a 2 s episode (20 ticks)."""
    robot = RobotConfig("maze", "icreate-maze", params=(("time_limit", "2"),), seed=3, live=False)
    return make_server(BridgeConfig(port=0), robots=(robot,))


@pytest.fixture
def maze_client(maze_server):
    with Lab.connect(maze_server.url, timeout=10) as client:
        yield client


# -- without a lab -----------------------------------------------------------------------


def test_non_finite_floats_become_null_at_any_depth():
    """NaN and infinities are sent as null (which the lab refuses by name); the rest stays."""
    value = {"a": [1.0, math.nan, {"b": -math.inf}], "c": (2, "x"), "d": math.inf}
    assert _nulls(value) == {"a": [1.0, None, {"b": None}], "c": [2, "x"], "d": None}


def test_a_tick_reads_an_episode_message():
    """A lab_msgs/Episode message gives the tick, time, status and reason."""
    episode = {
        "header": {"stamp": {"sec": 2, "nanosec": 500_000_000}, "frame_id": ""},
        "tick": 25,
        "status": "truncated",
        "reason": "the time limit of 2.5 s was reached",
    }
    tick = Tick.from_episode(episode)
    assert (tick.number, tick.time, tick.status) == (25, 2.5, "truncated")
    assert not tick.running and not tick.success
    assert tick.message == "tick 25 at 2.500 s: truncated: the time limit of 2.5 s was reached"


def test_connecting_where_nothing_listens_says_so():
    """A refused connection is ConnectionLost naming the URL, not a bare OSError."""
    with pytest.raises(
        ConnectionLost, match=r"could not connect to ws://127\.0\.0\.1:9/ \(.*refused"
    ):
        Lab.connect("ws://127.0.0.1:9/", timeout=5)


# -- against a lab -----------------------------------------------------------------------


@pytest.mark.integration
def test_latched_topics_arrive_on_subscription(maze_client):
    """/goal (latched) is there after one get(); /odom holds the pose of tick 0."""
    goal = maze_client.subscribe("/goal", "geometry_msgs/msg/PointStamped").get()
    assert goal["header"]["frame_id"] == "odom"
    odom = maze_client.subscribe("odom", ODOM).get()  # a relative name means the absolute one
    assert stamp_ns(odom) == 0
    assert maze_client.subscribe("/odom", ODOM).count == 1  # the same subscription


@pytest.mark.integration
def test_after_step_the_subscriptions_hold_that_ticks_observations(maze_client):
    """Every step returns with the tick's /odom and /clock in, its callbacks run, in order."""
    seen = []
    odom = maze_client.subscribe("/odom", ODOM, callback=lambda m: seen.append(stamp_ns(m)))
    clock = maze_client.subscribe("/clock", "rosgraph_msgs/msg/Clock")
    odom.get()
    for number in range(1, 6):
        maze_client.publish("/cmd_vel", TWIST, {"linear": {"x": 0.3}})
        tick = maze_client.step()
        assert (tick.number, tick.status) == (number, "running")
        assert tick.time == pytest.approx(number * 0.1)
        assert stamp_ns(odom.latest) == number * PERIOD_NS
        assert clock.latest is not None
        assert clock.latest["clock"] == {"sec": 0, "nanosec": number * PERIOD_NS}
        assert seen[-1] == number * PERIOD_NS
    assert seen == [k * PERIOD_NS for k in range(6)]
    assert odom.latest["pose"]["pose"]["position"]["x"] > 0.05  # the command was applied
    assert maze_client.episode["tick"] == 5 and maze_client.episode["status"] == "running"


@pytest.mark.integration
def test_the_step_that_ends_the_episode_raises_episode_over_and_so_do_later_ones(maze_client):
    """At the time limit, step raises EpisodeOver (truncated) with the last tick's
    observations in; a further step raises it again."""
    odom = maze_client.subscribe("/odom", ODOM)
    for _ in range(19):
        assert maze_client.step().running
    with pytest.raises(EpisodeOver) as ended:
        maze_client.step()
    over = ended.value
    assert (over.status, over.success, over.tick.number) == ("truncated", False, 20)
    assert "time limit" in over.reason and "time limit" in str(over)
    assert stamp_ns(odom.latest) == 20 * PERIOD_NS
    with pytest.raises(EpisodeOver) as again:
        maze_client.step()
    assert (again.value.status, again.value.tick.number) == ("truncated", 20)
    assert maze_client.episode["status"] == "truncated"


@pytest.mark.integration
def test_run_calls_the_policy_each_tick_until_the_episode_ends(maze_client):
    """run() gives the policy ticks 0..19 and returns the last one, tick 20."""
    numbers = []
    last = maze_client.run(lambda tick: numbers.append(tick.number))
    assert numbers == list(range(20))
    assert (last.number, last.status) == (20, "truncated")


@pytest.mark.integration
def test_a_refused_command_raises_status_error_after_the_step(maze_client):
    """A NaN in a command is refused by the lab; the next step raises its sentence, and
    the tick's observations are in all the same."""
    odom = maze_client.subscribe("/odom", ODOM)
    maze_client.publish("/cmd_vel", TWIST, {"linear": {"x": math.nan}})
    with pytest.raises(StatusError, match=r"msg\.linear\.x must be a finite number"):
        maze_client.step()
    assert maze_client.tick is not None and maze_client.tick.number == 1  # the step happened
    assert stamp_ns(odom.latest) == PERIOD_NS
    assert maze_client.step().number == 2  # the connection carries on


@pytest.mark.integration
def test_subscribing_with_the_wrong_type_raises_status_error(maze_client):
    """/odom is not a Twist: get() raises the lab's refusal instead of timing out."""
    with pytest.raises(StatusError, match="/odom"):
        maze_client.subscribe("/odom", TWIST).get(timeout=10)


@pytest.mark.integration
def test_a_failed_call_raises_service_error_with_the_labs_sentence(maze_client):
    """Calling a service no one provides is ServiceError naming it."""
    with pytest.raises(ServiceError, match=r"/no_such_service failed: .*no_such_service"):
        maze_client.call("/no_such_service")
    assert maze_client.call("/rosapi/get_time")["time"]["sec"] == 0  # simulation time


@pytest.mark.integration
def test_waiting_for_a_silent_topic_times_out_clearly(maze_client):
    """get() on a topic no one publishes raises LabTimeout naming the topic."""
    silent = maze_client.subscribe("/silence", "std_msgs/msg/String")
    with pytest.raises(LabTimeout, match=r"a message on /silence: nothing within 0\.2 s"):
        silent.get(timeout=0.2)


@pytest.mark.integration
def test_connect_reads_the_url_from_the_environment(maze_server, monkeypatch):
    """Without a URL, Lab.connect uses $LAB_BRIDGE_URL."""
    monkeypatch.setenv("LAB_BRIDGE_URL", maze_server.url)
    with Lab.connect() as lab:
        assert lab.url == maze_server.url
        assert lab.episode["task"] == "icreate-maze"


@pytest.mark.integration
def test_an_unknown_robot_path_is_connection_lost(maze_server):
    """A path the lab does not serve (HTTP 404) is ConnectionLost, naming the URL."""
    with pytest.raises(ConnectionLost, match="robots/nobody"):
        Lab.connect(maze_server.url + "/robots/nobody", timeout=5)


@pytest.mark.integration
def test_next_waits_for_a_message_published_meanwhile(maze_client):
    """A topic published by a client (here, this one) reaches its subscription via next()."""
    chatter = maze_client.subscribe("/chatter", "std_msgs/msg/String")
    maze_client.publish("/chatter", "std_msgs/msg/String", {"data": "hello"})
    assert chatter.next(timeout=10) == {"data": "hello"}
    maze_client.publish("/chatter", "std_msgs/msg/String", {"data": "again"})
    assert chatter.next(timeout=10) == {"data": "again"} and chatter.count == 2


class Authorizer(http.server.BaseHTTPRequestHandler):
    """Knows one key, "good", for 30 s."""

    def do_GET(self):
        key = parse_qs(urlsplit(self.path).query).get("key", [""])[0]
        status, body = (200, b'{"seconds": 30}') if key == "good" else (403, b"no")
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def guarded(make_server):
    """A lab with a maze robot that asks an authorizer about every connection's key."""
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Authorizer)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{httpd.server_address[1]}/api/auth"
    robot = RobotConfig("maze", "icreate-maze", seed=3, live=False)
    yield make_server(BridgeConfig(port=0, authorizer_url=url, auth_timeout=5), robots=(robot,))
    httpd.shutdown()
    httpd.server_close()


@pytest.mark.integration
def test_a_key_opens_a_guarded_lab_and_a_refused_one_is_connection_lost(guarded):
    """With a good key the client steps the robot; with a bad one the lab closes the
    connection (1008) and the client says why."""
    with Lab.connect(guarded.url, key="good") as lab:
        assert lab.step().number == 1
    with Lab.connect(guarded.url, key="bad") as lab, pytest.raises(ConnectionLost) as lost:
        lab.step(timeout=10)
    assert lost.value.code == 1008 and "authorization refused" in str(lost.value)


def test_in_a_sandbox_it_connects_to_the_bridges_unix_socket(maze_server, tmp_path, monkeypatch):
    """Without a URL, with ``$LAB_BRIDGE_SOCKET`` (set in the sandboxes), the client goes
    to that unix socket, not to ``$LAB_BRIDGE_URL``'s port (where the relay would be)."""
    target = urlsplit(maze_server.url)
    path = str(tmp_path / "bridge.sock")
    accepted: list[int] = []

    def pump(a, b):
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)
        with contextlib.suppress(OSError):
            b.shutdown(socket.SHUT_WR)

    def serve(listener):
        unix, _ = listener.accept()
        accepted.append(1)
        with unix, socket.create_connection((target.hostname, target.port)) as tcp:
            back = threading.Thread(target=pump, args=(unix, tcp))
            back.start()
            pump(tcp, unix)
            back.join()

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listener:
        listener.bind(path)
        listener.listen()
        forwarder = threading.Thread(target=serve, args=(listener,))
        forwarder.start()
        monkeypatch.setenv("LAB_BRIDGE_SOCKET", path)
        monkeypatch.setenv("LAB_BRIDGE_URL", f"ws://127.0.0.1:9{target.path}")  # nothing there
        with Lab.connect(timeout=10) as lab:
            odom = lab.subscribe("/odom", ODOM)
            lab.publish("/cmd_vel", TWIST, {"linear": {"x": 0.3}})
            first = lab.step()
            lab.publish("/cmd_vel", TWIST, {"linear": {"x": 0.3}})  # leaves with the step
            second = lab.step()
            assert second.number == first.number + 1
            assert odom.latest["twist"]["twist"]["linear"]["x"] > 0
        forwarder.join(10)
    assert accepted == [1]
