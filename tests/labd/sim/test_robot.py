"""The robot node: lockstep stepping through the graph, commands, episodes, live mode."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math

import pytest

from labd.errors import MessageError
from labd.graph.graph import Graph, Side
from labd.sim.robot import WATCHDOG, LiveRunner, Robot
from tests.labd.sim import pointmass
from tests.labd.sim.pointmass import TASK


@pytest.fixture
def world(registry):
    graph = Graph(registry, name="robot-test")
    robot = Robot(graph, TASK, {"time_limit": 2.0}, seed=3)
    client = graph.create_node("/controller")
    return graph, robot, client


def record(client, topic):
    got = []
    client.subscribe(topic, None, lambda m: got.append(m.data))
    return got


def step(client):
    answers = []
    client.call_service("/lab/step", None, answers.append)
    (answer,) = answers
    assert answer.ok
    return answer.response.data


def test_lockstep_applies_commands_then_publishes_then_answers(world):
    """A command sent before /lab/step moves the puck in that step, seen before the answer."""
    graph, robot, client = world
    events = []
    client.subscribe("/pose", None, lambda m: events.append(("pose", m.data["point"]["x"])))
    events.clear()  # the latched initial pose
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    cmd.publish({"linear": {"x": 0.5}})
    client.call_service("/lab/step", None, lambda r: events.append(("answer", r.response.data)))
    (pose, answer) = events
    assert pose[0] == "pose" and 0.0 < pose[1] < 0.06
    assert answer[1]["success"] is True and answer[1]["message"].startswith("tick 1 at 0.100 s")


def test_graph_time_is_simulation_time(world):
    """Stamps, /clock and the graph's clock follow the simulation, tick by tick."""
    graph, robot, client = world
    clocks = record(client, "/clock")
    for _ in range(3):
        step(client)
    assert clocks[-1] == {"clock": {"sec": 0, "nanosec": 300_000_000}}
    assert graph.now() == (0, 300_000_000)


def test_periodic_and_on_demand_topics(world):
    """A period-5 topic appears every fifth tick; an on-demand one only while subscribed."""
    graph, robot, client = world
    slow = record(client, "/slow")
    for _ in range(10):
        step(client)
    assert len(slow) == 1 + 2  # the latched initial one, then ticks 5 and 10
    assert robot.sim.task.renders == 0
    images = record(client, "/camera/image/compressed")
    assert len(images) == 1 and robot.sim.task.renders == 1  # rendered for the newcomer
    step(client)
    assert len(images) == 2 and robot.sim.task.renders == 2


def test_nan_command_is_refused_before_anyone_sees_it(world):
    """A NaN velocity is an error naming the field, and no subscriber receives it."""
    graph, robot, client = world
    seen = record(client, "/cmd_vel")
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    with pytest.raises(MessageError, match=r"linear\.x must be a finite number"):
        cmd.publish({"linear": {"x": None}})  # JSON null is NaN
    assert seen == []


def test_clipping_is_counted(world):
    """Commands beyond the limits are clipped and counted in the metrics."""
    graph, robot, client = world
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    cmd.publish({"linear": {"x": 7.0}})
    assert robot.sim.task.velocity[0] == 1.0
    assert robot.sim.metrics()["clipped_commands"] == 1


def test_episode_ends_and_further_steps_are_refused(world):
    """Reaching the goal ends the episode on /lab/episode; later steps answer success false."""
    graph, robot, client = world
    episodes = record(client, "/lab/episode")
    client.advertise("/cmd_vel", "geometry_msgs/msg/Twist").publish({"linear": {"x": 1.0}})
    for _ in range(30):
        answer = step(client)
        if "succeeded" in answer["message"]:
            break
    assert episodes[-1]["status"] == "succeeded" and episodes[-1]["success"] is True
    assert episodes[-1]["reason"] == "reached the goal"
    answers = []
    client.call_service("/lab/step", None, answers.append)
    assert answers[0].response.data["success"] is False
    assert "the episode has ended (succeeded" in answers[0].response.data["message"]


def test_time_limit_truncates(world):
    """Without reaching the goal, the episode is truncated at its time limit."""
    graph, robot, client = world
    for _ in range(20):
        answer = step(client)
    assert "truncated: the time limit of 2 s was reached" in answer["message"]
    assert robot.sim.status == "truncated"


