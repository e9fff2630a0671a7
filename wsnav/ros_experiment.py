# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportUnknownVariableType=false, reportUnknownArgumentType=false, reportAttributeAccessIssue=false
"""`wsnav experiment --backend ros`: the same planned runs (routes, raffles, seeds, configurations) driven by the
ROS 1 navigation installed here (move_base, navfn, DWA, costmap_2d) instead of wsnav's own navigator.

One roscore of our own on a free loopback port for the whole experiment (its /use_sim_time and /move_base
parameters are ours to set); per run: a fresh embedded broker, `wsnav sim --ros --clock` as the robot (its world
from the zone simulator over MQTT, simulated time on /clock), move_base with the configuration's parameters and,
for a configuration with the zone layer, `wsnav ros bridge --robot` (the zone grid and Algorithm 3; the goal goes
through its relay so the bridge's re-sends do not end it). This process is a ROS node too: it publishes the
site's map, sends the goal and reads /clock and /odom. move_base's CPU is its process's (user + system, psutil)
over the run, as the paper measured it. Replans and recoveries are counted from what move_base publishes: its
global planner's makePlan calls (navfn publishes a found plan twice with one stamp, an empty one once) and noetic's
/move_base/recovery_status (one per recovery behaviour); a move_base that publishes one of them not, or whose
topic this node could not connect to before the goal, has that column written as missing, never as 0.
"""

from __future__ import annotations

import copy
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import xmlrpc.client
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import yaml

import wsnav.ros_bridge
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.experiments.run_plan import RunSpec
from wsnav.experiments.single_run import (
    ROBOT,
    SENSORS,
    TIMEOUT_SIM_S,
    TRAJECTORY_EVERY_S,
    RunResult,
    StallMeter,
    start_pose,
)
from wsnav.robot_agent.agent_config import load_agent_config
from wsnav.ros_bridge.ros_env import LocalRosCore, require_rospy, stop_process_group
from wsnav.runtime.cli_support import CliError
from wsnav.runtime.clock import WallClock
from wsnav.schemas.site import Site
from wsnav.zone_sim.simulator import ZoneSimulator

MOVE_BASE_CMD = "rosrun move_base move_base"
"""The navigation process each run starts (`--move-base-cmd`); `move_base_argv` names its node move_base."""
NODE_NAME = "__name:=move_base"
"""The node name every run's move_base gets: the binary calls itself move_base_node (TurtleBot3's launch file
renames it), and its parameters, plan and recovery topics live under its node name, where this backend sets and
reads them under /move_base."""
RECOVERY_STATUS = "/move_base/recovery_status"
"""move_base_msgs/RecoveryStatus, one per recovery behaviour move_base runs (noetic's move_base)."""
CONNECT_TIMEOUT_S = 5.0
"""Real seconds to wait for this node's subscription to reach move_base's plan or recovery publisher."""
RELAY = "/wsnav/move_base"
"""The bridge's relay of move_base's action interface (`wsnav ros bridge --relay`)."""
CONFIG_DIR = Path(wsnav.ros_bridge.__file__).resolve().parent / "catkin" / "wsnav_ros" / "config"
ZONE_LAYER = "wsn_zone_layer"
START_TIMEOUT_S = 60.0
"""Real seconds for a run's processes to come up (the robot's clock, move_base's action server, the bridge)."""
SIM_DONE = re.compile(r"sim done: .* distance=(?P<distance>[0-9.]+)m collisions=(?P<collisions>\d+)")
MISSING = math.nan
"""A column this backend does not measure: an empty cell in runs.csv, n/a in the report, never a 0."""
BACKEND_LINE = (
    "ROS 1: move_base (`{cmd}`) with navfn, DWA and costmap_2d; `wsnav sim --ros --clock` as the robot"
)


def move_base_argv(cmd: str) -> list[str]:
    """The move_base command as argv, its node named move_base unless the command names it, or one line saying
    it is not installed (`rosrun PKG` needs rospack to find PKG: Debian packages no move_base)."""
    argv = shlex.split(cmd)
    if not argv:
        raise CliError("--move-base-cmd is empty")
    missing = (
        "move_base is not installed here ({why}): build it from its noetic sources (docs/ros.md) "
        "or name its command with --move-base-cmd"
    )
    if shutil.which(argv[0]) is None:
        raise CliError(missing.format(why=f"no {argv[0]} on PATH"))
    if Path(argv[0]).name == "rosrun" and len(argv) > 1:
        rospack = shutil.which("rospack")
        found = (
            rospack is not None
            and subprocess.run([rospack, "find", argv[1]], capture_output=True, timeout=30).returncode == 0
        )
        if not found:
            raise CliError(missing.format(why=f"rospack finds no package {argv[1]}"))
    if not any(arg.startswith("__name:=") for arg in argv):
        argv.append(NODE_NAME)
    return argv


