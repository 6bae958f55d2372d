"""Attacks on a live robot's drives from anonymous bridge clients (issue 24: Broken 1-3).

A real `labd serve` hosts one live maze robot on loopback; the attackers are plain
rosbridge clients (`websockets`), as a visitor's script would be. A session given to
`/lab/drive` is a path, or 300 characters long; watchers publish on made-up topics and
on `/ux/events` with the driver's session; a driver fills its record; one address
files drive after drive. The lab must write nothing outside its data folder, keep the
robot stepping for everyone, file each drive under a name it gives, and keep the
archive's demonstrations to the robot's and the driver's own data, within a size and
a rate.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import os
import shutil
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import orjson
import pytest
from websockets.asyncio.client import ClientConnection, connect

from labd.config import DriveLimits
from labd.graph.types import TypeRegistry
from labd.recorder import read_channels, read_messages
from tests.faults.conftest import Served, wait_for
from tests.helpers.timing import SECOND

pytestmark = pytest.mark.integration
LAB = ("--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0")
TWIST = "geometry_msgs/msg/Twist"
UX = "lab_msgs/msg/UxEvent"
LIMITS = DriveLimits()
MiB = 1024 * 1024


class Client:
    """A rosbridge client of one robot: calls services, publishes, and keeps what it hears."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.heard: dict[str, list[dict[str, Any]]] = defaultdict(list)
        self.statuses: list[str] = []
        self._ids = itertools.count(1)
        self._replies: dict[str, asyncio.Future[dict[str, Any]]] = {}
        self._news = asyncio.Event()
        self._advertised: set[str] = set()
        self._subscribed: set[str] = set()
        self.reader = asyncio.create_task(self._read())

    @classmethod
    async def open(cls, url: str) -> Client:
        ws = await connect(url, max_size=None)
        client = cls(ws)
        await client.send({"op": "set_level", "level": "warning"})
        return client

    async def _read(self) -> None:
        async for frame in self.ws:
            message = orjson.loads(frame)
            if message["op"] == "publish":
                self.heard[message["topic"]].append(message["msg"])
                self._news.set()
            elif message["op"] == "service_response":
                future = self._replies.pop(message.get("id", ""), None)
                if future is not None and not future.done():
                    future.set_result(message)
            elif message["op"] == "status":
                self.statuses.append(message["msg"])

    async def send(self, frame: dict[str, Any]) -> None:
        await self.ws.send(orjson.dumps(frame).decode())

    async def call(
        self, service: str, args: dict[str, Any] | None = None, timeout: float = 10
    ) -> dict[str, Any]:
        """The service's answer: its values, with ``result`` (False: the call failed)."""
        call_id = f"call-{next(self._ids)}"
        future = self._replies[call_id] = asyncio.get_running_loop().create_future()
        await self.send({"op": "call_service", "service": service, "args": args or {},
                         "id": call_id})  # fmt: skip
        try:
            answer = await asyncio.wait_for(future, timeout)
        except TimeoutError:
            return {"result": False, "message": f"{service}: no answer within {timeout:g} s"}
        values = answer.get("values")
        if not isinstance(values, dict):
            values = {"message": str(values)}
        return {**values, "result": answer.get("result", False)}

    async def subscribe(self, topic: str, type_name: str) -> None:
        if topic not in self._subscribed:
            await self.send({"op": "subscribe", "topic": topic, "type": type_name})
            self._subscribed.add(topic)

    async def publish(self, topic: str, type_name: str, msg: dict[str, Any]) -> None:
        if topic not in self._advertised:
            await self.send({"op": "advertise", "topic": topic, "type": type_name})
            self._advertised.add(topic)
        await self.send({"op": "publish", "topic": topic, "msg": msg})

    async def settled(self) -> None:
        """Every frame sent before this has been handled by the lab (one round trip)."""
        answer = await self.call("/rosapi/get_time")
        assert answer["result"], answer

    async def heard_where(
        self,
        topic: str,
        predicate: Callable[[dict[str, Any]], bool],
        timeout: float,
        since: int | None = None,
    ) -> dict[str, Any] | None:
        """The first message on ``topic`` from now on (or from its ``since``-th) for
        which ``predicate`` holds, or None if none comes within ``timeout`` seconds."""
        seen = len(self.heard[topic]) if since is None else since
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            for message in self.heard[topic][seen:]:
                if predicate(message):
                    return message
            seen = len(self.heard[topic])
            self._news.clear()
            left = deadline - loop.time()
            if left <= 0:
                return None
            try:
                await asyncio.wait_for(self._news.wait(), left)
            except TimeoutError:
                return None

    async def close(self) -> None:
        await self.ws.close()
        self.reader.cancel()


