"""Read a fleet MCAP log back: per-step timeline in the terminal, PNG and GIF of the run.

Usage: scripts/replay FILE.mcap [--out DIR] [--no-gif] [--recover]

The map comes from /map (OccupancyGrid), the cells of every step from /fleet/status (falling back
to the /robot_<i>/cell_move moves), the continuous motion from /robot_<i>/odom.
"""
from __future__ import annotations

import argparse
import re
import sys
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

ACTION_NAMES = ("stay", "up", "down", "left", "right")
OUTCOME_NAMES = ("ok", "blocked", "timeout", "rejected")
STATE_NAMES = ("waiting", "running", "success", "max_steps", "aborted")
ROBOT_TOPIC = re.compile(r"^/(?:.*/)?robot_(\d+)/(odom|cmd_vel|action|observation|cell_move)$")


@dataclass
class RunLog:
    path: Path
    grid: Optional[np.ndarray] = None
    cell_size: float = 1.0
    instance: str = ""
    goals: Optional[np.ndarray] = None
    statuses: List = field(default_factory=list)           # FleetStatus messages in log order
    moves: Dict[int, Dict[int, object]] = field(default_factory=lambda: defaultdict(dict))  # step -> robot -> CellMove
    actions: Dict[int, list] = field(default_factory=lambda: defaultdict(list))             # robot -> AgentActions
    observations: Dict[int, list] = field(default_factory=lambda: defaultdict(list))
    odom: Dict[int, list] = field(default_factory=lambda: defaultdict(list))  # robot -> (t, x, y, yaw, v, w)
    cmd_vel: Dict[int, list] = field(default_factory=lambda: defaultdict(list))  # robot -> (log_t, v, w)
    counts: Counter = field(default_factory=Counter)
    logs: List[str] = field(default_factory=list)             # /rosout warnings and errors
    notes: List[str] = field(default_factory=list)            # problems with the file itself

    @property
    def n_robots(self) -> int:
        if self.goals is not None:
            return len(self.goals)
        return max(self.odom.keys() | self.moves.get(0, {}).keys() | {-1}) + 1

    @property
    def final(self):
        return self.statuses[-1] if self.statuses else None

    def positions(self) -> np.ndarray:
        """(T+1, N, 2) cells of every completed step."""
        by_step = {}
        for s in self.statuses:
            if s.state != 0:  # not while waiting
                by_step[int(s.step)] = np.asarray(s.positions, dtype=np.int64).reshape(-1, 2)
        for step, per_robot in self.moves.items():
            if len(per_robot) == self.n_robots:
                order = [per_robot[i] for i in range(self.n_robots)]
                by_step.setdefault(step, np.array([m.from_cell for m in order], dtype=np.int64))
                by_step.setdefault(step + 1, np.array([m.to_cell for m in order], dtype=np.int64))
        if not by_step:
            raise ValueError(f"{self.path}: no /fleet/status or complete /robot_<i>/cell_move messages")
        last = max(by_step)
        missing = [k for k in range(last + 1) if k not in by_step]
        if missing:
            raise ValueError(f"{self.path}: no cells recorded for steps {missing[:10]}")
        return np.stack([by_step[k] for k in range(last + 1)])