def _yaml(name: str) -> dict[str, Any]:
    loaded = yaml.safe_load((CONFIG_DIR / name).read_text())
    assert isinstance(loaded, dict)
    return loaded


def move_base_params(config: str) -> dict[str, Any]:
    """move_base's parameters for an agent configuration: ROBOTIS' Burger set (move_base, DWA) and the shipped
    costmap files, with the configuration's own rates and sizes (planner_frequency, the global costmap's
    update rate, the local costmap's size and update rate, the controller's rate, inflation); the zone layer only where the
    configuration has one."""
    agent = load_agent_config(config)
    common = _yaml("costmap_common_params_burger.yaml")
    params = _yaml("move_base_params_burger.yaml")
    glob = {**copy.deepcopy(common), **_yaml("global_costmap_params.yaml")["global_costmap"]}
    local = {**copy.deepcopy(common), **_yaml("local_costmap_params.yaml")["local_costmap"]}
    if not agent.zone_layer:
        glob["plugins"] = [p for p in glob["plugins"] if p["name"] != ZONE_LAYER]
        glob.pop(ZONE_LAYER, None)
    glob["update_frequency"] = agent.global_costmap_rate_hz
    local["width"] = local["height"] = agent.local_costmap_size_m
    local["update_frequency"] = agent.local_costmap_rate_hz
    for costmap in (glob, local):
        costmap["inflation_layer"] = {
            "inflation_radius": agent.inflation.inflation_radius,
            "cost_scaling_factor": agent.inflation.cost_scaling_factor,
        }
    params["planner_frequency"] = agent.replan_rate_hz
    params["controller_frequency"] = agent.controller_rate_hz
    params["DWAPlannerROS"]["controller_frequency"] = agent.controller_rate_hz
    return {**params, "global_costmap": glob, "local_costmap": local}


def plan_topic(params: dict[str, Any]) -> str:
    """The topic move_base's global planner publishes each plan on: `/move_base/<planner>/plan`
    (base_global_planner `navfn/NavfnROS` -> /move_base/NavfnROS/plan)."""
    return f"/move_base/{str(params['base_global_planner']).rsplit('/', 1)[-1]}/plan"


def planning_cycles(plans: list[tuple[float, str]]) -> int:
    """The global planner's makePlan calls among its plan messages (time heard, header stamp): navfn publishes a
    found plan twice with the same stamp (from getPlanFromPotential, then with the goal pose appended at the end
    of makePlan) and a failed one once, so a message stamped as the one just before it is that plan again."""
    cycles, last = 0, None
    for _, stamp in plans:
        cycles += stamp != last
        last = stamp
    return cycles


class Heard:
    """Messages of one topic as they come (rospy's thread), kept with their /clock time."""

    def __init__(self, ros: RosSide, topic: str, msg_type: Any, describe: Callable[[Any], str]) -> None:
        self.topic = topic
        self.times: list[tuple[float, str]] = []
        self._ros = ros
        self._describe = describe
        self.sub = ros.subscriber(topic, msg_type, self._on_message)

    def _on_message(self, msg: Any) -> None:
        self.times.append((self._ros.sim_t if self._ros.sim_t is not None else math.nan, self._describe(msg)))

    def connected(self, waiting: Callable[[], None]) -> bool:
        """Whether this node's subscription reached a publisher of the topic (waited for a while, `waiting`
        meanwhile, if the master names one): only then does a count of 0 mean none were sent."""
        if self.topic not in self._ros.published_topics():
            return False
        deadline = time.monotonic() + CONNECT_TIMEOUT_S
        while self.sub.get_num_connections() == 0:
            if time.monotonic() > deadline:
                return False
            waiting()
        return True

    def since(self, mark: int) -> list[tuple[float, str]]:
        return list(self.times[mark:])