async def drive_ticks(driver: Client, answer: dict[str, Any], ticks: int) -> None:
    """Command the robot, and go on until the episode its drive started (``answer``,
    /lab/drive's) has run ``ticks`` ticks."""
    assert answer["success"], answer
    await driver.subscribe("/lab/episode", "lab_msgs/msg/Episode")
    await driver.publish("/cmd_vel", TWIST, {"linear": {"x": 0.1}, "angular": {"z": 0.3}})
    seed = answer["seed"]
    reached = await driver.heard_where(
        "/lab/episode", lambda m: m["seed"] == seed and m["tick"] >= ticks, 30, since=0
    )
    assert reached is not None, f"the driven episode (seed {seed}) did not reach tick {ticks}"


def demonstrations(lab: Served) -> list[dict[str, Any]]:
    trials: list[dict[str, Any]] = lab.get("/api/trials?kind=demonstration&limit=500")["trials"]
    return trials


def filings_done(lab: Served) -> None:
    """Wait until nobody drives and no drive's record is left in the work folder (each is
    filed or dropped: the lab deletes it once it is in the archive)."""
    live = lab.data / "work" / "live"

    def done() -> bool:
        robots = lab.get("/api/robots")
        return all(r["driver"] == "" for r in robots) and not (
            live.is_dir() and any(p.is_file() for p in live.rglob("*"))
        )

    wait_for("the drives to be filed", done, 60, every=0.2)


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# -- Broken 1: a session is a path; a typed user is who drove ---------------------------


@pytest.mark.timeout(120)
def test_a_session_never_becomes_a_path_nor_a_typed_user_the_driver(served, tmp_path: Path):
    """A drive whose session is a path out of the data folder writes nothing there and
    deletes nothing there; the session is kept only as data, and the drive is filed under
    a name the lab gives, the typed user kept apart as a claim."""
    outside = tmp_path / "outside"
    for seed in range(10):  # the folder the unfixed lab names: SESSION-SEED under it
        (outside / f"written-{seed}").mkdir(parents=True)
        (outside / f"written-{seed}" / "precious.txt").write_text(f"keep me {seed}\n")
    before = tree(outside)
    lab = served(*LAB).start()
    # DATA/work/live/icreate-1-<session>-<seed>: four levels up from there is tmp_path.
    session = "/../../../../outside/written"

    async def attack() -> dict[str, Any]:
        driver = await Client.open(lab.bridge + "/robots/icreate-1")
        try:
            answer = await driver.call(
                "/lab/drive", {"session": session, "interface": "video", "user": "mallory"}
            )
            await drive_ticks(driver, answer, LIMITS.min_ticks + 5)
            released = await driver.call("/lab/release")
            return {"drive": answer, "release": released}
        finally:
            await driver.close()

    answers = asyncio.run(attack())
    filings_done(lab)
    print("path as a session:", answers, "outside now:", sorted(tree(outside)))
    assert tree(outside) == before, "the drive wrote or deleted outside the data folder"
    assert answers["drive"]["success"], answers
    [demo] = demonstrations(lab)
    trial = lab.trial(demo["id"])
    assert demo["submitter"] != "mallory" and demo["submitter"].startswith("guest:"), demo
    driver = trial["manifest"]["driver"]
    assert driver["session"] == session and driver["claimed_user"] == "mallory", driver
    assert driver["user"] == demo["submitter"]


# -- Broken 2: one drive's error freezes the robot ---------------------------------------


@pytest.mark.rates  # one at a time with the others that load the machine
@pytest.mark.timeout(150 * SECOND)
@pytest.mark.parametrize("attack", ["long-session", "unwritable-record"])
def test_an_error_in_one_drive_does_not_freeze_the_robot(served, attack: str):
    """After a drive whose record cannot be made (a 300-character session, or a work
    folder that is not a folder), the robot's episode still ends and the next one runs,
    and a watcher gets /odom again in it (40 messages, in order); the driver is told."""
    lab = served(*LAB, "--param", "time_limit=4").start()
    if attack == "unwritable-record":
        live = lab.data / "work" / "live"
        shutil.rmtree(live)
        live.write_text("a file where the lab keeps drives being recorded\n")
    session = "s" * 300 if attack == "long-session" else "page-1"
    figures = asyncio.run(freeze(lab.bridge + "/robots/icreate-1", session))
    print(f"{attack}:", figures)
    assert figures["next_episode"], f"the robot froze after the drive:\n{figures}\n{lab.log}"
    assert figures["odom_after"] >= ODOM, figures  # the robot steps for everyone again
    assert figures["odom_in_order"], figures  # rising, or back to 0 at the new episode
    assert lab.process is not None and lab.process.poll() is None, lab.log
    answer = figures["answer"]
    if attack == "long-session":
        assert answer["success"] is False, answer
        assert f"at most {LIMITS.max_text} characters" in answer["message"], answer
    else:
        assert answer["success"] is True, answer
        assert "not recorded" in answer["message"], answer
        assert "Traceback" in lab.log and "not recorded" in lab.log, lab.log