def _decoded(path: Path, notes: List[str]) -> list:
    """[(schema, channel, message, decoded)] in log time order. A file that was not finalised (the
    recorder was killed, the file was cut) or is damaged is read up to its last complete chunk, with
    a warning in notes; ValueError naming the file when nothing can be read."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from mapf_world.mcap_recover import check_magic, scan

    check_magic(path)
    factory = DecoderFactory()
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[factory])
            if reader.get_summary() is not None:
                return list(reader.iter_decoded_messages(log_time_order=True))
        why = "it has no summary"
    except Exception as exc:  # the mcap reader raises many types for cut or damaged files
        why = f"reading it whole failed ({type(exc).__name__}: {exc})"
    found = scan(path)
    notes.append(f"warning: {path} was not finalised or is damaged: {why}; "
                 f"{found.problem or 'every record before the end is intact'}. Replaying the "
                 f"{len(found.messages)} messages up to its last complete chunk "
                 f"(scripts/replay --recover writes them to a finalised copy)")
    out = []
    for m in sorted(found.messages, key=lambda m: m.log_time):
        channel = found.channels[m.channel_id]
        schema = found.schemas.get(channel.schema_id)
        if schema is None:
            raise ValueError(f"{path}: channel {channel.topic} names schema {channel.schema_id}, which is not in the file")
        try:
            decoded = factory.decoder_for(channel.message_encoding, schema)(m.data)
        except Exception as exc:
            raise ValueError(f"{path}: a message on {channel.topic} does not decode "
                             f"({type(exc).__name__}: {exc})") from exc
        out.append((schema, channel, m, decoded))
    return out


def load_run(path) -> RunLog:
    path = Path(path)
    run = RunLog(path)
    for schema, channel, message, msg in _decoded(path, run.notes):
        topic = channel.topic
        run.counts[topic] += 1
        m = ROBOT_TOPIC.match(topic)
        try:
            if topic.endswith("/map") and schema.name == "nav_msgs/msg/OccupancyGrid":
                h, w = msg.info.height, msg.info.width
                run.grid = (np.flipud(np.asarray(msg.data, dtype=np.int16).reshape(h, w)) >= 50).astype(np.uint8)
                run.cell_size = float(msg.info.resolution)
            elif topic.endswith("fleet/status"):
                run.statuses.append(msg)
                run.instance = msg.instance
                run.cell_size = float(msg.cell_size)  # float64 here; the map's resolution is float32
                run.goals = np.asarray(msg.goals, dtype=np.int64).reshape(-1, 2)
            elif topic == "/rosout" and msg.level >= 30:
                run.logs.append(f"[{msg.name}] {msg.msg}")
            elif m:
                i, kind = int(m.group(1)), m.group(2)
                if kind == "odom":
                    p, t = msg.pose.pose, msg.twist.twist
                    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
                    yaw = 2.0 * np.arctan2(p.orientation.z, p.orientation.w)
                    run.odom[i].append((stamp, p.position.x, p.position.y, yaw, t.linear.x, t.angular.z))
                elif kind == "cmd_vel":
                    run.cmd_vel[i].append((message.log_time * 1e-9, msg.linear.x, msg.angular.z))
                elif kind == "cell_move":
                    run.moves[int(msg.step)][i] = msg
                elif kind == "action":
                    run.actions[i].append(msg)
                else:
                    run.observations[i].append(msg)
        except (AttributeError, ValueError, TypeError) as exc:  # a topic of the fleet's name with another type
            raise ValueError(f"{path}: {topic} [{schema.name}] is not what a fleet log holds there "
                             f"({type(exc).__name__}: {exc})") from exc
    if run.grid is None:
        raise ValueError(f"{path}: no /map message (was the world node running while recording?)")
    return run


def timeline(run: RunLog) -> List[str]:
    lines = []
    n = run.n_robots
    pos = run.positions()
    header = f"{run.path.name}: {run.instance or 'unknown instance'}, {run.grid.shape[0]}x{run.grid.shape[1]} map, {n} robots, cell {run.cell_size} m"
    lines.append(header)
    walls = {int(s.step): s.step_wall_s for s in run.statuses if s.step_wall_s > 0}
    for step in range(len(pos) - 1):
        parts = []
        for i in range(n):
            mv = run.moves.get(step, {}).get(i)
            if mv is None:
                a = "?"
            else:
                a = ACTION_NAMES[mv.action]
                if mv.outcome:
                    a += f"({OUTCOME_NAMES[mv.outcome]}" + (f" {ACTION_NAMES[mv.requested_action]}" if mv.outcome == 1 else "") + ")"
            parts.append(f"r{i} {tuple(pos[step, i].tolist())}->{tuple(pos[step + 1, i].tolist())} {a}")
        wall = f" {walls[step + 1]:.3f}s" if step + 1 in walls else ""
        lines.append(f"step {step:3d}{wall}: " + " | ".join(parts))
    final = run.final
    if final is not None:
        lines.append(f"end: {STATE_NAMES[final.state] if final.state < len(STATE_NAMES) else final.state} - {final.detail}; "
                     f"steps {final.step}, failed moves {final.failed_moves}, timeouts {final.timeouts}, "
                     f"rejected {final.rejected}")
    for note in run.notes:
        lines.append(f"note: {note}")
    lines.append("messages: " + ", ".join(f"{t} {c}" for t, c in sorted(run.counts.items())))
    for text in run.logs[:20]:
        lines.append(f"log: {text}")
    return lines


def render(run: RunLog, out_dir: Path, gif: bool = True) -> List[Path]:
    from mapf_world.render import render_gif, render_png

    pos = run.positions()
    goals = run.goals if run.goals is not None else pos[-1]
    tracks = {i: [(x, y) for _, x, y, *_ in od] for i, od in run.odom.items()}
    stem = run.path.stem
    title = f"{run.instance} ({len(pos) - 1} steps)"
    outs = [render_png(out_dir / f"{stem}.png", run.grid, pos, goals, tracks, run.cell_size, title)]
    if gif:
        outs.append(render_gif(out_dir / f"{stem}.gif", run.grid, pos, goals, title=run.instance))
    return outs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/replay", description=__doc__.splitlines()[0])
    ap.add_argument("mcap", type=Path, help="fleet MCAP log (from scripts/demo or the recorder node)")
    ap.add_argument("--out", type=Path, default=None, help="where to write PNG/GIF (default: next to the log)")
    ap.add_argument("--no-gif", action="store_true", help="only the PNG")
    ap.add_argument("--recover", action="store_true",
                    help="write the readable part of a log that was not finalised (recorder killed) or is "
                         "damaged to <out>/<name>.recovered.mcap, a finalised copy, and replay that")
    args = ap.parse_args(argv)
    try:
        path = args.mcap
        if args.recover:
            from mapf_world.mcap_recover import recover
            copy = (args.out or args.mcap.parent) / f"{args.mcap.stem}.recovered.mcap"
            found = recover(args.mcap, copy)
            state = "finalised, nothing to recover" if found.finalised else (found.problem or "no summary")
            print(f"recovered {len(found.messages)} messages on {len(found.channels)} topics from {args.mcap} "
                  f"({state}) into {copy}", file=sys.stderr)
            for note in found.notes:
                print(f"replay: warning: {note}", file=sys.stderr)
            path = copy
        run = load_run(path)
        for note in run.notes:
            print(f"replay: {note}", file=sys.stderr)
        for line in timeline(run):
            print(line)
        for p in render(run, args.out or args.mcap.parent, gif=not args.no_gif):
            print(f"wrote {p}")
    except (ValueError, OSError) as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
