"""Offline supervised fit of a model on expert-labelled rows: `scripts/fit_rows`.

The expert (supervised) half of training without the actors: a model is fine-tuned on rows that
`scripts/collect_rows` saved (states a policy visited, labelled by ODrM*; DAgger's aggregation step), and
its agreement with the expert is measured on held-out rows as it goes, split by situation as
`scripts/expert_agreement` splits it. It answers questions the online runs could not: whether the network
can fit the crowded states at all (agreement on a fixed sample of the training rows), whether that carries
over to other episodes (held-out rows), and which loss does it better. No DQN term: rows carry no rewards.

Loss = phi * HSCL (eq. 13, as in training) + ce * cross-entropy of softmax(Q / ce_temperature) with the
expert action. The cross-entropy is a change beyond the paper: with ce_temperature equal to the action
temperature of the shipped rule (0.04), it is the likelihood of the expert's action under the very
distribution the agents draw their actions from. --crowded-share draws that share of each batch from the
crowded rows (off goal, 4 or more other agents in view) instead of uniformly.

Output directory: config.json, fit.csv (one row per evaluation), fit.png (its curves), step_<k>.pt model files at each
evaluation, last.pt, and checkpoint.pt (model + optimizer + counters; git-ignored with runs/) from which
the same command resumes (also with a larger --steps; other settings must match).
  scripts/fit_rows models/hscl.pt runs/fit_a --rows runs/rows_train --held-out runs/rows_heldout --steps 20000
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

from mapf_policy.inference import FastForward, InferenceNet
from mapf_policy.losses import hscl_loss
from mapf_policy.model_io import load_model, model_payload, network_from_payload, save_model
from mapf_policy.train.agreement import situations, tally
from mapf_policy.train.log import CsvLog, read_csv, truncate_log
from mapf_policy.train.rows import load_rows

CROWDED = "off goal, 4+ in view"
FIT_COLUMNS = ("step", "loss", "hscl", "ce", "train_all", "train_crowded", "held_out_all", "held_out_crowded",
               "elapsed_s")


@dataclass(frozen=True)
class FitConfig:
    """One offline fit (saved as config.json in the output directory)."""

    init_model: str
    rows: tuple
    held_out: tuple
    steps: int = 20_000
    batch_size: int = 256
    lr: float = 1e-4
    phi: float = 1.0
    """Weight of HSCL (eq. 13)."""
    tau_h: float = 0.1
    temperature: float = 0.1
    """HSCL temperature T."""
    ce: float = 0.0
    """Weight of the cross-entropy of softmax(Q / ce_temperature) with the expert action (0: off, the paper)."""
    ce_temperature: float = 0.04
    crowded_share: float = -1.0
    """Share of each batch drawn from the crowded rows; < 0: uniform over all rows."""
    eval_every: int = 1000
    train_sample: int = 50_000
    """Training rows (a fixed random sample) scored at each evaluation, to see how well the rows are fitted."""
    threads: int = 2
    seed: int = 0

    def validate(self) -> None:
        for name in ("steps", "batch_size", "eval_every", "train_sample", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (self.phi >= 0 and self.ce >= 0 and self.phi + self.ce > 0):
            raise ValueError(f"phi and ce must be >= 0 and not both 0, got {self.phi}, {self.ce}")
        if not (self.lr > 0 and self.temperature > 0 and self.ce_temperature > 0):
            raise ValueError("lr, temperature and ce_temperature must be > 0")
        if not 0.0 < self.tau_h < 0.2:
            raise ValueError(f"tau_h must lie in (0, 0.2) (Table I), got {self.tau_h}")
        if self.crowded_share > 1.0:
            raise ValueError(f"crowded_share must be <= 1 (or < 0 for uniform), got {self.crowded_share}")
        if not self.rows or not self.held_out:
            raise ValueError("at least one --rows and one --held-out directory are needed")
        if set(map(str, self.rows)) & set(map(str, self.held_out)):
            raise ValueError("a directory is both a training and a held-out rows directory")


def row_tensors(rows: dict, idx) -> tuple:
    """(fov, last_action one-hot, position, expert) tensors of rows[idx]."""
    fov = torch.from_numpy(rows["fov"][idx]).float().contiguous(memory_format=torch.channels_last)
    last = F.one_hot(torch.from_numpy(rows["last_action"][idx].astype(np.int64)), 5).float()
    pos = torch.from_numpy(rows["position"][idx]).float()
    return fov, last, pos, torch.from_numpy(rows["expert"][idx].astype(np.int64))


def fit_loss(q: torch.Tensor, expert: torch.Tensor, cfg: FitConfig) -> tuple:
    """(total, hscl, ce) of one batch."""
    zero = q.new_zeros(())
    l_hscl = hscl_loss(q, expert, cfg.tau_h, cfg.temperature) if cfg.phi > 0 else zero
    l_ce = F.cross_entropy(q / cfg.ce_temperature, expert) if cfg.ce > 0 else zero
    return cfg.phi * l_hscl + cfg.ce * l_ce, l_hscl, l_ce


def score_rows(net, rows: dict, idx=None, chunk: int = 4096) -> dict:
    """agreement.tally of the network's argmax over rows[idx] (all rows when idx is None)."""
    idx = np.arange(len(rows["expert"])) if idx is None else idx
    forward, qs = InferenceNet(net.eval()), []
    with torch.inference_mode():
        for s in range(0, len(idx), chunk):
            fov, last, pos, _ = row_tensors(rows, idx[s:s + chunk])
            qs.append(forward(fov, last, pos).numpy())
    net.train()
    return tally(np.concatenate(qs), rows["expert"][idx].astype(np.int64), rows["fov"][idx])