def test_divergence_fails_the_episode_not_the_lab(world):
    """A diverging physics ends the episode as failed with the reason; the lab answers on."""
    graph, robot, client = world
    client.advertise("/explode", "std_msgs/msg/Bool").publish({"data": True})
    answer = step(client)
    assert "failed: the physics diverged at tick 1" in answer["message"]
    assert robot.sim.status == "failed"


def test_determinism_within_a_process(registry):
    """Two robots given the same seed and commands publish identical bytes."""
    streams = []
    for _ in range(2):
        graph = Graph(registry, name="det")
        Robot(graph, TASK, {}, seed=11)
        client = graph.create_node("/c")
        got = []
        client.subscribe("/pose", None, lambda m, got=got: got.append(m.cdr()))
        cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
        for i in range(12):
            cmd.publish({"linear": {"x": math.sin(i) / 2, "y": 0.1}})
            step(client)
        streams.append(got)
    assert streams[0] == streams[1] and len(streams[0]) == 13


def test_live_watchdog_stops_a_silent_twist(registry):
    """Live: a Twist not repeated within the watchdog time is replaced by zero."""
    now = [100.0]
    graph = Graph(registry, name="live")
    robot = Robot(graph, TASK, {}, live=True, wall_clock=lambda: now[0])
    client = graph.create_node("/teleop")
    client.advertise("/cmd_vel", "geometry_msgs/msg/Twist").publish({"linear": {"x": 0.5}})
    robot.expire_commands(now[0] + WATCHDOG / 2)
    assert robot.sim.task.velocity[0] == 0.5
    robot.expire_commands(now[0] + WATCHDOG * 2)
    assert robot.sim.task.velocity[0] == 0.0
    assert "/lab/reset" in graph.services and "/lab/step" not in graph.services


def test_live_robots_have_no_time_limit_unless_their_parameters_give_one(registry):
    """A live robot's episode runs past the task's default time limit (2 s here); one
    whose parameters give a limit ends there, truncated."""
    endless = Robot(Graph(registry, name="endless"), TASK, {}, live=True)
    limited = Robot(Graph(registry, name="limited"), TASK, {"time_limit": 0.5}, live=True)
    try:
        ticks = round(2.0 / endless.sim.control_timestep) + 5
        for _ in range(ticks):
            endless.step()
            if limited.sim.running:
                limited.step()
        assert endless.sim.running
        assert limited.sim.status == "truncated"
        assert limited.sim.tick == round(0.5 / limited.sim.control_timestep)
    finally:
        endless.close()
        limited.close()


def test_live_a_changed_command_is_reported_and_a_repeat_is_not(registry):
    """Live: ``on_command`` hears a client's command that changes what the robot was
    told, not a held key's repeats; after the watchdog's stop the same command is news."""
    now = [100.0]
    graph = Graph(registry, name="live")
    robot = Robot(graph, TASK, {}, live=True, wall_clock=lambda: now[0])
    heard = []
    robot.on_command = lambda: heard.append(robot.sim.task.velocity[0])
    cmd = graph.create_node("/teleop").advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    for x in (0.5, 0.5, 0.5, 0.0, 0.0, 0.5):
        cmd.publish({"linear": {"x": x}})
    robot.expire_commands(now[0] + WATCHDOG * 2)
    cmd.publish({"linear": {"x": 0.5}})
    assert heard == [0.5, 0.0, 0.5, 0.5]


async def test_live_runner_brings_the_next_tick_forward_for_a_changed_command(registry):
    """With ``prompt``, a changed command runs the next tick at once instead of on the
    grid (here 0.5 s apart), and the simulation's lead stays within one period; a
    repeat of the same command waits for its tick."""
    graph = Graph(registry, name="live")
    robot = Robot(graph, "icreate-maze", {"control_rate": 2}, live=True)
    client = graph.create_node("/teleop", side=Side.CLIENT)
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    loop = asyncio.get_running_loop()
    ticks: asyncio.Queue[float] = asyncio.Queue()
    client.subscribe("/clock", None, lambda m: ticks.put_nowait(loop.time()))
    runner = LiveRunner(robot, prompt=True)
    task = asyncio.create_task(runner.run())
    try:
        await ticks.get()
        ticked = await ticks.get()
        await asyncio.sleep(0.2)  # past the quarter period a command must wait
        sent = loop.time()
        cmd.publish({"angular": {"z": 1.0}})
        pulled = await ticks.get()
        assert sent <= pulled < ticked + 0.5  # brought forward: before its tick on the grid
        assert runner.early == 1 and 0 < runner.lead <= 0.5
        await asyncio.sleep(0.2)
        cmd.publish({"angular": {"z": 1.0}})
        assert await ticks.get() - pulled > 0.45
        assert runner.early == 1
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        robot.close()


