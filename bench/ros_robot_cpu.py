"""CPU of wsnav's navigator on ROS: `wsnav robot --ros` driving `wsnav sim --ros`, against `wsnav robot --sim` (the
same agent and simulator in one process, no ROS) as the baseline measured in the same run.

    ./.venv/bin/python -m bench.ros_robot_cpu [--seconds 20] [--no-write]

Each setup drives the school's route A -> B in real time (a real roscore on a free port, the broker in this
process); once the robot reports `navigating`, each wsnav process's CPU time (user + system, /proc) is read over
`--seconds` of driving. Needs Debian's ROS 1 packages (see .ci/run). Writes its section of BENCHMARKS.md.
`--quick`: 3 s per setup; the two ROS processes' CPU over the baseline's at most 5 (measured 1.56).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, quick_skipped
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.ros_env import LocalRosCore

REPO = Path(__file__).resolve().parent.parent
SCHOOL = REPO / "sites" / "school"
SECTION = "## ROS robot: CPU of `wsnav robot --ros` + `wsnav sim --ros`"
COMMAND = "./.venv/bin/python -m bench.ros_robot_cpu"
WSNAV = [sys.executable, "-m", "wsnav.cli"]
TICK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


@dataclass
class Measured:
    cpu: dict[str, float]
    """Process label -> CPU seconds per wall second while driving."""


def wait_line(proc: subprocess.Popen[str], text: str, timeout_s: float) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if text in line:
            return
        if not line and proc.poll() is not None:
            break
    raise RuntimeError(f"no {text!r} from {proc.args}")


def measure(procs: dict[str, subprocess.Popen[str]], seconds: float) -> Measured:
    before = {k: cpu_s(p.pid) for k, p in procs.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - t0
    return Measured({k: (cpu_s(p.pid) - before[k]) / wall for k, p in procs.items()})


def stop(*procs: subprocess.Popen[str]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_sim_baseline(broker: BrokerThread, seconds: float) -> Measured:
    mqtt = [
        "--broker",
        f"{broker.host}:{broker.port}",
        "--credentials",
        str(broker.credentials_dir / "robot1.json"),
    ]
    robot = subprocess.Popen(
        [*WSNAV, "robot", "--site", str(SCHOOL), *mqtt, "--sim", "--start", "A", "--goal", "B"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        wait_line(robot, " navigating ", 60)
        return measure({"wsnav robot --sim": robot}, seconds)
    finally:
        stop(robot)


def run_ros(broker: BrokerThread, seconds: float, log_dir: Path) -> Measured:
    procs: list[subprocess.Popen[str]] = []
    with LocalRosCore(log_dir) as core:
        env = core.env()
        try:
            mqtt = [
                "--broker",
                f"{broker.host}:{broker.port}",
                "--credentials",
                str(broker.credentials_dir / "robot1.json"),
            ]
            sim = subprocess.Popen(
                [*WSNAV, "sim", "--ros", "--site", str(SCHOOL), "--start", "A", *mqtt],
                env=env,
                stdout=subprocess.PIPE,
                text=True,
            )
            procs.append(sim)
            wait_line(sim, "simulated TurtleBot3", 60)
            robot = subprocess.Popen(
                [*WSNAV, "robot", "--ros", "--site", str(SCHOOL), *mqtt, "--goal", "B"],
                env=env,
                stdout=subprocess.PIPE,
                text=True,
            )
            procs.append(robot)
            wait_line(robot, " navigating ", 60)
            return measure({"wsnav robot --ros": robot, "wsnav sim --ros": sim}, seconds)
        finally:
            stop(*procs)


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parse_quick_args(parser)
    if args.quick:
        args.seconds = min(args.seconds, 3.0)
    if shutil.which("roscore") is None:
        if args.quick:
            quick_skipped("ROS 1 is not installed (see .ci/run for the Debian packages)")
        print("bench.ros_robot_cpu skipped: ROS 1 is not installed (see .ci/run for the Debian packages)")
        return
    with BrokerThread(SCHOOL) as broker, tempfile.TemporaryDirectory() as tmp:
        base = run_sim_baseline(broker, args.seconds)
        ros = run_ros(broker, args.seconds, Path(tmp))
    baseline = base.cpu["wsnav robot --sim"]
    total = sum(ros.cpu.values())
    rows = [
        f"| `wsnav robot --sim` (agent + simulator, one process: the baseline) | {baseline:.3f} | 1.00x |"
    ]
    rows += [f"| `{k[6:]}` | {v:.3f} | {v / baseline:.2f}x |" for k, v in ros.cpu.items()]
    rows.append(f"| `robot --ros` + `sim --ros` | {total:.3f} | {total / baseline:.2f}x |")
    if args.quick:
        print("\n".join(rows))
        check_ratio("CPU of `robot --ros` + `sim --ros` / `robot --sim`", total / baseline, 5.0)
        finish_quick()
    text = "\n".join(
        [
            "```",
            COMMAND,
            "```",
            "",
            f"The school's route A -> B in real time, {args.seconds:g} s of driving measured per setup once the robot "
            "reports `navigating` (the agent's `full` config; the simulator's odometry and tf at 30 Hz, lidar 5 Hz). "
            f"CPU seconds per wall second, user + system, from /proc. {machine_note()} (a shared machine: "
            "the ratios, taken in the same run, matter more than the absolute figures).",
            "",
            "| process | CPU s / s | vs baseline |",
            "| --- | --- | --- |",
            *rows,
            "",
            "What ROS adds: serialising scans (360 floats at 5 Hz), odometry and tf (30 Hz) in Python, and the agent's "
            "tf lookups; the agent's own work (costmap, planner, controller) is the same in both.",
        ]
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