def _share(t: dict, key: str) -> float:
    return t[key]["agree"] / t[key]["rows"] if t[key]["rows"] else float("nan")


class Fitter:
    def __init__(self, cfg: FitConfig, out: Path):
        cfg.validate()
        self.cfg, self.out = cfg, out
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.net, self.ncfg, meta = load_model(cfg.init_model)
        self.init_meta = meta
        self.net.train()
        self.forward = FastForward(self.net)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.step, self.elapsed = 0, 0.0
        self.rows, self.held_out = load_rows(cfg.rows), load_rows(cfg.held_out)
        for name, r in (("rows", self.rows), ("held-out rows", self.held_out)):
            if r["fov"].shape[-1] != self.ncfg.fov_size:
                raise ValueError(f"the {name} have a {r['fov'].shape[-1]}x{r['fov'].shape[-1]} field of view, "
                                 f"the model {self.ncfg.fov_size}x{self.ncfg.fov_size}")
        self.crowded = np.flatnonzero(situations(self.rows["fov"])[CROWDED])
        if cfg.crowded_share > 0 and len(self.crowded) == 0:
            raise ValueError("--crowded-share needs crowded rows (off goal, 4+ in view); the training rows have none")
        n = len(self.rows["expert"])
        self.train_idx = np.sort(np.random.default_rng(cfg.seed + 1).choice(n, min(n, cfg.train_sample), replace=False))

    def batch_indices(self) -> np.ndarray:
        b, n = self.cfg.batch_size, len(self.rows["expert"])
        if self.cfg.crowded_share < 0:
            return self.rng.integers(0, n, b)
        k = int(round(b * self.cfg.crowded_share))
        return np.concatenate([self.crowded[self.rng.integers(0, len(self.crowded), k)], self.rng.integers(0, n, b - k)])

    def update(self) -> dict:
        fov, last, pos, expert = row_tensors(self.rows, self.batch_indices())
        loss, l_hscl, l_ce = fit_loss(self.forward(fov, last, pos), expert, self.cfg)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        return {"loss": loss.item(), "hscl": l_hscl.item(), "ce": l_ce.item()}

    def evaluate(self) -> dict:
        train, held = score_rows(self.net, self.rows, self.train_idx), score_rows(self.net, self.held_out)
        return {"train_all": _share(train, "all"), "train_crowded": _share(train, CROWDED),
                "held_out_all": _share(held, "all"), "held_out_crowded": _share(held, CROWDED)}

    def meta(self) -> dict:
        return {"step": self.step, "fit_config": asdict(self.cfg), "init_meta": self.init_meta}

    def save_checkpoint(self) -> None:
        payload = {"model": model_payload(self.net, self.ncfg, self.meta()), "optimizer": self.opt.state_dict(),
                   "step": self.step, "elapsed": self.elapsed, "rng": self.rng.bit_generator.state,
                   "torch_rng": torch.get_rng_state()}
        tmp = self.out / "checkpoint.pt.tmp"
        torch.save(payload, tmp)
        os.replace(tmp, self.out / "checkpoint.pt")
        save_model(self.out / "last.pt", self.net, self.ncfg, self.meta())

    def load_checkpoint(self) -> None:
        path = self.out / "checkpoint.pt"
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
            net, ncfg, _ = network_from_payload(ck["model"], str(path))
        except Exception as exc:
            raise ValueError(f"{path} is not a readable fit checkpoint: {exc}") from exc
        if ncfg != self.ncfg:
            raise ValueError(f"{path}: network {ncfg} differs from {self.cfg.init_model}'s {self.ncfg}")
        self.net.load_state_dict(net.state_dict())
        self.opt.load_state_dict(ck["optimizer"])
        self.step, self.elapsed = int(ck["step"]), float(ck["elapsed"])
        self.rng.bit_generator.state = ck["rng"]
        torch.set_rng_state(ck["torch_rng"])


