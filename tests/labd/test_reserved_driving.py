"""Driving with reservations on: only a client whose key opened the robot drives, and
its drive is filed under the key's user, never under a name it gives."""

from __future__ import annotations

import pytest

from labd.config import DriveLimits
from labd.graph.graph import Side
from labd.live import Driving, NotDriving, NotReserved
from labd.station import Station

TWIST = "geometry_msgs/msg/Twist"


@pytest.fixture
def live(registry, tmp_path):
    station = Station(
        registry, "icreate-1", "icreate-maze", {}, 7, live=True, protected_prefixes=("/protected",)
    )
    filed = []
    driving = Driving(station, work=tmp_path / "live", file=filed.append, reserved=True)
    yield station, driving, filed
    driving.close()
    station.close()


def client(station, name, user=None):
    node = station.graph.create_node(name, side=Side.CLIENT)
    node.user = user
    return node, node.advertise("/cmd_vel", TWIST)


def call(node, service, request=None):
    answers = []
    node.call_service(service, request, answers.append)
    return answers[0].response.data


def test_without_a_key_a_client_watches_and_is_told_how_to_book(live):
    """A client without a key is refused commands, /lab/drive and /lab/reset, with
    how to book; nobody drives."""
    station, driving, filed = live
    visitor, command = client(station, "/visitor")
    with pytest.raises(NotReserved, match="driven only in a reserved slot; you are watching"):
        command.publish({"linear": {"x": 0.2}})
    answer = call(visitor, "/lab/drive", {"user": "mallory"})
    assert answer["success"] is False and "book a slot" in answer["message"]
    assert call(visitor, "/lab/reset")["success"] is False
    assert driving.current is None and filed == []


def test_the_key_holder_drives_under_their_own_name(live):
    """The client with the slot's key drives; the drive is the key's user's even when
    /lab/drive names someone else; another keyed client is refused while they drive."""
    station, driving, filed = live
    alice, command = client(station, "/page_1", user="alice")
    answer = call(alice, "/lab/drive", {"user": "mallory", "interface": "video"})
    assert answer["success"], answer
    command.publish({"linear": {"x": 0.2}})
    assert driving.current is not None and driving.current.user == "alice"
    other, other_command = client(station, "/page_2", user="alice")  # a second tab
    with pytest.raises(NotDriving, match="driven by alice"):
        other_command.publish({"linear": {"x": -0.2}})
    for _ in range(DriveLimits().min_ticks):  # a drive long enough to be filed
        station.robot.step()
    alice.destroy()
    [demo] = filed
    driver = demo.manifest.driver
    assert demo.user == "alice" and driver is not None and driver.user == "alice"
    assert driver.claimed_user == "mallory"  # kept apart, unchecked
