"""Training logs: an append-only CSV (survives resumes) and a PNG plot of the run so far."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

TRAIN_COLUMNS = (
    "step", "loss", "l1", "l2", "epsilon", "success_rate", "average_step", "samples_per_s", "env_samples_per_s",
    "agreement", "labelled_share", "team_cap", "mean_team", "episodes", "online_size", "demo_size", "elapsed_s",
)
EVAL_COLUMNS = ("step", "team_size", "success_rate", "average_step", "score")


class CsvLog:
    """Appends rows with fixed columns; writes the header only when the file is new."""

    def __init__(self, path: Path, columns: tuple):
        self.path, self.columns = Path(path), columns
        if self.path.is_file():
            with self.path.open() as f:
                header = next(csv.reader(f), None)
            if header is not None and tuple(header) != columns:
                raise ValueError(f"{self.path} has columns {header}, expected {list(columns)}")
        else:
            with self.path.open("w", newline="") as f:
                csv.writer(f).writerow(columns)

    def write(self, row: dict) -> None:
        missing = set(self.columns) - set(row)
        if missing:
            raise ValueError(f"log row lacks {sorted(missing)}")
        with self.path.open("a", newline="") as f:
            csv.writer(f).writerow([_fmt(row[c]) for c in self.columns])


def truncate_log(path: Path, step: int) -> None:
    """Drop rows logged after the checkpoint a run resumes from, so the CSV has no duplicate steps."""
    if not Path(path).is_file():
        return
    lines = Path(path).read_text().splitlines(keepends=True)
    kept = lines[:1] + [ln for ln in lines[1:] if int(float(ln.split(",", 1)[0])) <= step]
    Path(path).write_text("".join(kept))


def _fmt(v) -> str:
    if isinstance(v, float):
        return "" if np.isnan(v) else f"{v:.6g}"
    return str(v)


def read_csv(path: Path) -> dict:
    """Columns as float arrays (empty cells -> nan)."""
    with Path(path).open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    return {k: np.array([float(r[k]) if r[k] != "" else np.nan for r in rows]) for k in rows[0]}


def actor_rule_label(run_dir: Path) -> str:
    """How the run's actors chose actions, from its config.json (runs before the field existed: eps-greedy)."""
    path = Path(run_dir) / "config.json"
    t = json.loads(path.read_text()).get("actor_action_temperature", 0.0) if path.is_file() else 0.0
    return f"softmax(Q/{t:g}) + eps" if t > 0 else "eps-greedy"


def plot_run(run_dir: Path) -> Path | None:
    """runs/<name>/training.png: losses, epsilon, success rate and average step against learner step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_dir = Path(run_dir)
    train_path = run_dir / "train.csv"
    log = read_csv(train_path) if train_path.is_file() else {}
    if not log:
        return None
    evals = read_csv(run_dir / "eval.csv") if (run_dir / "eval.csv").is_file() else {}
    actors = actor_rule_label(run_dir)
    fig, axes = plt.subplots(2, 3, figsize=(14, 7), constrained_layout=True)
    step = log["step"]
    ax = axes[0, 0]
    for k, label in (("loss", "total"), ("l1", "L1 (DQN)"), ("l2", "L2 (HSCL)")):
        ax.plot(step, log[k], label=label, lw=1)
    ax.set_yscale("log")
    ax.set_title("loss")
    ax.legend()
    axes[0, 1].plot(step, log["epsilon"], lw=1)
    axes[0, 1].set_title("epsilon")
    axes[0, 2].plot(step, log["agreement"], lw=1)
    axes[0, 2].set_title("argmax Q = expert action (batch share)")
    for ax, key, title in ((axes[1, 0], "success_rate", "success rate"), (axes[1, 1], "average_step", "average step")):
        ax.plot(step, log[key], lw=1, label=f"training episodes ({actors})")
        if evals:
            for n in np.unique(evals["team_size"]):
                sel = evals["team_size"] == n
                ax.plot(evals["step"][sel], evals[key][sel], "o-", ms=3, label=f"validation, {int(n)} agents")
        ax.set_title(title)
        ax.legend(fontsize=7)
    axes[1, 2].plot(step, log["team_cap"], label="team cap", lw=1)
    axes[1, 2].plot(step, log["mean_team"], label="mean team size", lw=1)
    axes[1, 2].set_title("curriculum")
    axes[1, 2].legend()
    for ax in axes.flat:
        ax.set_xlabel("learner step")
        ax.grid(alpha=0.3)
    out = run_dir / "training.png"
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
