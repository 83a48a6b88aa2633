"""The Jazzy start-up and shutdown idiom shared by every node's main().

Start-up: bad parameters or files make the node refuse to start with one clear line and exit
code 2; SIGINT/SIGTERM while the node is being created is a clean stop. Spinning: SIGINT/SIGTERM
(KeyboardInterrupt, ExternalShutdownException) end it cleanly; `close` runs before the node is
destroyed (the recorder finalises its MCAP file there).
"""
from __future__ import annotations

import faulthandler
import os
import signal
import sys
from typing import Callable, Optional, Tuple, Type

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from mapf_world.fleet_launch import STACK_DUMP_SIGNAL

STOP_POLL_S = 0.1  # how often a node with a file to finalise checks for a requested stop
REFUSALS: Tuple[Type[BaseException], ...] = (ValueError, OSError, ParameterException)


def dump_stacks_on_signal() -> None:
    """On STACK_DUMP_SIGNAL print every thread's Python stack to stderr (the node's log) and go on. It works
    while the main thread is stuck in C code, where a Python signal handler (SIGINT, SIGTERM) never runs:
    ProcessGroup.stop sends it to a node that did not stop, before SIGKILL."""
    faulthandler.register(STACK_DUMP_SIGNAL, all_threads=True)


def create_node(name: str, factory: Callable[[], Node]) -> Optional[Node]:
    """Create the node; None when a signal stopped the start-up. Refusals exit with code 2."""
    dump_stacks_on_signal()
    try:
        return factory()
    except REFUSALS as exc:
        print(f"[{name}] refusing to start: {exc}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        # os._exit, not SystemExit: a refusal has opened nothing to finalise (every node checks its parameters
        # and files before it opens a log or a device), and the interpreter's own exit, after a node whose
        # construction failed half-way, once hung for more than 90 s after printing the line above (tenth
        # session, one full scripts/test run; three reruns of tests/ros/test_node_refusals.py passed).
        sys.stdout.flush()
        os._exit(2)
    except KeyboardInterrupt:  # SIGINT while starting up (e.g. loading the model)
        rclpy.try_shutdown()
        return None
    except Exception:
        if rclpy.ok():
            raise
        return None  # SIGINT/SIGTERM shut the context down while the node was being created


def spin_until_shutdown(node: Node, close: Optional[Callable[[], None]] = None) -> None:
    """Spin until a signal, then close (optional), destroy the node and shut rclpy down.

    With `close` (a node that finalises a file there), SIGINT/SIGTERM only request the stop, and the node
    spins one callback at a time until then. A KeyboardInterrupt raised in the middle of a callback could
    cut a file write short: once, a recorder's MCAP file ended up with a valid summary but a truncated
    chunk (tests/ros/test_fleet_faults.py, eleventh session)."""
    stop: list = []
    if close is not None:
        def request_stop(signum, frame):  # no exception mid-callback: the loop below sees the flag
            stop.append(signum)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, request_stop)
    try:
        if close is None:
            rclpy.spin(node)
        else:
            while not stop and rclpy.ok():
                rclpy.spin_once(node, timeout_sec=STOP_POLL_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # else: a signal shut the context down while a callback ran (an rclpy race): a clean stop
    finally:
        if close is not None:
            close()
        node.destroy_node()
        rclpy.try_shutdown()


def run_node(name: str, factory: Callable[[], Node], args=None, close_method: str = "") -> None:
    """main() of a spinning node: init, create (or refuse), spin, shut down."""
    dump_stacks_on_signal()  # before init: a start-up that hangs in the middleware leaves its place too
    rclpy.init(args=args)
    node = create_node(name, factory)
    if node is not None:
        spin_until_shutdown(node, getattr(node, close_method) if close_method else None)