class RosSide:
    """This process as a ROS node of the experiment's master: the map, the goal, the robot's clock and pose."""

    def __init__(self, site: Site, core: LocalRosCore) -> None:
        import actionlib
        import rospy
        from move_base_msgs.msg import MoveBaseAction
        from nav_msgs.msg import OccupancyGrid, Odometry
        from rosgraph_msgs.msg import Clock

        self._rospy = rospy
        env = core.env()
        os.environ.update({k: env[k] for k in ("ROS_MASTER_URI", "ROS_HOSTNAME", "ROS_LOG_DIR")})
        self.master = xmlrpc.client.ServerProxy(core.uri)
        self.set_param("/use_sim_time", True)
        rospy.init_node("wsnav_experiment", disable_signals=True)
        self.sim_t: float | None = None
        self.pose: tuple[float, float] | None = None
        rospy.Subscriber("/clock", Clock, self._on_clock, queue_size=10)
        rospy.Subscriber("/odom", Odometry, self._on_odom, queue_size=10)
        self._map_pub = rospy.Publisher("/map", OccupancyGrid, queue_size=1, latch=True)
        self._map_pub.publish(self._map(site, OccupancyGrid))
        self.clients = {
            name: actionlib.SimpleActionClient(name, MoveBaseAction) for name in ("/move_base", RELAY)
        }
        self._heard: dict[str, Heard] = {}

    def heard(self, topic: str, msg_type: Any, describe: Callable[[Any], str]) -> Heard:
        """The one subscription of this node to `topic`, kept for the whole experiment."""
        if topic not in self._heard:
            self._heard[topic] = Heard(self, topic, msg_type, describe)
        return self._heard[topic]

    def subscriber(self, topic: str, msg_type: Any, callback: Callable[[Any], None]) -> Any:
        return self._rospy.Subscriber(topic, msg_type, callback, queue_size=100)

    def published_topics(self) -> set[str]:
        return {name for name, _ in self._rospy.get_published_topics()}

    def forget_robot(self) -> None:
        """Before a run's robot starts: the last run's /clock and pose must not pass for this one's (its clock
        starts again at 1 s; a stale time made a run's time to goal seconds short)."""
        self.sim_t = None
        self.pose = None

    def set_param(self, key: str, value: bool | dict[str, Any]) -> None:
        self.master.deleteParam("/wsnav_experiment", key)  # no key of the last configuration stays
        self.master.setParam("/wsnav_experiment", key, value)

    def _on_clock(self, msg: Any) -> None:
        self.sim_t = msg.clock.to_sec()

    def _on_odom(self, msg: Any) -> None:
        p = msg.pose.pose.position
        self.pose = (float(p.x), float(p.y))

    @staticmethod
    def _map(site: Site, grid_type: Any) -> Any:
        """The site's map as map_server publishes it (same cells, row 0 at the origin's y)."""
        grid = site.grid
        msg = grid_type()
        msg.header.frame_id = "map"
        msg.info.resolution = grid.resolution
        msg.info.width, msg.info.height = grid.width, grid.height
        msg.info.origin.position.x, msg.info.origin.position.y = grid.origin[0], grid.origin[1]
        yaw = grid.origin[2]
        msg.info.origin.orientation.z, msg.info.origin.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        msg.data = grid.data.ravel().tolist()
        return msg

    def goal(self, action: str, xyyaw: tuple[float, float, float]) -> None:
        from move_base_msgs.msg import MoveBaseGoal

        goal = MoveBaseGoal()
        goal.target_pose.header.frame_id = "map"
        goal.target_pose.header.stamp = self._rospy.Time.now()
        x, y, yaw = xyyaw
        goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = x, y
        goal.target_pose.pose.orientation.z = math.sin(yaw / 2)
        goal.target_pose.pose.orientation.w = math.cos(yaw / 2)
        self.clients[action].send_goal(goal)

    def wait_server(self, action: str, alive: Callable[[], None]) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.clients[action].wait_for_server(self._rospy.Duration(0.5)):
            alive()
            if time.monotonic() > deadline:
                raise CliError(f"no action server at {action} after {START_TIMEOUT_S:g} s")

    def duration(self, seconds: float) -> Any:
        return self._rospy.Duration(seconds)

    def shutdown(self) -> None:
        self._rospy.signal_shutdown("the experiment is over")


@dataclass
class Child:
    """One process of a run, its output in a file (read for its lines)."""

    name: str
    proc: subprocess.Popen[bytes]
    log: Path

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def alive(self) -> None:
        if self.proc.poll() is not None:
            tail = "\n".join(self.text().splitlines()[-5:])
            raise CliError(f"{self.name} exited with {self.proc.returncode}:\n{tail}")

    def wait_for(self, text: str, step: Callable[[], None]) -> None:
        """Until a line matches the pattern `text`, stepping the zone simulator meanwhile."""
        deadline = time.monotonic() + START_TIMEOUT_S
        while re.search(text, self.text()) is None:
            self.alive()
            if time.monotonic() > deadline:
                raise CliError(f"{self.name} did not say {text!r} within {START_TIMEOUT_S:g} s")
            step()

    def stop(self) -> None:
        stop_process_group(self.proc)


