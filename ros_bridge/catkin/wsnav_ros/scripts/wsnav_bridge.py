#!/usr/bin/env python3
"""roslaunch's face of `wsnav ros bridge`: reads the node's ~parameters and runs the command with them.

Each parameter `key: value` becomes `--key-with-dashes value` (true: a flag; false: left out); `wsnav_command`
names the wsnav executable. roslaunch's own arguments (`__name:=`, `__log:=`) are kept out of wsnav's options.
"""

import os
import sys
import xmlrpc.client


def node_name() -> str:
    for arg in sys.argv[1:]:
        if arg.startswith("__name:="):
            name = arg.split(":=", 1)[1]
            namespace = os.environ.get("ROS_NAMESPACE", "/").rstrip("/")
            return f"{namespace}/{name}"
    sys.exit("wsnav_bridge: start me with roslaunch (no __name:= given)")


def options(params: dict[str, object]) -> list[str]:
    args: list[str] = []
    for key, value in sorted(params.items()):
        if key == "wsnav_command" or value is False:
            continue
        args.append("--" + key.replace("_", "-"))
        if value is not True:
            args.append(str(value))
    return args


def main() -> None:
    name = node_name()
    master = xmlrpc.client.ServerProxy(os.environ.get("ROS_MASTER_URI", "http://localhost:11311"))
    answer = master.getParam(name, name)
    code, message, params = (
        answer if isinstance(answer, list) and len(answer) == 3 else (0, "no answer", None)
    )
    if code != 1 or not isinstance(params, dict):
        sys.exit(f"wsnav_bridge: no parameters under {name} ({message}): load a YAML file into the node")
    command = str(params.get("wsnav_command", "wsnav"))
    argv = [command, "ros", "bridge", *options({str(k): v for k, v in params.items()})]
    try:
        os.execvp(command, argv)
    except OSError as exc:
        sys.exit(f"wsnav_bridge: cannot run {command}: {exc.strerror} (set the launch argument wsnav:=PATH)")


if __name__ == "__main__":
    main()
