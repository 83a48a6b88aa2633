"""Solver protocol and registry of the evaluation harness (docs/ARCHITECTURE.md).

Every solver runs step by step through MapfEnv, so all metrics mean the same thing:
`reset(env)` once per case (planners plan here and may raise PlanFailed), then `act(obs)` each step.
Registry entries are "module:factory", imported only when asked for, so a missing optional package
(torch models, the native planners) does not break the others.
"""
from __future__ import annotations

import importlib
from typing import Protocol, runtime_checkable

import numpy as np

REGISTRY: dict[str, str] = {
    "greedy": "mapf_world.solvers.greedy:make_greedy",
    "odrmstar": "mapf_world.planners.solvers:make_odrmstar",
    "cbs": "mapf_world.planners.solvers:make_cbs",
    "hscl": "mapf_policy.solver:make_hscl",
    "hscl_no_self_attention": "mapf_policy.solver:make_hscl_ablation",
    "hscl_no_channel_attention": "mapf_policy.solver:make_hscl_ablation",
    "hscl_no_spatial_attention": "mapf_policy.solver:make_hscl_ablation",
}

PLAN_FAILED_REASONS = ("unsolvable", "timeout")


@runtime_checkable
class Solver(Protocol):
    name: str

    def reset(self, env) -> None:  # env: mapf_world.env.MapfEnv
        ...

    def act(self, obs: dict) -> np.ndarray:  # (N,) int actions
        ...


class PlanFailed(RuntimeError):
    """Raised by a planner's reset() (or act()) when it gives up; the harness records a failed case."""

    def __init__(self, reason: str, message: str = ""):
        if reason not in PLAN_FAILED_REASONS:
            raise ValueError(f"PlanFailed reason must be one of {PLAN_FAILED_REASONS}, got {reason!r}")
        self.reason = reason
        super().__init__(message or reason)


def check_options(solver: str, options: dict, known: tuple[str, ...] = ()) -> None:
    """For factories: unknown keyword options are an error, never silently ignored."""
    unknown = sorted(set(options) - set(known))
    if unknown:
        allowed = ", ".join(known) if known else "none"
        raise ValueError(f"solver {solver!r}: unknown option(s) {unknown} (accepted: {allowed})")


def get_solver(name: str, **options) -> Solver:
    """Build the registered solver `name`; the options go to its factory."""
    if name not in REGISTRY:
        raise ValueError(f"unknown solver {name!r}; known solvers: {', '.join(sorted(REGISTRY))}")
    module_name, _, factory_name = REGISTRY[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"solver {name!r} is registered as {REGISTRY[name]} but cannot be imported: {exc}") from exc
    factory = getattr(module, factory_name, None)
    if factory is None:
        raise ValueError(f"solver {name!r}: {module_name} has no factory {factory_name!r}")
    if factory_name == "make_hscl_ablation":
        # One factory serves the ablations; it learns which one from the registry name.
        return factory(variant=name, **options)
    return factory(**options)
