"""Learner: DQN + HSCL updates (eq. 14) from actor replay and expert demonstrations, with checkpoints.

Run directory runs/<name>/: config.json, checkpoint.pt (model, target, optimizer, counters, replay
metadata, RNG states; resumed automatically), last.pt and best.pt (model files), train.csv, eval.csv,
training.png. The online replay itself is not checkpointed (hundreds of MB): after a resume the actor
refills it while the learner continues on demonstrations.
"""
from __future__ import annotations

import collections
import json
import multiprocessing as mp
import os
import queue
import signal
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapf_policy.config import TrainConfig
from mapf_policy.inference import FastForward, InferenceNet
from mapf_policy.losses import combined_loss, dqn_loss, expert_agreement, hscl_loss
from mapf_policy.model_io import load_model, model_payload, network_from_payload, save_model
from mapf_policy.network import QNetwork
from mapf_policy.train.actor import actor_main, epsilon_at, team_cap_at
from mapf_policy.train.demos import ensure_demos, load_demos, on_goal_stays
from mapf_policy.train.log import EVAL_COLUMNS, TRAIN_COLUMNS, CsvLog, plot_run, truncate_log
from mapf_policy.train.replay import ReplayBuffer, concat, to_tensors

CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "mapf_policy.checkpoint", 1


