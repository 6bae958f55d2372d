"""Driving a live robot: one driver at a time, and each drive recorded as a demonstration
that replays, the watchdog's stops included."""

from __future__ import annotations

import pytest

from labd.graph.graph import Side
from labd.live import Driving, NotDriving
from labd.replay import replay
from labd.station import Station

TWIST = "geometry_msgs/msg/Twist"


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def live(registry, tmp_path):
    station = Station(
        registry, "icreate-1", "icreate-maze", {}, 7, live=True, protected_prefixes=("/protected",)
    )
    clock = Clock()
    station.robot.wall_clock = clock
    filed = []
    driving = Driving(station, work=tmp_path / "live", file=filed.append)
    yield station, driving, filed, clock
    driving.close()
    station.close()


def client(station, name):
    node = station.graph.create_node(name, side=Side.CLIENT)
    return node, node.advertise("/cmd_vel", TWIST)


def call(node, service, request=None):
    answers = []
    node.call_service(service, request, answers.append)
    return answers[0].response.data


def test_the_first_to_command_drives_and_others_watch(live):
    """A client's first command makes it the driver, starting a new episode; another
    client's command is refused naming the driver; /lab/driver says who drives."""
    station, driving, filed, _ = live
    seed = station.robot.sim.seed
    alice, alice_cmd = client(station, "/alice")
    bob, bob_cmd = client(station, "/bob")
    heard = []
    bob.subscribe("/lab/driver", None, heard.append)
    assert heard[-1].data["driver"] == ""
    alice_cmd.publish({"linear": {"x": 0.2}})
    assert driving.current is not None and driving.current.node is alice
    assert station.robot.sim.seed == seed + 1  # a new episode for the drive
    assert heard[-1].data["driver"] == "/alice" and heard[-1].data["recording"] is True
    with pytest.raises(NotDriving, match="driven by /alice; you are watching"):
        bob_cmd.publish({"linear": {"x": -1.0}})
    refused = call(bob, "/lab/drive", {"session": "s", "interface": "video", "user": "bob"})
    assert refused == {"success": False, "message": "/alice drives", "seed": 0}
    assert call(bob, "/lab/reset")["success"] is False
    assert filed == []


def test_a_drive_is_filed_when_the_driver_leaves_and_replays(live):
    """The driver drives some ticks, the watchdog stops it once, the driver leaves: the
    drive is a demonstration whose record replays exactly."""
    station, driving, filed, clock = live
    robot = station.robot
    alice, _ = client(station, "/page")
    answer = call(alice, "/lab/drive", {"session": "abc", "interface": "perception", "user": "ann"})
    assert answer["success"] and answer["seed"] == robot.sim.seed
    command = alice.advertise("/cmd_vel", TWIST)
    for tick in range(12):
        clock.now = tick * 0.1
        if tick < 4:
            command.publish({"linear": {"x": 0.3}, "angular": {"z": 0.5}})
        robot.expire_commands(clock.now)  # at 0.7 s the 0.3 m/s command has lapsed
        robot.step()
    alice.destroy()
    assert driving.current is None
    [demo] = filed
    assert (demo.user, demo.interface, demo.session) == ("ann", "perception", "abc")
    assert demo.reason == "the driver left at tick 12" and not demo.achieved
    assert demo.manifest["kind"] == "demonstration" and demo.manifest["live"] is True
    verdict = replay(demo.folder / "trial.mcap")
    assert verdict.verified, verdict
    assert verdict.ticks == 12


def test_an_episode_that_ends_is_filed_and_the_next_is_recorded_anew(live):
    """When the driven episode ends its drive is filed; the driver stays and the next
    episode (a reset) is recorded as another demonstration."""
    station, driving, filed, _ = live
    robot = station.robot
    alice, command = client(station, "/alice")
    command.publish({"linear": {"x": 0.1}})
    robot.sim.status = "truncated"  # the episode ends (as a time limit would end it)
    robot.sim.reason = "the time limit was reached"
    driving._tick()
    assert len(filed) == 1 and filed[0].reason.startswith("the episode ended at tick 0")
    assert driving.current is not None and driving.current.node is alice
    robot.reset()
    assert driving.current.recorder is not None
    command.publish({"linear": {"x": 0.1}})
    robot.step()
    driving.release("the driver released the robot")
    assert [d.seed for d in filed] == [filed[0].seed, filed[0].seed + 1]