ODOM = 40  # /odom messages a watcher hears before the drive, and in the next episode


async def freeze(url: str, session: str) -> dict[str, Any]:
    watcher = await Client.open(url)
    attacker = await Client.open(url)
    try:
        await watcher.subscribe("/odom", "nav_msgs/msg/Odometry")
        await watcher.subscribe("/lab/episode", "lab_msgs/msg/Episode")
        running = await watcher.heard_where("/lab/episode", lambda m: m["tick"] > 0, 30 * SECOND)
        assert running is not None, "the robot does not step"
        odom_before = await odom_heard(watcher, ODOM)
        mark = len(watcher.heard["/lab/episode"])
        answer = await attacker.call(
            "/lab/drive", {"session": session, "interface": "video", "user": "x"}, timeout=8
        )
        await attacker.publish("/cmd_vel", TWIST, {"linear": {"x": 0.2}})
        # The 4 s episode ends, is shown for 3 s, and the next one starts.
        ended = await watcher.heard_where(
            "/lab/episode", lambda m: m["status"] != "running", 20 * SECOND, mark
        )
        following = None
        if ended is not None:
            following = await watcher.heard_where(
                "/lab/episode",
                lambda m: m["seed"] > ended["seed"] and m["tick"] > 0,  # seeds only grow
                15 * SECOND,
                mark,
            )
        odom_after = await odom_heard(watcher, ODOM) if following is not None else 0
        stamps = [stamp_ns(m) for m in watcher.heard["/odom"]]
        return {
            "answer": answer,
            "ended": ended is not None,
            "next_episode": following is not None,
            "odom_before": odom_before,
            "odom_after": odom_after,
            "odom_in_order": all(b > a or b <= STEP for a, b in itertools.pairwise(stamps)),
        }
    finally:
        await attacker.close()
        await watcher.close()


STEP = 50_000_000  # ns: an episode's first tick (20 Hz) is at most this far from its start


def stamp_ns(message: dict[str, Any]) -> int:
    stamp = message["header"]["stamp"]
    return int(stamp["sec"]) * 1_000_000_000 + int(stamp["nanosec"])


async def odom_heard(watcher: Client, count: int) -> int:
    """How many /odom messages the watcher hears from now on, waiting for ``count``
    (a robot that froze sends none)."""
    mark = len(watcher.heard["/odom"])
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 30 * SECOND
    while len(watcher.heard["/odom"]) - mark < count and (left := deadline - loop.time()) > 0:
        await watcher.heard_where("/odom", lambda m: True, left)
    return len(watcher.heard["/odom"]) - mark


# -- Broken 3: watchers fill the driver's record; one client fills the archive ---------


@pytest.mark.timeout(120)
def test_a_demonstration_holds_only_the_robot_and_its_driver(served, tmp_path: Path):
    """Watchers' messages on made-up topics and their /ux/events with the driver's
    session are not in the driver's demonstration; the driver's commands and events are."""
    lab = served(*LAB).start()
    url = lab.bridge + "/robots/icreate-1"
    junk = "j" * (100 * 1024)

    async def attack() -> dict[str, int]:
        driver, watcher = await Client.open(url), await Client.open(url)
        try:
            answer = await driver.call("/lab/drive", {"session": "page-1", "interface": "video"})
            assert answer["success"], answer
            event = {"session": "page-1", "kind": "key", "key": "ArrowUp", "value": "down",
                     "browser_ms": 1.0}  # fmt: skip
            for _ in range(3):
                await driver.publish("/ux/events", UX, event)
            for n in range(20):  # 2 MB on a topic of the watcher's own
                await watcher.publish("/junk", "std_msgs/msg/String", {"data": junk})
                await watcher.publish("/ux/events", UX, {**event, "kind": "forged", "value": n})
            await watcher.settled()
            await drive_ticks(driver, answer, LIMITS.min_ticks + 5)
            await driver.settled()
            released = await driver.call("/lab/release")
            assert released["success"], released
            return {"driver_events": 3}
        finally:
            await driver.close()
            await watcher.close()

    sent = asyncio.run(attack())
    filings_done(lab)
    [demo] = demonstrations(lab)
    record = tmp_path / "demo.mcap"
    record.write_bytes(httpx.get(demo["mcap"]["url"], timeout=60).content)
    channels = {(c.topic, c.side.value): c.message_count for c in read_channels(record)}
    print("the demonstration's channels:", channels)
    assert not any(topic == "/junk" for topic, _ in channels), channels
    types = TypeRegistry.default().typestore
    events = [
        types.deserialize_cdr(m.data, UX) for m in read_messages(record, topics=["/ux/events"])
    ]
    assert [e.kind for e in events] == ["key"] * sent["driver_events"], [e.kind for e in events]
    assert channels[("/cmd_vel", "client")] >= 1, channels


