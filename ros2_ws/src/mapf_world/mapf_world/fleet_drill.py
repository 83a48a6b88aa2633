"""The demo's fault drill (scripts/demo --kill-policies 0,1,2,3): SIGKILL some robots' policy nodes mid-run and
start them again a few steps later, while the world goes on.

The drilled robots' policy nodes run as processes of their own (a container would take its other robots
down with them). The drill follows the world's progress in its log ("step N done"). Expected, and what the
MCAP log records: the killed robots stay (outcome TIMEOUT, the world's warning in /rosout) from the step after
the kill until their restarted nodes answer again; every other robot keeps answering.
"""
from __future__ import annotations

import re
import signal
import time

STEP_DONE = re.compile(r"\] \[world\]: step (\d+) done")


def parse_ids(text: str) -> list[int]:
    """'0,1,2,3' -> [0, 1, 2, 3] ('' -> []); ValueError on anything else."""
    if not text:
        return []
    try:
        ids = [int(part) for part in text.split(",")]
    except ValueError:
        raise ValueError(f"--kill-policies takes robot ids like 0,1,2,3, got {text!r}") from None
    if any(i < 0 for i in ids) or len(set(ids)) != len(ids):
        raise ValueError(f"--kill-policies must name distinct robot ids >= 0, got {text!r}")
    return ids


def last_step_done(world_log: str) -> int:
    """The last step the world reported done (-1 before the first)."""
    steps = STEP_DONE.findall(world_log)
    return int(steps[-1]) if steps else -1


class Drill:
    """`poll()` while the world runs: kills at `kill_after` steps done, restarts `restart_after` steps later."""

    def __init__(self, group, robots: list[int], commands: dict, kill_after: int, restart_after: int):
        self.group, self.robots, self.commands = group, robots, commands
        self.kill_after, self.restart_after = kill_after, restart_after
        self.killed_at = self.restarted_at = None
        self.events: list[str] = []

    def poll(self) -> None:
        if not self.robots or self.restarted_at is not None:
            return
        done = last_step_done(self.group.log_text("world"))
        if self.killed_at is None and done >= self.kill_after:
            for i in self.robots:
                self.group.send(f"policy_{i}", signal.SIGKILL)
            self.killed_at = done
            self.events.append(f"SIGKILL to the policy nodes of robots {self.robots} after step {done} "
                               f"({time.strftime('%H:%M:%S')})")
        elif self.killed_at is not None and done >= self.killed_at + self.restart_after:
            for i in self.robots:
                self.group.procs[f"policy_{i}"].wait(timeout=5)
                self.group.start(f"policy_{i}", self.commands[i])
            self.restarted_at = done
            self.events.append(f"restarted the policy nodes of robots {self.robots} after step {done} "
                               f"({time.strftime('%H:%M:%S')})")
