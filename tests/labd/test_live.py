"""Driving a live robot: one driver at a time, and each drive recorded as a demonstration
that replays, the watchdog's stops included; what a client's drive may put in the
archive, under which name, and a drive's errors kept to that drive."""

from __future__ import annotations

import logging
import os

import pytest

from labd.config import DriveLimits
from labd.graph.graph import Side
from labd.live import Driving, Filings, NotDriving
from labd.recorder import read_channels, read_messages
from labd.replay import replay
from labd.station import Station
from repository.manifest import Driver

TWIST = "geometry_msgs/msg/Twist"
UX = "lab_msgs/msg/UxEvent"
LIMITS = DriveLimits()
ENOUGH = LIMITS.min_ticks + 5  # ticks of a drive long enough to be filed


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def make(registry, work, filed, **options):
    station = Station(
        registry, "icreate-1", "icreate-maze", {}, 7, live=True, protected_prefixes=("/protected",)
    )
    clock = Clock()
    station.robot.wall_clock = clock
    driving = Driving(station, work=work, file=filed.append, **options)
    return station, driving, clock


@pytest.fixture
def live(registry, tmp_path):
    filed = []
    station, driving, clock = make(registry, tmp_path / "live", filed)
    yield station, driving, filed, clock
    driving.close()
    station.close()


def client(station, name, address=None):
    node = station.graph.create_node(name, side=Side.CLIENT)
    node.address = address
    return node, node.advertise("/cmd_vel", TWIST)


def call(node, service, request=None):
    answers = []
    node.call_service(service, request, answers.append)
    return answers[0].response.data


def drive(station, command, ticks):
    """The driver commands, and the robot steps ``ticks`` times."""
    command.publish({"linear": {"x": 0.2}, "angular": {"z": 0.3}})
    for _ in range(ticks):
        station.robot.step()


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
    assert heard[-1].data["driver"] == "guest:alice" and heard[-1].data["recording"] is True
    with pytest.raises(NotDriving, match="driven by guest:alice; you are watching"):
        bob_cmd.publish({"linear": {"x": -1.0}})
    refused = call(bob, "/lab/drive", {"session": "s", "interface": "video", "user": "bob"})
    assert refused == {"success": False, "message": "guest:alice drives", "seed": 0}
    assert call(bob, "/lab/reset")["success"] is False
    assert filed == []


def test_a_drive_is_filed_when_the_driver_leaves_and_replays(live):
    """The driver drives some ticks, the watchdog stops it once, the driver leaves: the
    drive is a demonstration whose record replays exactly, filed under the lab's name
    for the client, the user it typed kept apart as a claim."""
    station, driving, filed, clock = live
    robot = station.robot
    alice, _ = client(station, "/page")
    answer = call(alice, "/lab/drive", {"session": "abc", "interface": "perception", "user": "ann"})
    assert answer["success"] and answer["seed"] == robot.sim.seed
    command = alice.advertise("/cmd_vel", TWIST)
    for tick in range(ENOUGH):
        clock.now = tick * 0.1
        if tick < 4:
            command.publish({"linear": {"x": 0.3}, "angular": {"z": 0.5}})
        robot.expire_commands(clock.now)  # at 0.7 s the 0.3 m/s command has lapsed
        robot.step()
    alice.destroy()
    assert driving.current is None
    [demo] = filed
    assert (demo.user, demo.interface, demo.session) == ("guest:page", "perception", "abc")
    assert demo.manifest.driver == Driver(
        user="guest:page", claimed_user="ann", interface="perception", session="abc"
    )
    assert demo.manifest.to_json()["driver"] == {
        "user": "guest:page",
        "claimed_user": "ann",
        "interface": "perception",
        "session": "abc",
    }
    assert demo.reason == f"the driver left at tick {ENOUGH}" and not demo.achieved
    assert demo.manifest.kind == "demonstration" and demo.manifest.live is True
    verdict = replay(demo.folder / "trial.mcap")
    assert verdict.verified, verdict
    assert verdict.ticks == ENOUGH


def test_an_episode_that_ends_is_filed_and_the_next_is_recorded_anew(live):
    """When the driven episode ends its drive is filed; the driver stays and the next
    episode (a reset) is recorded as another demonstration."""
    station, driving, filed, _ = live
    robot = station.robot
    alice, command = client(station, "/alice")
    drive(station, command, ENOUGH)
    robot.sim.status = "truncated"  # the episode ends (as a time limit would end it)
    robot.sim.reason = "the time limit was reached"
    driving._tick()
    assert len(filed) == 1 and filed[0].reason.startswith(f"the episode ended at tick {ENOUGH}")
    assert driving.current is not None and driving.current.node is alice
    robot.reset()
    assert driving.current.recorder is not None
    drive(station, command, ENOUGH)
    driving.release("the driver released the robot")
    assert [d.seed for d in filed] == [filed[0].seed, filed[0].seed + 1]


