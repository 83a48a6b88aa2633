"""Results of scripts/evaluate next to the seed paper's tables: a Markdown table and a two-panel picture.

`scripts/report OUT.json [OUT.json ...] [--markdown FILE.md] [--plot FILE.png]` reads JSON files written
by `scripts/evaluate --json` (any solvers, either benchmark variant), and prints, per benchmark variant,
one row per (agents, solver): our success rate, average step and mean sum of costs, the figure of the
solver's counterpart in the paper, and the difference (ours - paper). A second table lists every
reference figure. The variant (`dhc_40x40_d0.3` or `dcc_40x40_d0.3`) is read from the instance path
recorded in the JSON (`files[k].file`); `--variant` names it for files whose path does not.

The module is pure apart from `plot_comparison` (matplotlib, Agg backend, imported on use).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

# --- reference figures --------------------------------------------------------------------------
#: Team sizes of the benchmark and of the paper's tables.
AGENTS: Tuple[int, ...] = (4, 8, 16, 32, 64)

#: Benchmark variants the reference figures are about (directory names under the benchmark dir).
VARIANTS: Tuple[str, ...] = ("dhc_40x40_d0.3", "dcc_40x40_d0.3")

PAPER = "Chen et al., IEEE TIE 2023 (HSCL), Tables II and III"

#: Average step (lower is better) for 4, 8, 16, 32, 64 agents: the seed paper's Table II, copied from
#: /work/shared/benchmarks/dhc_40x40_d0.3/README.md. The paper says it used DHC's test set; the DCC
#: README explains why its 4..32-agent figures may come from the DCC variant instead.
PAPER_AVERAGE_STEP: Dict[str, Tuple[float, ...]] = {
    "ODrM* (eps=10)": (47.86, 55.47, 61.89, 66.94, 85.27),
    "HSCL (paper)": (47.86, 56.41, 62.84, 75.07, 104.47),
    "DCC": (48.575, 59.6, 71.34, 93.54, 135.55),
    "DHC": (52.33, 63.9, 79.63, 100.1, 147.26),
    "PRIMAL": (79.08, 76.53, 107.14, 155.21, 170.48),
}

#: Success rate (higher is better) for 4, 8, 16, 32, 64 agents: the paper's method and its ablations
#: (Table III).
PAPER_SUCCESS_RATE: Dict[str, Tuple[float, ...]] = {
    "HSCL (paper)": (1.0, 0.995, 0.995, 0.955, 0.845),
    "HSCL w/o self-attention": (1.0, 0.99, 0.985, 0.94, 0.82),
    "HSCL w/o channel attention": (1.0, 0.995, 0.995, 0.95, 0.83),
    "HSCL w/o spatial attention": (1.0, 0.995, 0.995, 0.955, 0.835),
}

#: The project issue's C++ ODrM* reference run on this machine, on the DHC variant (its 4-agent average
#: step, 49.74, is consistent with that file's makespan lower bound 49.5 and not with the DCC file's
#: 47.6): cases solved out of 200 and average step for 4, 8, 16, 32, 64 agents.
CPP_ODRMSTAR = "C++ ODrM* (issue's run)"
CPP_ODRMSTAR_VARIANT = "dhc_40x40_d0.3"
CPP_ODRMSTAR_SOLVED: Tuple[int, ...] = (200, 200, 200, 200, 196)
CPP_ODRMSTAR_CASES = 200
CPP_ODRMSTAR_AVERAGE_STEP: Tuple[float, ...] = (49.74, 54.91, 61.74, 67.46, 81.60)

#: Mean over cases of the longest single-agent shortest path (benchmark READMEs): no run can average
#: fewer steps than this on the full file.
MAKESPAN_LOWER_BOUND: Dict[str, Tuple[float, ...]] = {
    "dhc_40x40_d0.3": (49.5, 54.4, 60.2, 64.2, 67.2),
    "dcc_40x40_d0.3": (47.6, 55.0, 60.6, 63.5, 67.2),
}

#: The paper's counterpart of each registered solver (a key of PAPER_SUCCESS_RATE and/or
#: PAPER_AVERAGE_STEP); solvers not listed are compared with the paper's method.
COUNTERPART: Dict[str, str] = {
    "odrmstar": "ODrM* (eps=10)",
    "hscl": "HSCL (paper)",
    "hscl_no_self_attention": "HSCL w/o self-attention",
    "hscl_no_channel_attention": "HSCL w/o channel attention",
    "hscl_no_spatial_attention": "HSCL w/o spatial attention",
}
DEFAULT_COUNTERPART = "HSCL (paper)"
PAPER_MAX_STEPS = 256
FULL_CASES = 200  # cases per team size in the benchmark files and the paper


def reference_success(name: str, agents: int) -> Optional[float]:
    """The paper's success rate of `name` at `agents`, None where the paper gives none."""
    series = PAPER_SUCCESS_RATE.get(name)
    return series[AGENTS.index(agents)] if series is not None and agents in AGENTS else None