@pytest.mark.timeout(180)
def test_a_record_past_its_size_limit_ends_its_drive(served):
    """A driver that sends more than the record's size limit (64 MiB of events that do
    not compress) has its drive ended at the limit and filed as it stands, saying why."""
    lab = served(*LAB).start()
    limit = LIMITS.max_record
    value = base64.b64encode(os.urandom(768 * 1024)).decode()  # 1 MiB of text, ~0.77 MiB zstd
    count = int(1.3 * limit / (768 * 1024))

    async def attack() -> dict[str, Any]:
        driver = await Client.open(lab.bridge + "/robots/icreate-1")
        try:
            await driver.subscribe("/lab/driver", "lab_msgs/msg/Driver")
            answer = await driver.call("/lab/drive", {"session": "big", "interface": "video"})
            assert answer["success"], answer
            await drive_ticks(driver, answer, LIMITS.min_ticks + 5)  # a demonstration, so far
            mark = len(driver.heard["/lab/driver"])
            for n in range(count):  # within the bridge's burst of /ux/events at 50 a second
                await driver.publish("/ux/events", UX, {"session": "big", "kind": "fill",
                                                        "key": str(n), "value": value})  # fmt: skip
                if n % 40 == 39:
                    await driver.settled()
                    await asyncio.sleep(0.8)  # the bridge lets 50 events a second through
            await driver.settled()
            ended = await driver.heard_where("/lab/driver", lambda m: m["driver"] == "", 10, mark)
            return {"ended": ended is not None, "sent": count}
        finally:
            await driver.close()

    figures = asyncio.run(attack())
    filings_done(lab)
    [demo] = demonstrations(lab)
    size = demo["mcap"]["size"]
    print(f"record size limit {limit / MiB:g} MiB: sent {figures['sent']} MiB of events;"
          f" filed {size / MiB:.1f} MiB: {demo['reason']}")  # fmt: skip
    assert figures["ended"], "the drive did not end at the record's size limit"
    assert limit - 2 * MiB <= size <= limit + 2 * MiB, size  # chunks of 1 MiB: near it
    assert f"size limit of {limit // MiB} MiB" in demo["reason"], demo["reason"]


@pytest.mark.timeout(180)
def test_drives_without_commands_short_ones_and_too_many_file_nothing(served):
    """Drives with no command, or shorter than the minimum, file nothing; past the
    filings a minute one address may make, a further drive is not filed, from a new
    connection too; each not filed says why."""
    lab = served(*LAB).start()
    url = lab.bridge + "/robots/icreate-1"
    quota = LIMITS.filings_per_minute

    async def attack() -> list[str]:
        driver = await Client.open(url)
        notes = []
        try:
            drive = {"session": "s", "interface": "video"}
            for _ in range(3):  # no command at all
                answer = await driver.call("/lab/drive", drive)
                notes.append(answer["message"])
            for _ in range(3):  # a command, then at once another drive
                answer = await driver.call("/lab/drive", drive)
                notes.append(answer["message"])
                await driver.publish("/cmd_vel", TWIST, {"linear": {"x": 0.1}})
                await driver.settled()
            for _ in range(quota + 1):  # long enough, with commands
                answer = await driver.call("/lab/drive", drive)
                notes.append(answer["message"])
                await drive_ticks(driver, answer, LIMITS.min_ticks + 2)
            notes.append((await driver.call("/lab/release"))["message"])
        finally:
            await driver.close()
        other = await Client.open(url)  # the same address, a new connection
        try:
            answer = await other.call("/lab/drive", drive)
            await drive_ticks(other, answer, LIMITS.min_ticks + 2)
            notes.append((await other.call("/lab/release"))["message"])
        finally:
            await other.close()
        return notes

    notes = asyncio.run(attack())
    filings_done(lab)
    filed = demonstrations(lab)
    print(f"{len(filed)} demonstrations filed of {3 + 3 + quota + 2} drives:", *notes, sep="\n  ")
    assert len(filed) == quota, [d["reason"] for d in filed]
    text = "\n".join(notes)
    assert text.count("not filed: no command") == 3, text
    assert text.count(f"not filed: shorter than {LIMITS.min_ticks} ticks") == 3, text
    assert text.count(f"{quota} drives were filed from your address") == 2, text
