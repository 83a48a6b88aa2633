"""Centralized planners: ODrM* (the expert) and CBS (a baseline), plus the expert oracle.

The searches are C++ (csrc/, loaded with ctypes by planners/native.py); this package checks
inputs, validates every plan before returning it and adapts the planners to the harness.
"""
from mapf_world.planners.cbs import plan_cbs
from mapf_world.planners.expert import ExpertOracle
from mapf_world.planners.odrmstar import plan_odrmstar
from mapf_world.planners.result import PlanResult, plan_actions

__all__ = ["ExpertOracle", "PlanResult", "plan_actions", "plan_cbs", "plan_odrmstar"]