def test_a_reset_mid_drive_files_the_episode_it_ended(live):
    """/lab/reset during a drive files the episode being driven, with its own seed and
    ticks (read before the reset replaced it), and records the next."""
    station, driving, filed, _ = live
    alice, command = client(station, "/alice")
    drive(station, command, ENOUGH)
    seed = station.robot.sim.seed
    assert call(alice, "/lab/reset")["success"]
    [demo] = filed
    assert (demo.seed, demo.metrics["ticks"]) == (seed, ENOUGH)
    assert demo.reason == f"the episode was reset at tick {ENOUGH}"
    assert driving.current is not None and driving.current.recorder is not None


def test_what_a_client_gives_is_data_never_a_path(live, tmp_path):
    """A session that is a path is kept as data and the record's folder is the lab's,
    in the work folder; a text over the limit or with a control character is refused,
    saying so, and nobody drives."""
    station, driving, filed, _ = live
    page, command = client(station, "/page")
    path = "/../../../outside/written"
    assert call(page, "/lab/drive", {"session": path, "interface": "video"})["success"]
    assert driving.current is not None and driving.current.folder is not None
    assert driving.current.folder.parent == tmp_path / "live"
    assert path not in str(driving.current.folder)
    drive(station, command, ENOUGH)
    call(page, "/lab/release")
    [demo] = filed
    assert demo.manifest.driver is not None and demo.manifest.driver.session == path
    assert not (tmp_path / "outside").exists()
    limit = LIMITS.max_text
    for request in (
        {"session": "s" * (limit + 1)},
        {"interface": "i" * 300},
        {"user": "u" * (limit + 1)},
        {"session": "two\nlines"},
    ):
        answer = call(page, "/lab/drive", request)
        assert answer["success"] is False, request
        assert f"may be at most {limit} characters, none of them a control" in answer["message"]
    assert driving.current is None
    assert call(page, "/lab/drive", {"session": "s" * limit})["success"]


def test_a_record_holds_the_robot_and_its_driver_only(live):
    """A watcher's messages on its own topics, and its /ux/events with the driver's
    session, are not in the driver's record; the driver's commands and events are."""
    station, driving, filed, _ = live
    page, command = client(station, "/page")
    watcher, _ = client(station, "/watcher")
    assert call(page, "/lab/drive", {"session": "s-1"})["success"]
    event = {"session": "s-1", "kind": "key", "key": "ArrowUp", "value": "down"}
    page.advertise("/ux/events", UX).publish(event)
    watcher.advertise("/junk", "std_msgs/msg/String").publish({"data": "x" * 10_000})
    watcher.advertise("/ux/events", UX).publish({**event, "kind": "forged"})
    page.advertise("/own", "std_msgs/msg/String").publish({"data": "the driver's own topic"})
    drive(station, command, ENOUGH)
    call(page, "/lab/release")
    [demo] = filed
    mcap = demo.folder / "trial.mcap"
    channels = {(c.topic, c.side) for c in read_channels(mcap)}
    assert ("/cmd_vel", Side.CLIENT) in channels and ("/odom", Side.LAB) in channels
    assert {topic for topic, _ in channels}.isdisjoint({"/junk", "/own", "/rosout"}), channels
    events = [m.data for m in read_messages(mcap, topics=["/ux/events"])]
    types = station.graph.types.typestore
    assert [types.deserialize_cdr(e, UX).kind for e in events] == ["key"]


def test_a_client_drive_without_a_command_or_too_short_files_nothing(live):
    """A client's drive that gave no command, or ran fewer ticks than the minimum,
    is not filed, and the driver is told why when it releases or drives again."""
    station, driving, filed, _ = live
    page, command = client(station, "/page")
    call(page, "/lab/drive")
    station.robot.step()
    again = call(page, "/lab/drive")
    assert again["message"].endswith("your last drive is not filed: no command was given")
    drive(station, command, LIMITS.min_ticks - 1)
    released = call(page, "/lab/release")
    least = LIMITS.min_ticks
    assert released["message"] == (
        f"released; the drive is not filed: shorter than {least} ticks ({least - 1})"
    )
    assert filed == [] and not any(driving.work.iterdir())
    call(page, "/lab/drive")
    drive(station, command, least)
    assert (
        call(page, "/lab/release")["message"] == "released; the drive is filed as a demonstration"
    )
    assert len(filed) == 1