def plot_fit(out: Path) -> Path | None:
    """OUT/fit.png: the losses, and agreement with the expert (all rows and crowded rows, training sample and
    held-out) against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = read_csv(out / "fit.csv") if (out / "fit.csv").is_file() else {}
    if not log:
        return None
    fig, (ax_loss, ax_agree) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for key, label in (("hscl", "HSCL"), ("ce", "cross-entropy")):
        if np.nanmax(np.abs(np.nan_to_num(log[key]))) > 0:
            ax_loss.plot(log["step"], log[key], "o-", ms=3, label=label)
    ax_loss.set_title("loss (mean since the previous evaluation)")
    ax_loss.legend()
    for key, style, label in (("train_all", "C0--", "training sample, all rows"),
                              ("train_crowded", "C0-", f"training sample, {CROWDED}"),
                              ("held_out_all", "C1--", "held-out, all rows"),
                              ("held_out_crowded", "C1-", f"held-out, {CROWDED}")):
        ax_agree.plot(log["step"], log[key], style, marker="o", ms=3, label=label)
    ax_agree.set_title("argmax Q = expert action")
    ax_agree.legend(fontsize=7)
    for ax in (ax_loss, ax_agree):
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    fig.savefig(out / "fit.png", dpi=90)
    plt.close(fig)
    return out / "fit.png"


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def fit(cfg: FitConfig, out: Path, progress: bool = True) -> Fitter:
    """Run (or resume) the fit in `out` up to cfg.steps; evaluates at step 0 (the start model) too."""
    out.mkdir(parents=True, exist_ok=True)
    config_path = out / "config.json"
    if config_path.is_file():  # a resume may raise `steps`; anything else must match
        old, new = json.loads(config_path.read_text()), json.loads(json.dumps(asdict(cfg)))
        diff = sorted(k for k in set(old) | set(new) if k != "steps" and old.get(k) != new.get(k))
        if diff:
            raise ValueError(f"{out} holds a fit with other settings (differs in {diff}); use another directory")
    torch.set_num_threads(cfg.threads)
    fitter = Fitter(cfg, out)
    config_path.write_text(json.dumps(asdict(cfg), indent=1))
    log_path = out / "fit.csv"
    if (out / "checkpoint.pt").is_file():
        fitter.load_checkpoint()
        truncate_log(log_path, fitter.step)
        log = CsvLog(log_path, FIT_COLUMNS)
    else:
        log_path.unlink(missing_ok=True)
        log = CsvLog(log_path, FIT_COLUMNS)
        log.write({"step": 0, "loss": float("nan"), "hscl": float("nan"), "ce": float("nan"), **fitter.evaluate(),
                   "elapsed_s": 0.0})
    print(f"{len(fitter.rows['expert'])} training rows ({len(fitter.crowded)} crowded), "
          f"{len(fitter.held_out['expert'])} held-out rows", flush=True)
    previous = signal.signal(signal.SIGTERM, _interrupt)
    bar = tqdm(total=cfg.steps, initial=fitter.step, desc=out.name, unit="step", disable=not progress,
               mininterval=1.0 if sys.stderr.isatty() else 30.0)
    start, losses = time.monotonic() - fitter.elapsed, []
    try:
        while fitter.step < cfg.steps:
            losses.append(fitter.update())
            bar.update(1)
            if fitter.step % cfg.eval_every == 0 or fitter.step == cfg.steps:
                fitter.elapsed = time.monotonic() - start
                mean = {k: float(np.mean([l[k] for l in losses])) for k in ("loss", "hscl", "ce")}
                row = {"step": fitter.step, **mean, **fitter.evaluate(), "elapsed_s": fitter.elapsed}
                log.write(row)
                save_model(out / f"step_{fitter.step}.pt", fitter.net, fitter.ncfg, fitter.meta())
                fitter.save_checkpoint()
                plot_fit(out)
                bar.set_postfix(crowded=f"{row['held_out_crowded']:.3f}", train=f"{row['train_crowded']:.3f}")
                losses = []
    except KeyboardInterrupt:
        print(f"\ninterrupted at step {fitter.step}: rerun the same command to resume from step "
              f"{fitter.step - fitter.step % cfg.eval_every}")
    finally:
        bar.close()
        signal.signal(signal.SIGTERM, previous)
    return fitter


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/fit_rows", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", type=Path, help="model file to start from")
    p.add_argument("out", type=Path, help="output directory (resumed when it holds a checkpoint of the same fit)")
    p.add_argument("--rows", type=Path, nargs="+", required=True, help="row directories to fit on")
    p.add_argument("--held-out", type=Path, nargs="+", required=True,
                   help="row directories to evaluate on (collected with --held-out)")
    defaults = {f.name: f.default for f in fields(FitConfig)}
    for name in ("steps", "batch_size", "lr", "phi", "tau_h", "temperature", "ce", "ce_temperature", "crowded_share",
                 "eval_every", "train_sample", "threads", "seed"):
        kind = type(defaults[name])
        p.add_argument("--" + name.replace("_", "-"), type=kind, default=defaults[name],
                       help=f"(default {defaults[name]})")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if not args.model.is_file():
        p.error(f"no such model file: {args.model}")
    cfg = FitConfig(init_model=str(args.model), rows=tuple(map(str, args.rows)),
                    held_out=tuple(map(str, args.held_out)),
                    **{k: getattr(args, k) for k in FitConfig.__dataclass_fields__
                       if k not in ("init_model", "rows", "held_out")})
    try:
        fitter = fit(cfg, args.out, not args.no_progress)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"step {fitter.step}; log {args.out / 'fit.csv'}")
    print((args.out / "fit.csv").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
