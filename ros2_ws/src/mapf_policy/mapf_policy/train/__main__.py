"""CLI of training: `scripts/train [--field value ...]`, one flag per TrainConfig field.

The run directory is runs/<run name>; the default name says what runs, so the same command resumes
the same run. When the run exists, its saved config.json is used; flags may change only the schedule
fields below (e.g. a larger --total-steps), any other difference is an error naming the fields.
  scripts/train --total-steps 20 --map-size 10 --max-agents 2 ...   (smoke run)
  scripts/train --data-only                                            (only generate the demo cache)
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import sys
from pathlib import Path

from mapf_policy.config import TrainConfig
from mapf_policy.solver import repo_root

SCHEDULE_FIELDS = ("total_steps", "checkpoint_minutes", "log_every", "device", "learner_threads", "actor_threads",
                   "actors", "session_minutes", "max_replay_ratio", "eval_minutes", "data_workers")


def field_docs(cls) -> dict:
    """Attribute docstrings of a dataclass (the string literal under each field), for --help."""
    docs, body = {}, ast.parse(inspect.getsource(cls)).body[0].body
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant):
            docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="scripts/train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    docs = field_docs(TrainConfig)
    for f in dataclasses.fields(TrainConfig):
        flag, helptext = "--" + f.name.replace("_", "-"), f"{docs.get(f.name, '')} (default: {f.default!r})"
        if isinstance(f.default, bool):
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=helptext)
        elif isinstance(f.default, tuple):
            parser.add_argument(flag, dest=f.name, type=int, nargs="+", default=None, help=helptext)
        else:
            parser.add_argument(flag, dest=f.name, type=type(f.default), default=None, help=helptext)
    parser.add_argument("--resume", action="store_true", help="require an existing run and resume it")
    parser.add_argument("--data-only", action="store_true", help="generate the expert demonstration cache and exit")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def resolve_config(explicit: dict, root: Path, resume: bool) -> tuple[TrainConfig, Path]:
    """The run's config: the saved one when the run exists (schedule overrides only), else the flags."""
    explicit = {k: tuple(v) if isinstance(v, list) else v for k, v in explicit.items()}
    fresh = TrainConfig(**explicit)
    fresh.validate()
    run_dir = root / fresh.runs_dir / fresh.resolved_run_name()
    saved_path = run_dir / "config.json"
    if not saved_path.is_file():
        if resume:
            raise ValueError(f"--resume: no run at {run_dir} (no config.json)")
        return fresh, run_dir
    saved = TrainConfig.from_dict(json.loads(saved_path.read_text()))
    differing = sorted(k for k, v in explicit.items() if getattr(saved, k) != v and k not in SCHEDULE_FIELDS)
    if differing:
        raise ValueError(f"run {run_dir} exists with other values of {differing}; resume it without them "
                         f"or pick another --run-name (only {list(SCHEDULE_FIELDS)} may change on resume)")
    cfg = dataclasses.replace(saved, **{k: v for k, v in explicit.items() if k in SCHEDULE_FIELDS})
    cfg.validate()
    return cfg, run_dir


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    explicit = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if getattr(args, f.name) is not None}
    root = repo_root()
    try:
        cfg, run_dir = resolve_config(explicit, root, args.resume)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"run {run_dir}\n" + json.dumps(cfg.asdict(), indent=1))
    if args.data_only:
        from mapf_policy.train.demos import ensure_demos, load_demos

        paths = ensure_demos(cfg, root, progress=not args.no_progress)
        print(json.dumps(load_demos(paths, cfg.demo_capacity, cfg.fov_size, cfg.demo_goal_keep, cfg.seed)[1], indent=1))
        return 0
    from mapf_policy.train.learner import train

    learner = train(cfg, run_dir, root, progress=not args.no_progress)
    print(f"stopped at step {learner.step}; checkpoint {run_dir / 'checkpoint.pt'}, model {run_dir / 'last.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