def _start(name: str, argv: list[str], env: dict[str, str], folder: Path) -> Child:
    log = folder / f"{name}.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    return Child(name, proc, log)


def _wsnav(*args: str) -> list[str]:
    return [sys.executable, "-m", "wsnav.cli", *args]


class CpuMeter:
    """move_base's process CPU (user + system, its children's included: `rosrun` execs, a wrapper may not) and
    its resident-set peak, sampled while the run goes."""

    def __init__(self, pid: int) -> None:
        self.proc = psutil.Process(pid)
        self.peak_mb = 0.0
        self.start = self.cpu_s()

    def cpu_s(self) -> float:
        try:
            procs = [self.proc, *self.proc.children(recursive=True)]
            total = 0.0
            for p in procs:
                t = p.cpu_times()
                total += t.user + t.system
                self.peak_mb = max(self.peak_mb, p.memory_info().rss / 2**20)
            return total
        except psutil.Error:
            return self.start


def run_on_ros(
    site: Site,
    specs: list[RunSpec],
    move_base: list[str],
    progress: Callable[[int, int], None] | None = None,
) -> list[tuple[RunSpec, RunResult]]:
    """Every run in turn on one roscore of our own (ROS allows one master per graph: runs cannot overlap)."""
    require_rospy()
    done: list[tuple[RunSpec, RunResult]] = []
    with (
        _sigterm_unwinds(),
        tempfile.TemporaryDirectory(prefix="wsnav-ros-experiment-") as tmp,
        LocalRosCore(Path(tmp)) as core,
    ):
        ros = RosSide(site, core)
        try:
            for spec in specs:
                folder = Path(tmp) / f"run-{len(done)}"
                folder.mkdir()
                done.append((spec, ros_run(site, spec, ros, core, move_base, folder)))
                if progress is not None:
                    progress(len(done), len(specs))
        finally:
            ros.shutdown()
    return done


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """SIGTERM (`kill`, systemd, a CI timeout) ends the experiment through its `finally` blocks, which stop
    roscore, the simulator, the bridge and move_base: each runs in a session of its own, so nothing else would."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def unwind(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, unwind)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def _children() -> Iterator[list[Child]]:
    started: list[Child] = []
    try:
        yield started
    finally:
        for child in reversed(started):
            child.stop()


def ros_run(
    site: Site, spec: RunSpec, ros: RosSide, core: LocalRosCore, move_base: list[str], folder: Path
) -> RunResult:
    """One run: the robot, move_base (and the bridge), the zones blocked, the goal, until it ends or the cap."""
    agent = load_agent_config(spec.config)
    ros.set_param("/move_base", move_base_params(spec.config))
    ros.forget_robot()  # the last run's processes are gone: nothing of theirs arrives after this
    env = core.env()
    with BrokerThread(site) as broker, _children() as children:
        robot_creds = str(broker.credentials_dir / f"{ROBOT}.json")
        at = f"{broker.host}:{broker.port}"
        x, y, yaw = start_pose(site, spec)
        sim_args = ("sim", "--ros", "--clock", "--site", str(site.path), f"--start={x},{y},{yaw}")
        sim = _start("sim", _wsnav(*sim_args, "--broker", at, "--credentials", robot_creds), env, folder)
        children.append(sim)
        nav = _start("move_base", move_base, env, folder)  # every process starts at once: they import a while
        children.append(nav)
        bridge: Child | None = None
        if agent.zone_layer:
            bridge_args = ("--broker", at, "--credentials", robot_creds, "--robot", ROBOT, "--relay", RELAY)
            bridge = _start(
                "bridge",
                _wsnav("ros", "bridge", "--site", str(site.path), *bridge_args, "--map-wait", "0"),
                env,
                folder,
            )
            children.append(bridge)
        zones = ZoneSimulator(
            site,
            broker.credentials_dir,
            (broker.host, broker.port),
            WallClock(),
            seed=spec.seed,
            sensor=SENSORS,
        )

        def step() -> None:
            zones.step(io_timeout_s=0.02)

        zones.start()
        try:
            zones.wait_online(timeout_s=START_TIMEOUT_S)
            sim.wait_for("simulated TurtleBot3", step)
            deadline = time.monotonic() + START_TIMEOUT_S
            while ros.sim_t is None or ros.pose is None:
                sim.alive()
                if time.monotonic() > deadline:
                    raise CliError(f"no /clock and /odom from the simulated robot in {START_TIMEOUT_S:g} s")
                step()
            for zone in spec.blocked:
                zones.block(zone)
            if spec.blocked:
                sim.wait_for(r"world: [1-9]", step)
            action = "/move_base"
            ros.wait_server(action, nav.alive)
            if bridge is not None:
                bridge.wait_for(f"supervising /move_base for {ROBOT}", step)
                action = RELAY
                ros.wait_server(action, bridge.alive)
            return _drive(site, spec, ros, action, nav, sim, step)
        finally:
            zones.stop()
            sim.stop()


def _drive(
    site: Site, spec: RunSpec, ros: RosSide, action: str, nav: Child, sim: Child, step: Callable[[], None]
) -> RunResult:
    from actionlib_msgs.msg import GoalStatus
    from move_base_msgs.msg import RecoveryStatus
    from nav_msgs.msg import Path as PlanPath

    client = ros.clients[action]
    plans = ros.heard(plan_topic(move_base_params(spec.config)), PlanPath, lambda msg: str(msg.header.stamp))
    recoveries = ros.heard(RECOVERY_STATUS, RecoveryStatus, lambda msg: str(msg.recovery_behavior_name))

    def waiting() -> None:
        nav.alive()
        step()

    counted = {heard.topic: heard.connected(waiting) for heard in (plans, recoveries)}
    marks = (len(plans.times), len(recoveries.times))
    cpu = CpuMeter(nav.proc.pid)
    assert ros.sim_t is not None and ros.pose is not None
    t0 = ros.sim_t
    trajectory = [ros.pose]
    stalls = StallMeter(t0, ros.pose)
    next_sample = t0 + TRAJECTORY_EVERY_S
    ros.goal(action, site.point(spec.goal))
    ending = (
        GoalStatus.SUCCEEDED,
        GoalStatus.ABORTED,
        GoalStatus.REJECTED,
        GoalStatus.PREEMPTED,
        GoalStatus.LOST,
    )
    state = GoalStatus.PENDING
    while ros.sim_t - t0 < TIMEOUT_SIM_S:
        step()
        sim.alive()
        if nav.proc.poll() is not None:
            state = GoalStatus.LOST
            break
        now, pose = ros.sim_t, ros.pose
        stalls.update(now, pose)
        if now >= next_sample:
            trajectory.append(pose)
            next_sample += TRAJECTORY_EVERY_S
            cpu.cpu_s()  # samples move_base's resident set for its peak
        state = client.get_state()
        if state in ending:
            break
    else:
        client.cancel_goal()
    client.wait_for_result(ros.duration(2.0))  # done on both sides: no late transition from the next server
    elapsed = ros.sim_t - t0
    cpu_s = cpu.cpu_s() - cpu.start
    planned = plans.since(marks[0])
    recovered = recoveries.since(marks[1])
    stalls.close(ros.sim_t)
    trajectory.append(ros.pose)
    sim.stop()
    summary = SIM_DONE.search(sim.text())
    if summary is None:
        raise CliError(f"the simulated robot did not sum up its run:\n{sim.text()[-500:]}")
    outcome = {GoalStatus.SUCCEEDED: "arrived", GoalStatus.ABORTED: "aborted", GoalStatus.REJECTED: "aborted"}
    ended = outcome.get(state, "timeout" if elapsed >= TIMEOUT_SIM_S else "cancelled")
    row: dict[str, object] = {
        "config": spec.config,
        "route": spec.route,
        "blocked": spec.blocked_label,
        "run": spec.run,
        "seed": spec.seed,
        "success": ended == "arrived",
        "collisions": int(summary["collisions"]),
        "time_s": round(elapsed, 3),
        "distance_m": round(float(summary["distance"]), 3),
        # The first plan is the goal's, not a replan (as the sim backend counts them); not heard: missing.
        "replans": max(planning_cycles(planned) - 1, 0) if counted[plans.topic] else MISSING,
        "recoveries": len(recovered) if counted[recoveries.topic] else MISSING,
        "stalled_s": round(stalls.stalled_s, 3),
        "outcome": ended,
        "recovery_log": "; ".join(
            [f"{t - t0:.1f} {name}" for t, name in recovered]
            + ([] if nav.proc.poll() is None else ["move_base exited"])
        ),
        "planning_ms": MISSING,  # move_base does not say how long its planner took
        "agent_cpu_s": MISSING,  # no wsnav agent runs: move_base's CPU is process_cpu_s
        "process_cpu_s": round(cpu_s, 6),
        "peak_mem_mb": round(cpu.peak_mb, 1),
    }
    return RunResult(row, np.asarray(trajectory, dtype=np.float64))