class Learner:
    """Owns the networks, optimizer, buffers and counters of one run."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, demos: dict | None):
        self.cfg, self.run_dir = cfg, run_dir
        self.device = torch.device(cfg.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device cuda was asked for but torch sees no CUDA device")
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0]))
        self.keep_rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 5]))
        self.ncfg = cfg.network_config()
        # channels_last: about 20% faster convolutions in QNetwork.forward (measured before inference.py);
        # numerics unchanged. On CPU, update() uses the passes of inference.py instead (below), and
        # scripts/bench_learner times this plain channels-last forward as its reference.
        self.net = QNetwork(self.ncfg).to(self.device, memory_format=torch.channels_last)
        self.target = QNetwork(self.ncfg).to(self.device, memory_format=torch.channels_last)
        self.target.load_state_dict(self.net.state_dict())
        self.target.eval()
        # On CPU, both networks' Q-values come from the faster forward passes of inference.py (the same
        # function): the online network's differentiable FastForward, and the target's InferenceNet, which
        # follows the target's weights as they are copied in. Figures: models/README.md, "Inference speed".
        cpu = self.device.type == "cpu"
        self.online_q = FastForward(self.net) if cpu else self.net
        self.target_q = InferenceNet(self.target) if cpu else self.target
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.online = ReplayBuffer(cfg.replay_capacity, cfg.fov_size)
        self.demo = None
        if demos is not None:
            self.demo = ReplayBuffer(len(demos["action"]), cfg.fov_size)
            self.demo.add(demos)
        self.step, self.episode = 0, 0
        self.online_drawn = 0  # online samples drawn in this session (the replay is not checkpointed either)
        # Online transitions received from the actors in this session, before the goal-wait filter of
        # add_online: the count the actors' own gate uses, so learning_starts and max_replay_ratio count
        # the same thing (with the filter, the replay grows slower than the actors produce).
        self.online_received = 0
        self.session_start = time.monotonic()
        self.elapsed = 0.0  # wall seconds of earlier sessions of this run (the CSV's elapsed_s adds this one)

    # --- checkpoints ------------------------------------------------------------------------------
    def save_checkpoint(self) -> None:
        meta = {"step": self.step, "train_config": self.cfg.asdict()}
        payload = {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "step": self.step, "episode": self.episode,
            "elapsed": self.elapsed + time.monotonic() - self.session_start,
            "model": model_payload(self.net, self.ncfg, meta),
            "target_state_dict": {k: v.cpu() for k, v in self.target.state_dict().items()},
            "optimizer": self.opt.state_dict(),
            "replay": {"online_size": len(self.online), "online_added": self.online.added,
                       "demo_size": len(self.demo) if self.demo else 0},
            "rng": {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state},
            "train_config": self.cfg.asdict(),
        }
        tmp = self.run_dir / "checkpoint.pt.tmp"
        torch.save(payload, tmp)
        os.replace(tmp, self.run_dir / "checkpoint.pt")
        save_model(self.run_dir / "last.pt", self.net, self.ncfg, meta)

    def load_checkpoint(self, path: Path) -> None:
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{path} is not a readable checkpoint: {exc}") from exc
        if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT or ck.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path} is not a version-{CHECKPOINT_VERSION} training checkpoint")
        net, ncfg, _ = network_from_payload(ck["model"], f"{path} (model)")
        if ncfg != self.ncfg:
            raise ValueError(f"{path}: checkpoint network {ncfg} differs from the run's {self.ncfg}")
        self.net.load_state_dict(net.state_dict())
        self.target.load_state_dict(ck["target_state_dict"])
        self.opt.load_state_dict(ck["optimizer"])
        self.step, self.episode = int(ck["step"]), int(ck["episode"])
        self.elapsed = float(ck["elapsed"])
        torch.set_rng_state(ck["rng"]["torch"])
        self.rng.bit_generator.state = ck["rng"]["numpy"]

    def init_from(self, path: Path) -> None:
        """Start from a model file's weights (online and target network); its architecture must match."""
        net, ncfg, _ = load_model(path)
        if ncfg != self.ncfg:
            raise ValueError(f"init_model {path} has network {ncfg}, this run needs {self.ncfg}")
        self.net.load_state_dict(net.state_dict())
        self.target.load_state_dict(net.state_dict())

    def add_online(self, chunk: dict) -> int:
        """An actor episode's transitions into the replay; a share cfg.online_goal_keep of its on-goal waits
        (demos.on_goal_stays) is kept, terminal rows always. Returns the rows kept."""
        keep_share = self.cfg.online_goal_keep
        self.online_received += len(chunk["action"])
        if keep_share < 1.0:
            # A generator of its own, so that the batch draws of self.rng do not depend on this setting.
            drop = on_goal_stays(chunk) & ~chunk["terminated"].astype(bool)
            drop &= self.keep_rng.random(len(drop)) >= keep_share
            if drop.any():
                chunk = {k: v[~drop] for k, v in chunk.items()}
        n = len(chunk["action"])
        if n:
            self.online.add(chunk)
        return n

    def online_ready(self) -> bool:
        """learning_starts online transitions received, and some of them in the replay."""
        return self.online_received >= max(1, self.cfg.learning_starts) and len(self.online) > 0

    # --- one gradient step --------------------------------------------------------------------------
    def sample(self) -> dict:
        b = self.cfg.batch_size
        online_ready = self.online_ready()
        n_demo = 0 if self.demo is None else (b if not online_ready else int(round(b * self.cfg.demo_fraction)))
        parts = []
        if n_demo:
            parts.append(self.demo.sample(n_demo, self.rng))
        if b - n_demo:
            parts.append(self.online.sample(b - n_demo, self.rng))
            self.online_drawn += b - n_demo
        return to_tensors(concat(parts), self.device)

    def update(self) -> dict:
        cfg, t = self.cfg, self.sample()
        q = self.online_q(t["fov"], t["last_action"], t["position"])
        with torch.no_grad():
            next_q = self.target_q(t["next_fov"], t["next_last_action"], t["next_position"])
        l1 = dqn_loss(q, t["action"], t["reward"], next_q, t["terminated"], cfg.gamma)
        labelled = t["expert"] >= 0
        if labelled.any():
            l2 = hscl_loss(q[labelled], t["expert"][labelled], cfg.tau_h, cfg.temperature)
            agreement = expert_agreement(q[labelled].detach(), t["expert"][labelled])
        else:
            l2, agreement = torch.zeros((), device=self.device), float("nan")
        loss = combined_loss(l1, l2, cfg.delta, cfg.phi)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.net.parameters(), cfg.grad_clip)
        self.opt.step()
        self.step += 1
        if self.step % cfg.target_update_every == 0:
            self.target.load_state_dict(self.net.state_dict())
        return {"loss": loss.item(), "l1": l1.item(), "l2": l2.item(), "agreement": agreement}

    def weights(self) -> dict:
        return {"step": self.step, "state_dict": {k: v.detach().cpu().numpy().copy() for k, v in self.net.state_dict().items()}}


