"""The navigation process's CPU and memory in real time, per configuration, as the paper measured move_base's:
`wsnav robot --sim --config X` driving the school's A -> B in real time with z4 blocked by emulated nodes.

    ./.venv/bin/python -m bench.nav_process_cpu [--seconds 30] [--rounds 2] [--no-write]

The configurations take turns (default, zones, full, then again), so a change in the machine's load falls on
each alike; `default` is the baseline of every ratio, measured in the same run. Once the robot reports
`navigating`, the process's CPU time (user + system, every thread, /proc) is read over `--seconds` of driving;
its peak resident memory (VmHWM) at the end. The process holds the agent and the simulated robot and lidar (as
`wsnav robot --sim` does): an upper bound of the navigation's own share. The broker (amqtt, in this process)
and the zone nodes (`wsnav zones`, a process of their own) are not counted. Writes its section of BENCHMARKS.md.
`--quick`: `default` then `full`, 4 s each; `full`'s CPU over `default`'s at most 3 (measured 0.78-1.2), and
`default`'s CPU s/s over a fixed reference workload timed in the same run (`bench.quick.reference_work_s`, in s) at
most 30 (measured 8.5 at load 5).
"""

from __future__ import annotations

import statistics
import subprocess
import time
from pathlib import Path

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, reference_work_s
from bench.ros_robot_cpu import WSNAV, cpu_s, stop, wait_line
from wsnav.broker.amqtt.embedded import BrokerThread

REPO = Path(__file__).resolve().parent.parent
SCHOOL = REPO / "sites" / "school"
SECTION = "## Navigation process CPU and memory in real time, per configuration (bench/nav_process_cpu.py)"
COMMAND = "./.venv/bin/python -m bench.nav_process_cpu"
CONFIGS = ("default", "zones", "full")
BLOCKED = "z4"


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def one(broker: BrokerThread, config: str, seconds: float) -> tuple[float, float]:
    """(CPU s per wall s, peak MB) of one robot process driving A -> B under `config`."""
    robot = subprocess.Popen(
        [
            *WSNAV,
            "robot",
            "--site",
            str(SCHOOL),
            "--broker",
            f"{broker.host}:{broker.port}",
            "--credentials",
            str(broker.credentials_dir / "robot1.json"),
            "--sim",
            "--start",
            "A",
            "--goal",
            "B",
            "--config",
            config,
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        wait_line(robot, " navigating ", 120)
        before, t0 = cpu_s(robot.pid), time.monotonic()
        time.sleep(seconds)
        cpu = (cpu_s(robot.pid) - before) / (time.monotonic() - t0)
        return cpu, peak_rss_mb(robot.pid)
    finally:
        stop(robot)


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rounds", type=int, default=2)
    args = parse_quick_args(parser)
    configs = ("default", "full") if args.quick else CONFIGS
    if args.quick:
        args.seconds, args.rounds = min(args.seconds, 4.0), 1
    load = machine_note()
    got: dict[str, list[tuple[float, float]]] = {c: [] for c in configs}
    with BrokerThread(SCHOOL) as broker:
        nodes = subprocess.Popen(
            [
                *WSNAV,
                "zones",
                "--site",
                str(SCHOOL),
                "--broker",
                f"{broker.host}:{broker.port}",
                "--credentials",
                str(broker.credentials_dir),
                "--block",
                BLOCKED,
                "--seed",
                "1",
                "--quiet",
            ],
            stdout=subprocess.DEVNULL,
            text=True,
        )
        try:
            time.sleep(5)  # the nodes online and z4 reported before the first robot plans
            for _ in range(args.rounds):
                for config in configs:
                    got[config].append(one(broker, config, args.seconds))
                    print(config, got[config][-1], flush=True)
        finally:
            stop(nodes)
    base = statistics.mean(c for c, _ in got["default"])
    if args.quick:
        check_ratio(
            "`full` process CPU / `default` process CPU",
            statistics.mean(c for c, _ in got["full"]) / base,
            3.0,
        )
        ref = reference_work_s(clock=time.thread_time)  # the figure is CPU time
        print(f"reference workload: {ref * 1000:.1f} ms of CPU")
        check_ratio("`default` process CPU s/s / reference workload s", base / ref, 30.0)
        finish_quick()
    rows = []
    for config in CONFIGS:
        cpus = [c for c, _ in got[config]]
        mean = statistics.mean(cpus)
        rows.append(
            f"| `{config}` | {mean:.3f} ({', '.join(f'{c:.3f}' for c in cpus)}) | {mean / base:.2f}x | "
            f"{max(m for _, m in got[config]):.0f} |"
        )
    text = "\n".join(
        [
            "```",
            COMMAND
            + (f" --seconds {args.seconds:g}" if args.seconds != 30.0 else "")
            + (f" --rounds {args.rounds}" if args.rounds != 2 else ""),
            "```",
            "",
            f"`wsnav robot --sim --config X` driving the school's A -> B in real time, {BLOCKED} blocked by the "
            f"emulated nodes (`wsnav zones`); {args.seconds:g} s of driving measured per run once the robot "
            f"reports `navigating`, {args.rounds} runs per configuration taking turns. {load} at the start "
            "(a shared machine: the ratios, taken in the same run, matter more than the absolute figures).",
            "",
            "| config | process CPU s / wall s, mean (each run) | vs default | peak resident memory (MB) |",
            "| --- | --- | --- | --- |",
            *rows,
            "",
            "What it is: the CPU of the process that navigates, in real time, as the paper measured move_base's; "
            "the process also simulates the robot and its lidar, which every configuration does alike. The "
            "experiment's agent-step CPU per simulated second (docs/experiment/report.md) is the agent's own "
            "step only.",
        ]
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
