"""Robot container: several robots' nodes in one process, in the manner of a ROS 2 component container.

    robot_container --robots 0-31 --nodes policy drive --policy-param model_path:=models/hscl.npz \
        --drive-param real_time_factor:=10.0

Each robot gets its own PolicyNode and/or DriveExecutor, created in its own namespace /robot_<i> with its own
parameters, exactly the nodes `policy_node` and `drive_executor` run alone: own subscriptions, publishers,
model copy, sampling generator and previous cell. Nothing is shared between robots but the process and its
executor (which only dispatches callbacks); no node names another robot's topic. Why: on a small machine,
64 robots as 128 Python processes would spend their memory on 128 interpreters and their CPU on 128 DDS
participants; a few containers keep each robot's state apart at a fraction of that (docs/FLEET.md).

The executor is rclpy's EventsExecutor (rclpy.experimental): it waits on events in C++ instead of
rebuilding a wait set of every node's entities at each callback, which costs milliseconds per callback
with hundreds of entities (measured: docs/FLEET.md, "64 robots"). Parameters are written as `-p` values
(YAML); a bad one, or a robot whose node refuses its parameters, stops the container with exit status 2
and the refusal's message. SIGINT/SIGTERM: clean stop, exit 0.
"""
from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as in policy_node.py: one BLAS thread per process

import rclpy  # noqa: E402
import yaml  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from mapf_world.node_main import REFUSALS, dump_stacks_on_signal  # noqa: E402

NODE_KINDS = ("policy", "drive")


def parse_robots(text: str) -> list[int]:
    """'0-3,7' -> [0, 1, 2, 3, 7]; ValueError on anything else (negative ids, empty, repeats)."""
    ids = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise ValueError(f"--robots takes ids and ranges like 0-31,40, got {text!r}")
        ids += list(range(int(lo), int(hi) + 1)) if sep else [int(lo)]
    if not ids or len(set(ids)) != len(ids):
        raise ValueError(f"--robots must name each robot once, got {text!r}")
    return ids


def parse_params(items: list[str], flag: str) -> list[Parameter]:
    """['name:=value', ...] -> rclpy Parameters, values read as YAML (as `-p name:=value` is)."""
    params = []
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise ValueError(f"{flag} takes name:=value, got {item!r}")
        params.append(Parameter(name, value=yaml.safe_load(value)))
    return params


def make_nodes(robots: list[int], kinds: list[str], policy_params: list[Parameter],
               drive_params: list[Parameter]) -> list:
    """The nodes, robot by robot; a node that refuses its parameters raises (ValueError and co.)."""
    from mapf_policy.drive_executor import DriveExecutor
    from mapf_policy.policy_node import PolicyNode
    nodes = []
    for i in robots:
        ns = f"/robot_{i}"
        if "drive" in kinds:
            nodes.append(DriveExecutor(namespace=ns, parameter_overrides=list(drive_params)))
        if "policy" in kinds:
            nodes.append(PolicyNode(namespace=ns, parameter_overrides=list(policy_params)))
    return nodes


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    own = argv[:len(argv) - len(ros_args)]
    ap = argparse.ArgumentParser(prog="robot_container", description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", required=True, help="robot ids, e.g. 0-31 or 0,2,5")
    ap.add_argument("--nodes", nargs="+", choices=NODE_KINDS, default=list(NODE_KINDS),
                    help="which nodes each robot gets here (default: both)")
    ap.add_argument("--policy-param", action="append", default=[], metavar="NAME:=VALUE")
    ap.add_argument("--drive-param", action="append", default=[], metavar="NAME:=VALUE")
    args = ap.parse_args(own)
    # A container that does not stop on SIGINT/SIGTERM prints its threads' stacks on ProcessGroup.stop's
    # SIGUSR1 (as single nodes do, node_main.create_node) instead of dying by it (a 32-drive container did not
    # stop once in a fresh-clone test run, exit -10; where it hung is unknown).
    dump_stacks_on_signal()
    rclpy.init(args=["robot_container"] + ros_args)
    nodes = []
    try:
        robots = parse_robots(args.robots)
        nodes = make_nodes(robots, args.nodes, parse_params(args.policy_param, "--policy-param"),
                           parse_params(args.drive_param, "--drive-param"))
    except REFUSALS as exc:
        print(f"[robot_container] refusing to start: {exc}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        sys.stdout.flush()
        os._exit(2)  # as node_main.create_node: nothing opened to finalise
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return 0
    from rclpy.experimental import EventsExecutor
    executor = EventsExecutor()
    for node in nodes:
        executor.add_node(node)
    print(f"[robot_container] robots {robots}: {len(nodes)} nodes ({', '.join(args.nodes)}) spinning", flush=True)
    try:
        # spin_once in a loop, not spin(): with EventsExecutor.spin() of this rclpy (Jazzy, PyPI wheels) the
        # timers ran but no subscription callback ever did (a policy container never answered; seen here).
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # Nodes leave the executor before it shuts down and before they are destroyed: without remove_node, a
        # policy container's destroy_node blocked now and then in destroy_when_not_in_use (the EventsExecutor
        # still held the node; 1 stop in 6 of the 64-robot test, SIGKILLed; stack in its log).
        for node in nodes:
            executor.remove_node(node)
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
