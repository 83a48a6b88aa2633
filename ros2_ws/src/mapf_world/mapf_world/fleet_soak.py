"""Soak benchmark of the fleet behind scripts/bench_soak: many grid steps, episodes back to back.

One recorder, and per robot a policy node and a drive executor, run for the whole soak; each episode is
a new world node on a new seeded random map (its latched initial poses put the robots on their new start
cells). Reports, per process, memory (RSS) and CPU after the warm-up and at the end, the messages the
publishers numbered against those the recorder received (its sequence-number account) and wrote,
failed moves, timeouts and crashes (a node that exits by itself, an aborted episode). The RSS of every
long-running process is also sampled every --rss-period-s into <out>/rss_kb.tsv (RssSeries), to tell
growth per episode, per message or per minute apart.

Usage: scripts/bench_soak [--robots 8] [--steps 10000] [--out DIR] [...]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from mapf_world.fleet_launch import ProcessGroup, claim_domain_id, fleet_env, node_command


@dataclass
class SoakConfig:
    robots: int = 8
    steps: int = 10_000          # grid steps in all, over the episodes
    warmup_steps: int = 200      # start figures are taken once this many steps have run
    size: int = 16
    density: float = 0.2
    episode_steps: int = 96      # step limit of one episode
    seed: int = 0
    model: str = ""              # default: models/hscl.npz when present, else models/hscl.pt
    real_time_factor: float = 10.0
    rate_hz: float = 10.0
    episode_timeout_s: float = 600.0
    rss_period_s: float = 60.0   # period of the RSS series (<out>/rss_kb.tsv)
    out: str = ""


def usage_row(group: ProcessGroup, name: str):
    u = group.usage(name)
    return None if u is None else {"cpu_s": u.cpu_s, "rss_mb": u.rss_mb, "peak_rss_mb": u.peak_rss_mb, "t": time.monotonic()}


class RssSeries:
    """The RSS series of a soak: a tab-separated file with a header line (t_s, steps, episodes, then one
    column per process), then one line per sample: wall seconds since the start, grid steps and episodes
    done so far, and each process's RSS in KiB ('-' for one that is not running). sample() writes a line
    when period_s has passed since the last one (the first call always does); force=True writes one now."""

    def __init__(self, path: Path, names, period_s: float, clock=time.monotonic):
        if not period_s > 0:
            raise ValueError(f"RSS sample period must be > 0 s, got {period_s!r}")
        self.path, self.names, self.period_s, self.clock = Path(path), list(names), float(period_s), clock
        self.t0 = clock()
        self.last = None
        self.path.write_text("\t".join(["t_s", "steps", "episodes"] + self.names) + "\n")

    def sample(self, rss_mb, steps: int, episodes: int, force: bool = False) -> bool:
        """rss_mb(name) -> MiB or None. True when a line was written."""
        now = self.clock()
        if not force and self.last is not None and now - self.last < self.period_s:
            return False
        self.last = now
        kib = ["-" if v is None else str(round(v * 1024)) for v in map(rss_mb, self.names)]
        cells = [f"{now - self.t0:.0f}", str(steps), str(episodes)] + kib
        with self.path.open("a") as f:
            f.write("\t".join(cells) + "\n")
        return True


def run(cfg: SoakConfig, progress=None) -> dict:
    """The soak; progress(partial report) after every episode. SIGINT/SIGTERM end it early, with a report."""
    root = Path(os.environ.get("MAPF_ROOT", Path.cwd()))
    model = Path(cfg.model) if cfg.model else (root / "models" / "hscl.npz" if (root / "models" / "hscl.npz").is_file()
                                               else root / "models" / "hscl.pt")
    from mapf_world.fleet_demo import policy_model_params
    # The robots run the export; the world builds the observation the model reads (last action, extra channels).
    policy_params, observation_params = policy_model_params(model)
    out = Path(cfg.out or f"runs/soak/{time.strftime('%Y%m%d-%H%M%S')}")
    (out / "episodes").mkdir(parents=True, exist_ok=True)
    domain, lock = claim_domain_id(from_top=True)
    env = fleet_env(domain)
    group = ProcessGroup(out / "logs", env)
    mcap = out / "soak.mcap"
    robots = [f"policy_{i}" for i in range(cfg.robots)] + [f"drive_{i}" for i in range(cfg.robots)]
    group.start("recorder", node_command("mapf_world", "recorder", params=dict(output=str(mcap))))
    for i in range(cfg.robots):
        ns = f"/robot_{i}"
        group.start(f"drive_{i}", node_command("mapf_policy", "drive_executor", namespace=ns,
                                               params=dict(real_time_factor=cfg.real_time_factor, rate_hz=cfg.rate_hz)))
        group.start(f"policy_{i}", node_command("mapf_policy", "policy_node", namespace=ns,
                                                params=policy_params))
    steady = ["recorder"] + robots
    t0 = time.monotonic()
    totals = dict(steps=0, episodes=0, successes=0, failed_moves=0, timeouts=0, rejected=0, aborted=0)
    rss = RssSeries(out / "rss_kb.tsv", steady, cfg.rss_period_s)

    def rss_mb(name):
        u = group.usage(name)
        return None if u is None else u.rss_mb

    start_usage, world_usage, crashes, episodes = None, {}, [], []
    stopped = []

    def stop_early(signum, _frame):
        stopped.append(signal.Signals(signum).name)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop_early)
    try:
        e = 0
        while totals["steps"] < cfg.steps:
            dead = [n for n in steady if group.procs[n].poll() is not None]
            if dead:
                crashes += [f"{n} exited with {group.procs[n].returncode}" for n in dead]
                break
            name, summary_path = f"world_{e:04d}", out / "episodes" / f"{e:04d}.json"
            max_steps = min(cfg.episode_steps, cfg.steps - totals["steps"])
            group.start(name, node_command("mapf_world", "world_node", params=dict(
                instance_source="random", seed=cfg.seed + e, size=cfg.size, density=cfg.density,
                n_robots=cfg.robots, max_steps=max_steps, summary_path=str(summary_path), linger_s=0.0,
                wait_for_recorder="recorder") | observation_params))
            end = time.monotonic() + cfg.episode_timeout_s
            proc = group.procs[name]
            while proc.poll() is None and time.monotonic() < end:
                world_usage = usage_row(group, name) or world_usage
                rss.sample(rss_mb, totals["steps"], totals["episodes"])
                time.sleep(0.5)
            if proc.poll() is None:
                group.stop(name)
                crashes.append(f"{name} did not end within {cfg.episode_timeout_s} s")
                break
            if not summary_path.is_file():
                crashes.append(f"{name} exited with {proc.returncode} without a summary (see {group.log_dir / name}.log)")
                break
            s = json.loads(summary_path.read_text())
            episodes.append({"episode": e, "state": s["state"], "steps": s["steps"], "wall_s": s["wall_s"],
                             "failed_moves": s["failed_moves"], "timeouts": s["timeouts"],
                             "world_peak_rss_mb": round(world_usage["peak_rss_mb"], 1) if world_usage else None})
            totals["steps"] += int(s["steps"])
            totals["episodes"] += 1
            totals["successes"] += s["state"] == "success"
            totals["aborted"] += s["state"] == "aborted" or proc.returncode == 1
            for key in ("failed_moves", "timeouts", "rejected"):
                totals[key] += int(s[key])
            if start_usage is None and totals["steps"] >= cfg.warmup_steps:
                start_usage = {n: usage_row(group, n) for n in steady}
                start_usage["world"] = world_usage
                start_usage["_steps"] = totals["steps"]
            print(f"episode {e}: {s['state']}, {s['steps']} steps (total {totals['steps']}), "
                  f"failed moves {s['failed_moves']}, timeouts {s['timeouts']}", flush=True)
            if s["steps"] == 0 and s["state"] != "success":
                crashes.append(f"{name}: no step made ({s['state']}: {s.get('detail', '')})")
                break
            e += 1
            if progress is not None:
                progress(dict(totals=dict(totals), usage=per_process(start_usage, {n: usage_row(group, n) for n in steady}
                                                                       | {"world": world_usage}, t0)))
    except KeyboardInterrupt:
        stopped.append(stopped[-1] if stopped else "SIGINT")
    finally:
        end_usage = {n: usage_row(group, n) for n in steady}
        end_usage["world"] = world_usage
        rss.sample(rss_mb, totals["steps"], totals["episodes"], force=True)
        codes = group.stop_all([n for n in group.procs if n != "recorder"])
        codes |= group.stop_all(["recorder"])
        lock.close()
    wall = time.monotonic() - t0
    account = re.search(r"wrote (\d+) messages.*sequence numbers: (\d+) published, (\d+) received, (\d+) lost",
                        group.log_text("recorder"))
    from mcap.reader import make_reader
    with open(mcap, "rb") as f:
        summary = make_reader(f).get_summary()
    in_file = summary.statistics.message_count if summary is not None else None
    bad_exits = {n: c for n, c in codes.items() if n in steady and c not in (0, None)}
    crashes += [f"{n} exit status {c}" for n, c in bad_exits.items()]
    return {
        "config": asdict(cfg) | {"model": str(model)}, "wall_s": wall, "totals": totals,
        "messages": {"published": int(account[2]) if account else None, "received": int(account[3]) if account else None,
                     "lost": int(account[4]) if account else None, "recorder_wrote": int(account[1]) if account else None,
                     "in_file": in_file},
        "stopped_early": stopped[0] if stopped else None,
        "crashes": crashes, "usage": per_process(start_usage, end_usage, t0), "episodes": episodes,
        "out": str(out), "rss_series": str(rss.path),
    }


def per_process(start: dict | None, end: dict, t0: float) -> dict:
    """{process: {rss_start_mb, rss_end_mb, rss_growth_pct, cpu_pct_start, cpu_pct_end}}: RSS after the warm-up
    and at the end; CPU (% of one core) over the warm-up and from the warm-up to the end. "world" is the
    world node of the episode that ended last at each moment (a new process per episode); its figures are that
    process's peak RSS (VmHWM at its last reading), since its RSS at the last reading depends on the moment
    of its short life at which it was taken."""
    out = {}
    if start is None:
        return out
    for name, e in end.items():
        s = start.get(name)
        if not s or not e:
            continue
        span = e["t"] - s["t"]
        key = "peak_rss_mb" if name == "world" else "rss_mb"
        out[name] = {"rss_start_mb": round(s[key], 1), "rss_end_mb": round(e[key], 1),
                     "rss_growth_pct": round(100.0 * (e[key] - s[key]) / s[key], 2),
                     "cpu_pct_start": None if name == "world" else round(100.0 * s["cpu_s"] / (s["t"] - t0), 1),
                     "cpu_pct_end": None if name == "world" or span <= 0 else
                     round(100.0 * (e["cpu_s"] - s["cpu_s"]) / span, 1)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/bench_soak", description=__doc__.split("\n\n")[0])
    for name, value in asdict(SoakConfig()).items():
        ap.add_argument("--" + name.replace("_", "-"), type=type(value), default=value, help=f"(default {value!r})")
    cfg = SoakConfig(**vars(ap.parse_args(argv)))
    if cfg.robots < 1 or cfg.steps < 1 or cfg.warmup_steps < 0 or not cfg.rss_period_s > 0:
        ap.error("--robots and --steps must be >= 1, --warmup-steps >= 0 and --rss-period-s > 0")
    out = Path(cfg.out or f"runs/soak/{time.strftime('%Y%m%d-%H%M%S')}")
    cfg.out = str(out)
    out.mkdir(parents=True, exist_ok=True)

    def progress(partial):  # a long soak that is stopped or dies still leaves its figures so far
        (out / "soak.progress.json").write_text(json.dumps(partial, indent=1) + "\n")

    try:
        report = run(cfg, progress)
    except ValueError as exc:  # a model the robots cannot run (no export, or a stale one): the message says the fix
        print(f"soak: error: {exc}", file=sys.stderr)
        return 2
    (out / "soak.json").write_text(json.dumps(report, indent=1) + "\n")
    t, m = report["totals"], report["messages"]
    print(f"soak: {t['steps']} grid steps in {t['episodes']} episodes ({t['successes']} solved), {cfg.robots} robots, "
          f"{report['wall_s'] / 60:.1f} min; failed moves {t['failed_moves']}, timeouts {t['timeouts']}, "
          f"aborted episodes {t['aborted']}")
    print(f"messages: published {m['published']}, received {m['received']}, lost {m['lost']} "
          f"(single-publisher topics); recorder wrote {m['recorder_wrote']}, file holds {m['in_file']}")
    print(f"{'process':<12} {'RSS start MB':>12} {'RSS end MB':>10} {'growth %':>9} {'CPU % start':>11} {'CPU % end':>9}")
    for name, u in report["usage"].items():
        print(f"{name:<12} {u['rss_start_mb']:>12} {u['rss_end_mb']:>10} {u['rss_growth_pct']:>9} "
              f"{u['cpu_pct_start']!s:>11} {u['cpu_pct_end']!s:>9}")
    peaks = [ep["world_peak_rss_mb"] for ep in report["episodes"] if ep.get("world_peak_rss_mb")]
    if peaks:
        print(f"world node peak RSS per episode (MB): min {min(peaks)}, median {statistics.median(peaks):.1f}, "
              f"max {max(peaks)} over {len(peaks)} episodes; first {peaks[0]}, last {peaks[-1]}")
    print("crashes: " + ("; ".join(report["crashes"]) if report["crashes"] else "none")
          + (f"; stopped early by {report['stopped_early']}" if report["stopped_early"] else ""))
    print(f"report: {out / 'soak.json'}")
    return 0 if not report["crashes"] and m["lost"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