async def test_live_runner_steps_on_past_a_tick_that_raises(registry, caplog):
    """A tick that raises (a bug in what runs on it) is logged once, with its traceback,
    and the runner steps on: the robot's clock keeps coming."""
    graph = Graph(registry, name="live")
    robot = Robot(graph, TASK, {}, live=True)

    def broken() -> None:
        raise RuntimeError("a bug in a drive")

    robot.on_tick = broken
    ticks: asyncio.Queue[object] = asyncio.Queue()
    graph.create_node("/watcher", side=Side.CLIENT).subscribe("/clock", None, ticks.put_nowait)
    runner = LiveRunner(robot)
    task = asyncio.create_task(runner.run())
    try:
        for _ in range(5):
            await asyncio.wait_for(ticks.get(), 5)
        assert runner.errors >= 4 and not task.done()
        logged = [r for r in caplog.records if "a tick failed" in r.getMessage()]
        assert len(logged) == 1 and logged[0].exc_info is not None, caplog.records
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        robot.close()


def test_reset_starts_the_next_seed(registry):
    """/lab/reset on a live robot starts a new episode with the next seed."""
    graph = Graph(registry, name="live")
    robot = Robot(graph, TASK, {}, seed=4, live=True)
    client = graph.create_node("/teleop")
    robot.step()
    answers = []
    client.call_service("/lab/reset", None, answers.append)
    assert answers[0].response.data["message"] == "new episode, seed 5"
    assert robot.sim.tick == 0 and robot.sim.seed == 5


def test_unheard_topics_are_built_when_someone_subscribes(world):
    """A topic no one heard is skipped, and a new subscriber still gets the current state."""
    graph, robot, client = world
    for _ in range(4):
        step(client)
    poses = record(client, "/pose")
    assert len(poses) == 1 and poses[0]["header"]["stamp"] == {"sec": 0, "nanosec": 400_000_000}


def test_a_late_subscriber_gets_what_was_published_once(registry):
    """/goal, published once when the episode begins, reaches a subscriber who comes
    ticks later, though nobody listened at tick 0."""
    graph = Graph(registry, name="late")
    robot = Robot(graph, "icreate-maze", {}, 4)
    client = graph.create_node("/late")
    step_once = []
    client.call_service("/lab/step", None, step_once.append)
    client.call_service("/lab/step", None, step_once.append)
    got = []
    client.subscribe("/goal", None, got.append)
    assert len(got) == 1 and got[0].data["header"]["stamp"] == {"sec": 0, "nanosec": 200_000_000}
    robot.close()


def test_a_task_not_built_in_normal_form_is_validated(registry):
    """A task that does not claim to build its observations in normal form (one from
    elsewhere) has them validated as a client's would be: a /pose with a field left
    out and an int for a float64 reaches a subscriber whole and typed."""

    class Sloppy(pointmass.PointMass):
        def observe(self, physics, topic, stamp):
            data = super().observe(physics, topic, stamp)
            if topic == "/pose":
                del data["point"]["z"]  # a default, which validation fills in
                data["point"]["x"] = 1  # an int where the type says float64
            return data

    def make(values, seed, **kwargs):
        return pointmass.make(values, seed, kind=Sloppy, **kwargs)

    for trusted, expected in ((False, {"x": 1.0, "y": 0.0, "z": 0.0}), (True, None)):
        spec = dataclasses.replace(TASK, build=make, normal_form=trusted)
        graph = Graph(registry, name=f"sloppy-{trusted}")
        robot = Robot(graph, spec, {}, seed=3)
        got = record(graph.create_node("/watcher"), "/pose")
        robot.publish()
        if expected is not None:
            assert got[-1]["point"] == expected
            assert type(got[-1]["point"]["x"]) is float
        else:  # what a task that claims normal form builds is passed on as built
            assert got[-1]["point"] == {"x": 1, "y": 0.0}