def test_filings_a_minute_are_limited_per_address_over_robots(registry, tmp_path):
    """Past the filings a minute one address may make, over two robots and new
    connections, a drive is not filed, saying when the next may be; a minute on, it is."""
    filed = []
    limits = DriveLimits(filings_per_minute=2)
    shared = Filings(limits.filings_per_minute)
    one, first, clock = make(registry, tmp_path / "a", filed, limits=limits, filings=shared)
    two, second, _ = make(registry, tmp_path / "b", filed, limits=limits, filings=shared)
    two.robot.wall_clock = clock
    try:
        notes = []
        for n, station in enumerate((one, two, two)):
            clock.now = 10.0 * n
            node, command = client(station, f"/client_{n}", address="10.0.0.1")
            call(node, "/lab/drive")
            drive(station, command, ENOUGH)
            notes.append(call(node, "/lab/release")["message"])
            node.destroy()
        assert notes[:2] == ["released; the drive is filed as a demonstration"] * 2
        assert notes[2] == (
            "released; the drive is not filed: 2 drives were filed from your address in the"
            " last minute, the most the lab files; the next may be filed in 40 s"
        )
        other, command = client(one, "/elsewhere", address="10.0.0.2")
        call(other, "/lab/drive")
        drive(one, command, ENOUGH)
        assert call(other, "/lab/release")["message"].endswith("filed as a demonstration")
        clock.now = 61.0
        node, command = client(two, "/later", address="10.0.0.1")
        call(node, "/lab/drive")
        drive(two, command, ENOUGH)
        assert call(node, "/lab/release")["message"].endswith("filed as a demonstration")
        assert len(filed) == 4
    finally:
        for driving, station in ((first, one), (second, two)):
            driving.close()
            station.close()


def test_the_labs_own_driver_is_trusted_with_its_user(live):
    """A drive the lab's own code takes (a scripted driver) is filed under the user it
    names, short and without a command as it may be."""
    station, driving, filed, _ = live
    node = station.graph.create_node("/scripted", side=Side.CLIENT)
    driving.take(node, user="script", interface="script")
    station.robot.step()
    driving.release("the script stopped")
    [demo] = filed
    assert demo.user == "script"


def test_a_record_past_its_size_limit_ends_the_drive_filed_as_it_stands(registry, tmp_path):
    """Past the record's size limit the driver's events are no longer recorded, and the
    drive ends at the next tick, filed with the reason; the record stays near the limit."""
    filed = []
    limit = 256 * 1024
    station, driving, _ = make(
        registry, tmp_path / "live", filed, limits=DriveLimits(max_record=limit)
    )
    try:
        page, command = client(station, "/page")
        call(page, "/lab/drive", {"session": "big"})
        drive(station, command, ENOUGH)
        events = page.advertise("/ux/events", UX)
        for n in range(100):  # 50 kB each, half of it after compression
            noise = os.urandom(25_000).hex()
            events.publish({"session": "big", "kind": "fill", "key": str(n), "value": noise})
            if driving.current is None:
                break
            station.robot.step()
        assert driving.current is None, "the drive did not end at the size limit"
        [demo] = filed
        assert demo.reason.startswith("the record reached its size limit of 0.25 MiB at tick")
        size = (demo.folder / "trial.mcap").stat().st_size
        assert limit <= size <= limit + 1024 * 1024, size
    finally:
        driving.close()
        station.close()


def test_a_drive_whose_record_cannot_be_made_goes_on_unrecorded(registry, tmp_path, caplog):
    """A work folder that is a file: the drive is taken, the driver told it is not
    recorded, the error logged with its traceback; the robot steps on, and nothing is
    filed."""
    work = tmp_path / "live"
    work.write_text("not a folder")
    filed = []
    station, driving, _ = make(registry, work, filed)
    try:
        page, command = client(station, "/page")
        with caplog.at_level(logging.ERROR, logger="labd.live"):
            answer = call(page, "/lab/drive", {"session": "s"})
        assert answer["success"], answer
        assert "this drive is not recorded: its record could not be made" in answer["message"]
        assert any(r.exc_info for r in caplog.records), caplog.records
        drive(station, command, ENOUGH)
        assert station.robot.sim.tick == ENOUGH
        assert call(page, "/lab/release")["message"].startswith(
            "released; the drive is not recorded"
        )
        assert filed == []
    finally:
        driving.close()
        station.close()


def test_a_drive_whose_filing_fails_is_dropped_and_the_robot_steps_on(registry, tmp_path, caplog):
    """Filing that raises (a bug, a full archive) drops that drive's record, logged with
    its traceback; the episode's end does not raise into the robot's tick."""
    station = Station(
        registry, "icreate-1", "icreate-maze", {"time_limit": 1.5}, 7, live=True,
        protected_prefixes=("/protected",),
    )  # fmt: skip

    def broken(demo):
        raise RuntimeError("the archive is away")

    driving = Driving(station, work=tmp_path / "live", file=broken)
    robot = station.robot
    try:
        page, command = client(station, "/page")
        call(page, "/lab/drive")
        command.publish({"linear": {"x": 0.2}})
        with caplog.at_level(logging.ERROR, logger="labd.live"):
            while robot.sim.running:  # the tick that ends the episode files its drive
                robot.step()
        assert robot.sim.tick == 30
        assert "this drive is not filed: the archive is away" in caplog.text
        assert any(r.exc_info for r in caplog.records)
        assert not any((tmp_path / "live").iterdir())
        robot.reset()  # the next episode is recorded, and the robot steps
        robot.step()
        assert driving.current is not None and driving.current.recorder is not None
    finally:
        driving.close()
        station.close()