def reference_average_step(name: str, agents: int) -> Optional[float]:
    """The paper's average step of `name` at `agents`, None where the paper gives none."""
    series = PAPER_AVERAGE_STEP.get(name)
    return series[AGENTS.index(agents)] if series is not None and agents in AGENTS else None


# --- loading ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One file row of one evaluate JSON: one solver on one instances file."""

    source: str  # the JSON file
    instances: str  # the .npz path recorded in the JSON
    variant: Optional[str]  # a name from VARIANTS, or None when the path names none
    solver: str  # registered name
    label: str  # solver plus its options, e.g. "odrmstar (epsilon=10.0)"
    agents: int
    cases: int
    max_steps: int
    success_rate: float
    average_step: float
    mean_sum_of_costs: float


def detect_variant(instances_path: str) -> Optional[str]:
    """The known benchmark variant named by a directory of the path (the last one), else None."""
    found = [part for part in Path(instances_path).parts if part in VARIANTS]
    return found[-1] if found else None


def _label(solver: str, options: dict) -> str:
    if not options:
        return solver
    shown = []
    for key in sorted(options):
        value = str(options[key])
        if "/" in value:  # a path (model weights): its file name is enough to tell runs apart
            value = Path(value).name
        shown.append(f"{key}={value}")
    return f"{solver} ({', '.join(shown)})"


def _need(obj: dict, key: str, where: str):
    if key not in obj:
        raise ValueError(f"{where}: not a scripts/evaluate JSON: missing key {key!r}")
    return obj[key]