def _publish(weights_qs, item) -> None:
    """In every actor's queue, replace whatever it has not picked up yet with the newest weights."""
    for q in weights_qs:
        try:
            q.get_nowait()
        except queue.Empty:
            pass
        q.put(item)


def _raise_interrupt(signum, frame):
    """SIGTERM (kill, a scheduler's stop) ends the run like Ctrl-C: checkpoint, then exit."""
    raise KeyboardInterrupt


def train(cfg: TrainConfig, run_dir: Path, root: Path, progress: bool = True) -> Learner:
    """Train (or resume) the run in `run_dir` up to cfg.total_steps learner steps."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.asdict(), indent=1))
    torch.set_num_threads(cfg.learner_threads)
    demos, demo_stats = None, {}
    if cfg.demo_instances > 0:
        demos, demo_stats = load_demos(ensure_demos(cfg, root, progress), cfg.demo_capacity, cfg.fov_size,
                                       cfg.demo_goal_keep, cfg.seed)
        (run_dir / "demos.json").write_text(json.dumps(demo_stats, indent=1))
    learner = Learner(cfg, run_dir, demos)
    del demos
    if (run_dir / "checkpoint.pt").is_file():
        learner.load_checkpoint(run_dir / "checkpoint.pt")
        truncate_log(run_dir / "train.csv", learner.step)
        truncate_log(run_dir / "eval.csv", learner.step)
    elif cfg.init_model:
        learner.init_from(Path(cfg.init_model))
    train_log, eval_log = CsvLog(run_dir / "train.csv", TRAIN_COLUMNS), CsvLog(run_dir / "eval.csv", EVAL_COLUMNS)

    ctx = mp.get_context("spawn")
    weights_qs = [ctx.Queue(maxsize=1) for _ in range(cfg.actors)]
    data_q = ctx.Queue(maxsize=64 * cfg.actors)
    learner_step, stop = ctx.Value("q", learner.step), ctx.Event()
    _publish(weights_qs, learner.weights())
    actors = [ctx.Process(target=actor_main, name=f"mapf-actor-{k}", daemon=True,
                          args=(cfg.asdict(), str(run_dir), learner.episode, weights_qs[k], data_q, learner_step, stop, k))
              for k in range(cfg.actors)]
    for actor in actors:
        actor.start()
    previous_sigterm = signal.signal(signal.SIGTERM, _raise_interrupt)
    deadline = time.monotonic() + 60.0 * cfg.session_minutes if cfg.session_minutes > 0 else float("inf")

    recent = collections.deque(maxlen=100)
    window = {"losses": [], "env": 0, "t": time.monotonic(), "steps": 0}
    last_ckpt = time.monotonic()
    bar = tqdm(total=cfg.total_steps, initial=learner.step, desc=run_dir.name, unit="step", disable=not progress,
               mininterval=1.0 if sys.stderr.isatty() else 60.0)  # a log file gets a line a minute
    try:
        while learner.step < cfg.total_steps:
            while True:  # drain the actor's messages
                try:
                    msg = data_q.get_nowait()
                except queue.Empty:
                    break
                if msg["kind"] == "episode":
                    learner.add_online(msg["transitions"])
                    learner.episode = max(learner.episode, msg["episode"])
                    recent.append(msg["stats"])
                    window["env"] += len(msg["transitions"]["action"])
                else:
                    for n, v in msg["result"]["sizes"].items():
                        eval_log.write({"step": msg["result"]["step"], "team_size": n, "score": msg["result"]["score"], **v})
            dead = [a for a in actors if not a.is_alive()]
            if dead:
                raise RuntimeError(f"actor process {dead[0].name} died (exit code {dead[0].exitcode}); "
                                   "see its traceback above")
            if time.monotonic() > deadline:
                print(f"\nsession limit of {cfg.session_minutes:g} min reached at step {learner.step}: checkpointing; "
                      "rerun the same command to continue")
                break
            if learner.demo is None and not learner.online_ready():
                time.sleep(0.05)  # nothing to learn from yet
                continue
            if cfg.max_replay_ratio > 0 and learner.online_drawn > cfg.max_replay_ratio * max(1, learner.online_received):
                time.sleep(0.005)  # the actors are behind: wait for fresh samples
                continue
            window["losses"].append(learner.update())
            window["steps"] += 1
            learner_step.value = learner.step
            bar.update(1)
            if learner.step % cfg.weights_sync_every == 0:
                _publish(weights_qs, learner.weights())
            if learner.step % cfg.log_every == 0 or learner.step == cfg.total_steps:
                row = _log_row(cfg, learner, window, recent, time.monotonic() - learner.session_start)
                train_log.write(row)
                bar.set_postfix(loss=f"{row['loss']:.3g}", agree=f"{row['agreement']:.2f}", sr=f"{row['success_rate']:.2f}")
                window.update(losses=[], env=0, t=time.monotonic(), steps=0)
            if time.monotonic() - last_ckpt > 60.0 * cfg.checkpoint_minutes:
                learner.save_checkpoint()
                plot_run(run_dir)
                last_ckpt = time.monotonic()
    except KeyboardInterrupt:
        print(f"\ninterrupted at step {learner.step}: checkpointing; rerun the same command to resume")
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        stop.set()
        bar.close()
        learner.save_checkpoint()
        plot_run(run_dir)
        for actor in actors:
            actor.join(timeout=10)
            if actor.is_alive():
                actor.terminate()
                actor.join()
        # Weights an actor never picked up sit in a queue feeder thread blocked on a full pipe;
        # without this the interpreter would wait for it forever at exit.
        for q in (*weights_qs, data_q):
            q.cancel_join_thread()
            q.close()
    return learner


def _log_row(cfg: TrainConfig, learner: Learner, window: dict, recent, elapsed: float) -> dict:
    dt = max(1e-9, time.monotonic() - window["t"])
    def mean(key: str) -> float:
        values = [x[key] for x in window["losses"] if not np.isnan(x[key])]
        return float(np.mean(values)) if values else float("nan")

    eps_stats = list(recent)
    return {
        "step": learner.step, "loss": mean("loss"), "l1": mean("l1"), "l2": mean("l2"),
        "epsilon": epsilon_at(cfg, learner.step),
        "success_rate": float(np.mean([s["success"] for s in eps_stats])) if eps_stats else float("nan"),
        "average_step": float(np.mean([s["steps"] for s in eps_stats])) if eps_stats else float("nan"),
        "samples_per_s": window["steps"] * cfg.batch_size / dt, "env_samples_per_s": window["env"] / dt,
        "agreement": mean("agreement"),
        "labelled_share": (sum(s["labelled"] for s in eps_stats) / max(1, sum(s["transitions"] for s in eps_stats))
                           if eps_stats else float("nan")),
        "team_cap": team_cap_at(cfg, learner.step),
        "mean_team": float(np.mean([s["n_agents"] for s in eps_stats])) if eps_stats else float("nan"),
        "episodes": learner.episode, "online_size": len(learner.online),
        "demo_size": len(learner.demo) if learner.demo else 0, "elapsed_s": round(learner.elapsed + elapsed, 1),
    }
