"""ctypes binding of the native planners (csrc/, built by setup.py as mapf_world/_native*.so).

The library is a plain shared library with a C ABI (csrc/api.cpp), not a Python extension
module: `mapf_plan` returns a result handle that is read with accessors and freed here. ctypes
releases the GIL during the call, so another thread can cancel a search through `cancel`.
Inputs are assumed checked (planners/inputs.py); the C++ side re-checks shapes and cells anyway.
"""
from __future__ import annotations

import ctypes
import importlib.machinery
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ODRMSTAR, CBS, ODRMSTAR_FREE_GOAL_WAIT, ODRMSTAR_GOAL_KEEPING = 0, 1, 2, 3  # algorithm codes of csrc/api.cpp
ABI_VERSION = 2
STATUS_NAMES = {0: "solved", 1: "unsolvable", 2: "timeout"}
STATUS_ERROR = 3

_LIB: ctypes.CDLL | None = None


def library_path() -> Path:
    """The built library next to the mapf_world package; FileNotFoundError if it is missing."""
    package_dir = Path(__file__).resolve().parent.parent
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = package_dir / f"_native{suffix}"
        if path.is_file():
            return path
    raise FileNotFoundError(
        f"the native planner library mapf_world/_native*.so is missing from {package_dir}: run scripts/setup"
    )


def library() -> ctypes.CDLL:
    global _LIB
    if _LIB is None:
        lib = ctypes.CDLL(str(library_path()))
        vp, i32, i64, f64 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_double
        lib.mapf_abi_version.restype = i32
        lib.mapf_plan.restype = vp
        lib.mapf_plan.argtypes = [i32, vp, i32, i32, i32, vp, vp, f64, f64, vp]
        for name, res in (("status", i32), ("steps", i32), ("sum_of_costs", i64), ("expansions", i64),
                          ("seconds", f64), ("message", ctypes.c_char_p)):
            fn = getattr(lib, f"mapf_result_{name}")
            fn.restype, fn.argtypes = res, [vp]
        lib.mapf_result_cells.restype, lib.mapf_result_cells.argtypes = None, [vp, vp]
        lib.mapf_result_free.restype, lib.mapf_result_free.argtypes = None, [vp]
        if lib.mapf_abi_version() != ABI_VERSION:
            raise RuntimeError(f"{library_path()} has ABI {lib.mapf_abi_version()}, expected {ABI_VERSION}: run scripts/setup")
        _LIB = lib
    return _LIB


@dataclass
class NativeResult:
    status: str  # 'solved' | 'unsolvable' | 'timeout'
    cells: np.ndarray | None  # (T+1, N) flat cells row * w + col, None unless solved
    sum_of_costs: int | None
    seconds: float
    expansions: int
    message: str


def run(algorithm: int, grid: np.ndarray, starts: np.ndarray, goals: np.ndarray, epsilon: float,
        time_limit: float, cancel: np.ndarray | None = None) -> NativeResult:
    """Plan with the native core. grid (H, W) uint8; starts, goals (N, 2) (row, col).

    cancel: optional int32 array of one element; setting it nonzero from another thread stops the
    search (reported as 'timeout'). A native error (bad input that got past the Python checks)
    raises ValueError with the C++ message.
    """
    lib = library()
    grid = np.ascontiguousarray(grid, dtype=np.uint8)
    s = np.ascontiguousarray(starts, dtype=np.int32)
    g = np.ascontiguousarray(goals, dtype=np.int32)
    n = s.shape[0]
    cancel_ptr = None
    if cancel is not None:
        if cancel.dtype != np.int32 or cancel.size != 1 or not cancel.flags.c_contiguous:
            raise ValueError("cancel must be a contiguous int32 array of one element")
        cancel_ptr = cancel.ctypes.data
    handle = lib.mapf_plan(algorithm, grid.ctypes.data, grid.shape[0], grid.shape[1], n, s.ctypes.data,
                           g.ctypes.data, float(epsilon), float(time_limit), cancel_ptr)
    if not handle:
        raise MemoryError("native planner: could not allocate a result")
    try:
        code = lib.mapf_result_status(handle)
        message = lib.mapf_result_message(handle).decode("utf-8", "replace")
        if code == STATUS_ERROR or code not in STATUS_NAMES:
            raise ValueError(f"native planner: {message}")
        cells = None
        soc = None
        if code == 0:
            steps = lib.mapf_result_steps(handle)
            cells = np.empty((steps + 1, n), dtype=np.int32)
            lib.mapf_result_cells(handle, cells.ctypes.data)
            soc = int(lib.mapf_result_sum_of_costs(handle))
        return NativeResult(STATUS_NAMES[code], cells, soc, float(lib.mapf_result_seconds(handle)),
                            int(lib.mapf_result_expansions(handle)), message)
    finally:
        lib.mapf_result_free(handle)