def _integer(value, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{where} must be an integer >= {minimum}, got {value!r}")
    return value


def _number(value, where: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (low <= value <= high):
        raise ValueError(f"{where} must be a number in [{low}, {high}], got {value!r}")
    return float(value)


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def parse_evaluation(data, source: str, variant: Optional[str] = None) -> List[Entry]:
    """Check the layout written by scripts/evaluate and return its file rows as entries.

    `variant` is used for rows whose instance path names no known variant. Each row's summary must
    agree with its per-case results (when they are there).
    """
    if not isinstance(data, dict):
        raise ValueError(f"{source}: not a scripts/evaluate JSON: the top level is a {type(data).__name__}, "
                         "not an object")
    solver = _need(data, "solver", source)
    if not isinstance(solver, str) or not solver:
        raise ValueError(f"{source}: 'solver' must be a non-empty string, got {solver!r}")
    options = data.get("options", {})
    if not isinstance(options, dict):
        raise ValueError(f"{source}: 'options' must be an object, got {options!r}")
    max_steps = _integer(_need(data, "max_steps", source), f"{source}: 'max_steps'", 1)
    files = _need(data, "files", source)
    if not isinstance(files, list) or not files:
        raise ValueError(f"{source}: 'files' must be a non-empty list, got {files!r}")
    label = _label(solver, options)
    entries = []
    for k, row in enumerate(files):
        where = f"{source}: files[{k}]"
        if not isinstance(row, dict):
            raise ValueError(f"{where}: not a scripts/evaluate JSON: a file row must be an object")
        instances = _need(row, "file", where)
        if not isinstance(instances, str):
            raise ValueError(f"{where}: 'file' must be a string, got {instances!r}")
        if row.get("solver", solver) != solver:
            raise ValueError(f"{where}: solver {row['solver']!r} differs from the file's solver {solver!r}")
        agents = _integer(_need(row, "agents", where), f"{where}: 'agents'", 1)
        cases = _integer(_need(row, "cases", where), f"{where}: 'cases'", 1)
        success = _number(_need(row, "success_rate", where), f"{where}: 'success_rate'", 0.0, 1.0)
        average = _number(_need(row, "average_step", where), f"{where}: 'average_step'", 0.0, max_steps)
        soc = _number(_need(row, "mean_sum_of_costs", where), f"{where}: 'mean_sum_of_costs'", 0.0)
        results = row.get("results")
        if results is not None:
            if not isinstance(results, list) or len(results) != cases:
                raise ValueError(f"{where}: 'results' must list {cases} cases (its 'cases'), got "
                                 f"{len(results) if isinstance(results, list) else results!r}")
            try:
                steps = [float(r["steps"]) for r in results]
                solved = [bool(r["success"]) for r in results]
                costs = [float(r["sum_of_costs"]) for r in results]
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{where}: a per-case result lacks steps/success/sum_of_costs ({exc!r})") from None
            for key, mine, recomputed in (("success_rate", success, sum(solved) / cases),
                                          ("average_step", average, sum(steps) / cases),
                                          ("mean_sum_of_costs", soc, sum(costs) / cases)):
                if not _close(mine, recomputed):
                    raise ValueError(f"{where}: {key!r} is {mine} but its per-case results give {recomputed}")
        entries.append(Entry(source, instances, detect_variant(instances) or variant, solver, label, agents,
                             cases, max_steps, success, average, soc))
    return entries


def load_evaluation(path, variant: Optional[str] = None) -> List[Entry]:
    """Read one JSON file written by scripts/evaluate --json (see parse_evaluation)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a scripts/evaluate JSON: not valid JSON ({exc})") from None
    return parse_evaluation(data, str(path), variant)


def parse_labels(specs: Sequence[str], paths: Sequence) -> Dict[str, str]:
    """{JSON path: label} from "PATH=LABEL" strings; PATH must be one of `paths`."""
    known = {str(Path(p)) for p in paths}
    labels: Dict[str, str] = {}
    for spec in specs:
        path, sep, label = spec.partition("=")
        if not sep or not label.strip():
            raise ValueError(f"--label {spec!r}: expected EVAL.json=LABEL")
        if str(Path(path)) not in known:
            raise ValueError(f"--label {spec!r}: {path} is not one of the JSON files given")
        labels[str(Path(path))] = label.strip()
    return labels


def load_evaluations(paths: Sequence, variant: Optional[str] = None,
                     labels: Optional[Dict[str, str]] = None) -> List[Entry]:
    """Entries of several JSON files; the same solver, variant and team size twice is an error. `labels`
    ({path: text}) replaces the label made from a file's solver and options."""
    if variant is not None and variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; known variants: {', '.join(VARIANTS)}")
    entries: List[Entry] = []
    seen: Dict[tuple, Entry] = {}
    for path in paths:
        for e in load_evaluation(path, variant):
            if labels and str(Path(path)) in labels:
                e = dataclasses.replace(e, label=labels[str(Path(path))])
            key = (e.variant, e.label, e.agents)
            if key in seen:
                other = seen[key]
                raise ValueError(f"{e.label} with {e.agents} agents on {e.variant or 'an unknown variant'} "
                                 f"appears twice: {other.source} ({other.instances}) and {e.source} "
                                 f"({e.instances})")
            seen[key] = e
            entries.append(e)
    if not entries:
        raise ValueError("no evaluate JSON files given")
    return entries


# --- comparison ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Comparison:
    """One row of the table: our entry next to its counterpart's figures (None where none)."""

    entry: Entry
    reference: Optional[str]  # counterpart name; None when the variant is unknown
    ref_success_rate: Optional[float]
    ref_average_step: Optional[float]

    @property
    def success_diff(self) -> Optional[float]:
        return None if self.ref_success_rate is None else self.entry.success_rate - self.ref_success_rate

    @property
    def average_step_diff(self) -> Optional[float]:
        return None if self.ref_average_step is None else self.entry.average_step - self.ref_average_step


def counterpart(solver: str) -> str:
    return COUNTERPART.get(solver, DEFAULT_COUNTERPART)


def build_comparison(entries: Sequence[Entry]) -> Dict[Optional[str], List[Comparison]]:
    """Rows grouped by variant (known variants in VARIANTS order, then unknown), sorted by agents and
    then by the order in which the solvers first appear."""
    order = {}
    for e in entries:
        order.setdefault(e.label, len(order))
    groups: Dict[Optional[str], List[Comparison]] = {}
    variants = [v for v in VARIANTS if any(e.variant == v for e in entries)]
    if any(e.variant is None for e in entries):
        variants.append(None)
    for v in variants:
        rows = []
        for e in sorted((e for e in entries if e.variant == v), key=lambda e: (e.agents, order[e.label])):
            if v is None:
                rows.append(Comparison(e, None, None, None))
                continue
            name = counterpart(e.solver)
            rows.append(Comparison(e, name, reference_success(name, e.agents), reference_average_step(name, e.agents)))
        groups[v] = rows
    return groups


# --- Markdown -----------------------------------------------------------------------------------
DASH = "—"


def _fmt(value: Optional[float], digits: int, signed: bool = False) -> str:
    if value is None:
        return DASH
    if signed and _close(value, 0.0):
        value = 0.0  # no "-0.00"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"


def _table(header: Sequence[str], align: Sequence[str], rows: Sequence[Sequence[str]]) -> List[str]:
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


COMPARISON_HEADER = ("agents", "solver", "cases", "success", "avg step", "mean SoC", "paper counterpart",
                     "paper success", "Δ success", "paper avg step", "Δ avg step")


def variant_title(variant: Optional[str]) -> str:
    return variant if variant is not None else "unknown benchmark variant"


def render_markdown(entries: Sequence[Entry]) -> str:
    """The whole report: per variant our rows next to the paper's, then the reference figures."""
    groups = build_comparison(entries)
    out = [f"# MAPF results next to the paper ({PAPER})", ""]
    for variant, rows in groups.items():
        out += [f"## {variant_title(variant)}", ""]
        if variant is None:
            sources = sorted({c.entry.instances for c in rows})
            out += [f"The instance paths ({', '.join(sources)}) name none of {', '.join(VARIANTS)}, so there "
                    "is nothing of the paper's to compare with (name the variant with --variant).", ""]
        else:
            out += ["Ours from scripts/evaluate; paper: the figure of the solver's counterpart (solvers without "
                    f"one are set against {DEFAULT_COUNTERPART}). Δ = ours − paper; success: higher is better, "
                    f"average step (a failed case counts max-steps): lower is better. {DASH}: not in the paper.",
                    ""]
        table_rows = []
        for c in rows:
            e = c.entry
            table_rows.append([str(e.agents), e.label, str(e.cases), _fmt(e.success_rate, 3),
                               _fmt(e.average_step, 2), _fmt(e.mean_sum_of_costs, 1), c.reference or DASH,
                               _fmt(c.ref_success_rate, 3), _fmt(c.success_diff, 3, signed=True),
                               _fmt(c.ref_average_step, 2), _fmt(c.average_step_diff, 2, signed=True)])
        out += _table(COMPARISON_HEADER, "rlrrrrlrrrr", table_rows)
        notes = []
        partial: Dict[str, List[str]] = {}
        for c in rows:
            if c.entry.cases < FULL_CASES:
                partial.setdefault(c.entry.label, []).append(f"{c.entry.cases} ({c.entry.agents} agents)")
        if partial:
            notes.append(f"Fewer than the benchmark's {FULL_CASES} cases per file (ours is over the first cases "
                         "only, the paper's over all): "
                         + "; ".join(f"{label}: {', '.join(counts)}" for label, counts in partial.items()) + ".")
        other_limit = sorted({(c.entry.label, c.entry.max_steps) for c in rows if c.entry.max_steps != PAPER_MAX_STEPS})
        if other_limit:
            notes.append(f"The paper's episodes end at {PAPER_MAX_STEPS} steps; other limits here: "
                         + ", ".join(f"{label} {limit}" for label, limit in other_limit) + ".")
        if variant == "dcc_40x40_d0.3":
            notes.append("The paper says it used DHC's test set; its 4- to 32-agent average steps may come from "
                         "this DCC variant (see the benchmark README).")
        if notes:
            out += [""] + [f"- {n}" for n in notes]
        out.append("")
    out += render_reference_tables([v for v in groups if v is not None])
    return "\n".join(out).rstrip("\n") + "\n"


def render_reference_tables(variants: Sequence[str]) -> List[str]:
    """All reference figures per team size: the paper's (both tables), the C++ ODrM* run and lower bounds."""
    if not variants:
        return []
    header = ["agents"] + [f"avg step {name}" for name in PAPER_AVERAGE_STEP] + \
             [f"success {name}" for name in PAPER_SUCCESS_RATE]
    align = "r" * len(header)
    with_cpp = CPP_ODRMSTAR_VARIANT in variants
    if with_cpp:
        header += [f"{CPP_ODRMSTAR} solved", f"{CPP_ODRMSTAR} avg step"]
        align += "rr"
    header += [f"makespan LB {v}" for v in variants]
    align += "r" * len(variants)
    rows = []
    for k, n in enumerate(AGENTS):
        row = [str(n)] + [_fmt(s[k], 3 if name == "DCC" else 2) for name, s in PAPER_AVERAGE_STEP.items()]
        row += [_fmt(s[k], 3) for s in PAPER_SUCCESS_RATE.values()]
        if with_cpp:
            row += [f"{CPP_ODRMSTAR_SOLVED[k]}/{CPP_ODRMSTAR_CASES}", _fmt(CPP_ODRMSTAR_AVERAGE_STEP[k], 2)]
        row += [_fmt(MAKESPAN_LOWER_BOUND[v][k], 1) for v in variants]
        rows.append(row)
    lines = ["## Reference figures", "",
             f"Paper: {PAPER} (benchmark: 40x40 grids, obstacle density 0.3, 200 cases per team size). "
             + (f"{CPP_ODRMSTAR}: the project issue's reference run on {CPP_ODRMSTAR_VARIANT}. " if with_cpp else "")
             + "Makespan LB: mean over cases of the longest single-agent shortest path (benchmark README).", ""]
    return lines + _table(header, align, rows) + [""]


# --- picture ------------------------------------------------------------------------------------
def plot_comparison(entries: Sequence[Entry], out_path) -> Path:
    """Two panels per variant (success rate, average step vs agents): ours solid, the paper dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = build_comparison(entries)
    variants = list(groups)
    fig, axes = plt.subplots(len(variants), 2, figsize=(13, 6.4 * len(variants)), squeeze=False)
    ours_colors = ["#d62728", "#1f4fd8", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]
    paper_colors = {"ODrM* (eps=10)": "#555555", "HSCL (paper)": "#b8860b", "DCC": "#20a0a0", "DHC": "#7f5fbf",
                    "PRIMAL": "#a0522d", "HSCL w/o self-attention": "#6b8e23",
                    "HSCL w/o channel attention": "#4682b4", "HSCL w/o spatial attention": "#c71585"}
    labels = list(dict.fromkeys(e.label for e in entries))
    color_of = {label: ours_colors[k % len(ours_colors)] for k, label in enumerate(labels)}
    for r, variant in enumerate(variants):
        ax_s, ax_a = axes[r]
        rows = groups[variant]
        # The paper's figures: dashed and faint, behind ours.
        if variant is not None:
            for name, series in PAPER_SUCCESS_RATE.items():
                ax_s.plot(AGENTS, series, "--", marker="s", ms=3, lw=1.2, alpha=0.5, color=paper_colors[name],
                          label=f"paper: {name}", zorder=1)
            for name, series in PAPER_AVERAGE_STEP.items():
                ax_a.plot(AGENTS, series, "--", marker="s", ms=3, lw=1.2, alpha=0.5, color=paper_colors[name],
                          label=f"paper: {name}", zorder=1)
            if variant == CPP_ODRMSTAR_VARIANT:
                solved = [s / CPP_ODRMSTAR_CASES for s in CPP_ODRMSTAR_SOLVED]
                for ax, series in ((ax_s, solved), (ax_a, CPP_ODRMSTAR_AVERAGE_STEP)):
                    ax.plot(AGENTS, series, ":", marker="^", ms=4, lw=1.5, alpha=0.7, color="black",
                            label=CPP_ODRMSTAR, zorder=1)
            ax_a.plot(AGENTS, MAKESPAN_LOWER_BOUND[variant], "-", lw=4, alpha=0.15, color="black",
                      label=f"makespan lower bound (all {FULL_CASES} cases)", zorder=0)
        # Ours: solid, on top.
        for label in labels:
            mine = [c.entry for c in rows if c.entry.label == label]
            if not mine:
                continue
            xs = [e.agents for e in mine]
            partial = any(e.cases < FULL_CASES for e in mine)
            name = f"ours: {label}" + (" (partial)" if partial else "")
            ax_s.plot(xs, [e.success_rate for e in mine], "-o", lw=2.2, ms=6, color=color_of[label], label=name,
                      zorder=3)
            ax_a.plot(xs, [e.average_step for e in mine], "-o", lw=2.2, ms=6, color=color_of[label], label=name,
                      zorder=3)
        xs_all = sorted(set(AGENTS if variant is not None else ()) | {c.entry.agents for c in rows})
        for ax in (ax_s, ax_a):
            ax.set_xscale("log", base=2)
            ax.set_xticks(xs_all)
            ax.set_xticklabels([str(x) for x in xs_all])
            ax.minorticks_off()
            ax.set_xlabel("agents")
            ax.grid(True, alpha=0.3)
        ax_s.set_ylim(-0.03, 1.03)
        ax_s.set_ylabel("success rate (higher is better)")
        ax_s.set_title(f"Success rate — {variant_title(variant)}")
        ax_a.set_ylabel("average step, failed case = max-steps (lower is better)")
        ax_a.set_title(f"Average step — {variant_title(variant)}")
        limits = sorted({c.entry.max_steps for c in rows})
        for limit in limits:
            ax_a.axhline(limit, color="black", lw=0.8, alpha=0.4, zorder=0)
            ax_a.annotate(f"max-steps {limit}: all cases failed", (0.01, limit), xycoords=("axes fraction", "data"),
                          xytext=(0, -10), textcoords="offset points", fontsize=7, alpha=0.6)
        for ax in (ax_s, ax_a):  # below the panel, never over the lines
            ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    names = ", ".join(variant_title(v) for v in variants)
    fig.suptitle(f"Ours (solid) vs. the paper (dashed) on {names}", fontsize=13)
    fig.tight_layout()
    out_path = Path(out_path)
    fig.savefig(out_path, dpi=110)
    plt.close(fig)
    return out_path


# --- command line -------------------------------------------------------------------------------
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="scripts/report",
        description="Put scripts/evaluate results next to the seed paper's Tables II and III: a Markdown "
                    "table on stdout and, with --plot, a two-panel picture.",
        epilog=f"Variants: {', '.join(VARIANTS)} (read from the instance paths in the JSON). Solvers are set "
               "against their counterpart in the paper: " + ", ".join(f"{s} -> {n}" for s, n in COUNTERPART.items())
               + f"; any other -> {DEFAULT_COUNTERPART}.",
    )
    p.add_argument("json", nargs="+", type=Path, metavar="EVAL.json", help="files written by scripts/evaluate --json")
    p.add_argument("--markdown", type=Path, default=None, metavar="FILE.md", help="also write the table here")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE.png", help="write the two-panel picture here")
    p.add_argument("--variant", default=None, choices=VARIANTS,
                   help="benchmark variant of files whose instance path names none")
    p.add_argument("--label", action="append", default=[], metavar="EVAL.json=LABEL",
                   help="name a file's rows LABEL instead of its solver and options (repeatable)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        entries = load_evaluations(args.json, args.variant, parse_labels(args.label, args.json))
        if args.plot is not None and args.plot.suffix.lower() != ".png":
            raise ValueError(f"--plot {args.plot}: the picture is a PNG; name it *.png")
        text = render_markdown(entries)
        if args.markdown is not None:
            args.markdown.write_text(text)
        if args.plot is not None:
            plot_comparison(entries, args.plot)
    except (ValueError, OSError) as exc:
        print(f"report: error: {exc}", file=sys.stderr)
        return 2
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
