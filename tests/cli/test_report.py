"""scripts/report: evaluate JSONs next to the paper's tables (Markdown and a two-panel PNG)."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from mapf_world import report
from mapf_world.report import (
    AGENTS,
    PAPER_AVERAGE_STEP,
    PAPER_SUCCESS_RATE,
    build_comparison,
    detect_variant,
    load_evaluation,
    load_evaluations,
    plot_comparison,
    render_markdown,
)

DHC = "/bench/dhc_40x40_d0.3"
DCC = "/bench/dcc_40x40_d0.3"


def _case(steps, success, soc):
    return {"index": 0, "steps": steps, "success": success, "sum_of_costs": soc, "failed_moves": 0,
            "reason": None if success else "max_steps", "seconds": 0.01}


def _file_row(path, agents, cases):
    """A file row as scripts/evaluate writes it, its summary computed from `cases`."""
    return {"file": path, "solver": "x", "agents": agents, "cases": len(cases),
            "success_rate": sum(c["success"] for c in cases) / len(cases),
            "average_step": float(np.mean([c["steps"] for c in cases])),
            "mean_sum_of_costs": float(np.mean([c["sum_of_costs"] for c in cases])),
            "wall_time_s": 0.5, "results": cases}


def _evaluation(solver, rows, options=None, max_steps=256):
    for row in rows:
        row["solver"] = solver
    return {"solver": solver, "options": options or {}, "max_steps": max_steps, "files": rows}


def _write(path, data):
    path.write_text(json.dumps(data))
    return path


def _tables(markdown: str) -> dict:
    """{section title: [row dict, ...]} for the first table under each '## ' heading."""
    out, section, header = {}, None, None
    for line in markdown.splitlines():
        if line.startswith("## "):
            section, header = line[3:].strip(), None
            out[section] = []
        elif line.startswith("|") and section is not None and header != "done":
            cells = [c.strip() for c in line.strip("|").split("|")]
            if header is None:
                header = cells
            elif not set("".join(cells)) <= set("-:"):
                out[section].append(dict(zip(header, cells)))
        elif section is not None and header is not None and out[section] and not line.startswith("|"):
            header = "done"  # only the first table of a section
    return out


# --- unit: the comparison on hand-written JSON ----------------------------------------------------
def test_variant_detection():
    assert detect_variant("/x/dhc_40x40_d0.3/agents_04.npz") == "dhc_40x40_d0.3"
    assert detect_variant("../shared/benchmarks/dcc_40x40_d0.3/agents_64.npz") == "dcc_40x40_d0.3"
    assert detect_variant("tests/fixtures/tiny.npz") is None
    assert detect_variant("/x/dhc_40x40_d0.3_copy/agents_04.npz") is None  # a whole directory name only


def test_comparison_on_hand_written_json(tmp_path):
    hscl = _evaluation("hscl", [
        _file_row(f"{DHC}/agents_04.npz", 4, [_case(40, True, 100), _case(256, False, 600)]),
        _file_row(f"{DHC}/agents_08.npz", 8, [_case(50, True, 300)] * 4),
        _file_row(f"{DHC}/agents_12.npz", 12, [_case(60, True, 500)]),  # a team size the paper lacks
    ], options={"model": "models/best/hscl.pt"})
    odr = _evaluation("odrmstar", [_file_row(f"{DCC}/agents_64.npz", 64, [_case(90, True, 4000)] * 3)],
                      options={"epsilon": "10.0"})
    greedy = _evaluation("greedy", [_file_row("/elsewhere/agents_04.npz", 4, [_case(70, True, 200)])])
    entries = load_evaluations([_write(tmp_path / "hscl.json", hscl), _write(tmp_path / "odr.json", odr),
                                _write(tmp_path / "greedy.json", greedy)])
    groups = build_comparison(entries)
    assert list(groups) == ["dhc_40x40_d0.3", "dcc_40x40_d0.3", None]

    four, eight, twelve = groups["dhc_40x40_d0.3"]
    assert four.entry.label == "hscl (model=hscl.pt)" and four.entry.agents == 4
    assert four.reference == "HSCL (paper)"
    assert four.entry.success_rate == 0.5 and four.ref_success_rate == 1.0
    assert four.success_diff == pytest.approx(-0.5)
    assert four.entry.average_step == 148.0 and four.ref_average_step == 47.86
    assert four.average_step_diff == pytest.approx(148.0 - 47.86)
    assert four.entry.mean_sum_of_costs == 350.0
    assert eight.ref_success_rate == 0.995 and eight.ref_average_step == 56.41
    assert eight.success_diff == pytest.approx(0.005) and eight.average_step_diff == pytest.approx(50 - 56.41)
    assert twelve.reference == "HSCL (paper)" and twelve.ref_success_rate is None and twelve.success_diff is None

    (sixty_four,) = groups["dcc_40x40_d0.3"]
    assert sixty_four.reference == "ODrM* (eps=10)"
    assert sixty_four.ref_success_rate is None  # the paper gives no success rate for ODrM*
    assert sixty_four.ref_average_step == 85.27 and sixty_four.average_step_diff == pytest.approx(90 - 85.27)

    (unknown,) = groups[None]
    assert unknown.reference is None and unknown.average_step_diff is None

    tables = _tables(render_markdown(entries))
    rows = tables["dhc_40x40_d0.3"]
    assert [r["agents"] for r in rows] == ["4", "8", "12"]
    assert rows[0] == {"agents": "4", "solver": "hscl (model=hscl.pt)", "cases": "2", "success": "0.500",
                       "avg step": "148.00", "mean SoC": "350.0", "paper counterpart": "HSCL (paper)",
                       "paper success": "1.000", "Δ success": "-0.500", "paper avg step": "47.86",
                       "Δ avg step": "+100.14"}
    assert rows[1]["Δ success"] == "+0.005" and rows[1]["Δ avg step"] == "-6.41"
    assert rows[2]["paper success"] == "—" and rows[2]["Δ avg step"] == "—"
    assert tables["dcc_40x40_d0.3"][0]["solver"] == "odrmstar (epsilon=10.0)"
    assert tables["dcc_40x40_d0.3"][0]["paper avg step"] == "85.27"
    assert tables["unknown benchmark variant"][0]["paper counterpart"] == "—"
    reference = tables["Reference figures"]
    assert [int(r["agents"]) for r in reference] == list(AGENTS)
    assert [float(r["avg step PRIMAL"]) for r in reference] == list(PAPER_AVERAGE_STEP["PRIMAL"])
    assert [float(r["success HSCL w/o self-attention"]) for r in reference] == \
        list(PAPER_SUCCESS_RATE["HSCL w/o self-attention"])
    assert reference[-1]["C++ ODrM* (issue's run) solved"] == "196/200"

    # --variant names the variant of the file whose path does not tell.
    (forced,) = load_evaluations([tmp_path / "greedy.json"], variant="dcc_40x40_d0.3")
    assert forced.variant == "dcc_40x40_d0.3"
    (row,) = build_comparison([forced])["dcc_40x40_d0.3"]
    assert row.ref_average_step == 47.86 and row.average_step_diff == pytest.approx(70 - 47.86)


def test_the_reference_constants_match_the_paper():
    # Tables II and III of the seed paper (as in the benchmark README) and the C++ ODrM* run.
    assert AGENTS == (4, 8, 16, 32, 64)
    assert PAPER_AVERAGE_STEP == {
        "ODrM* (eps=10)": (47.86, 55.47, 61.89, 66.94, 85.27),
        "HSCL (paper)": (47.86, 56.41, 62.84, 75.07, 104.47),
        "DCC": (48.575, 59.6, 71.34, 93.54, 135.55),
        "DHC": (52.33, 63.9, 79.63, 100.1, 147.26),
        "PRIMAL": (79.08, 76.53, 107.14, 155.21, 170.48),
    }
    assert PAPER_SUCCESS_RATE == {
        "HSCL (paper)": (1.0, 0.995, 0.995, 0.955, 0.845),
        "HSCL w/o self-attention": (1.0, 0.99, 0.985, 0.94, 0.82),
        "HSCL w/o channel attention": (1.0, 0.995, 0.995, 0.95, 0.83),
        "HSCL w/o spatial attention": (1.0, 0.995, 0.995, 0.955, 0.835),
    }
    assert report.CPP_ODRMSTAR_SOLVED == (200, 200, 200, 200, 196) and report.CPP_ODRMSTAR_CASES == 200
    assert report.CPP_ODRMSTAR_AVERAGE_STEP == (49.74, 54.91, 61.74, 67.46, 81.60)


def test_plot_of_hand_written_json_without_a_known_variant(tmp_path):
    data = _evaluation("greedy", [_file_row("/elsewhere/agents_04.npz", 4, [_case(70, True, 200)])])
    out = plot_comparison(load_evaluation(_write(tmp_path / "g.json", data)), tmp_path / "g.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- errors -----------------------------------------------------------------------------------------
def test_files_that_are_not_evaluate_json(tmp_path):
    good = _evaluation("greedy", [_file_row(f"{DHC}/agents_04.npz", 4, [_case(40, True, 100)])])
    (tmp_path / "nope.json").write_text("agents,steps\n4,40\n")
    with pytest.raises(ValueError, match=r"nope\.json: not a scripts/evaluate JSON: not valid JSON"):
        load_evaluation(tmp_path / "nope.json")
    with pytest.raises(ValueError, match=r"list\.json: not a scripts/evaluate JSON: the top level is a list"):
        load_evaluation(_write(tmp_path / "list.json", [1, 2]))
    with pytest.raises(ValueError, match=r"other\.json: not a scripts/evaluate JSON: missing key 'solver'"):
        load_evaluation(_write(tmp_path / "other.json", {"name": "a training log", "loss": [1.0, 0.5]}))
    no_files = dict(good, files=[])
    with pytest.raises(ValueError, match=r"'files' must be a non-empty list"):
        load_evaluation(_write(tmp_path / "a.json", no_files))
    no_agents = json.loads(json.dumps(good))
    del no_agents["files"][0]["agents"]
    with pytest.raises(ValueError, match=r"b\.json: files\[0\]: not a scripts/evaluate JSON: missing key 'agents'"):
        load_evaluation(_write(tmp_path / "b.json", no_agents))
    bad_rate = json.loads(json.dumps(good))
    bad_rate["files"][0]["success_rate"] = 1.5
    with pytest.raises(ValueError, match=r"files\[0\]: 'success_rate' must be a number in \[0.0, 1.0\], got 1.5"):
        load_evaluation(_write(tmp_path / "c.json", bad_rate))
    disagrees = json.loads(json.dumps(good))
    disagrees["files"][0]["average_step"] = 41.0
    with pytest.raises(ValueError, match=r"'average_step' is 41.0 but its per-case results give 40.0"):
        load_evaluation(_write(tmp_path / "d.json", disagrees))
    with pytest.raises(ValueError, match=r"missing\.json: cannot read"):
        load_evaluation(tmp_path / "missing.json")
    _write(tmp_path / "good.json", good)
    with pytest.raises(ValueError, match=r"greedy with 4 agents on dhc_40x40_d0.3 appears twice"):
        load_evaluations([tmp_path / "good.json", tmp_path / "good.json"])
    with pytest.raises(ValueError, match=r"unknown variant 'dhc'"):
        load_evaluations([tmp_path / "good.json"], variant="dhc")


def test_cli_errors(repo_root, tmp_path):
    script = str(repo_root / "scripts" / "report")
    (tmp_path / "log.json").write_text(json.dumps({"loss": [0.3, 0.2]}))
    proc = subprocess.run([script, str(tmp_path / "log.json")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert "log.json: not a scripts/evaluate JSON: missing key 'solver'" in proc.stderr
    good = _evaluation("greedy", [_file_row(f"{DHC}/agents_04.npz", 4, [_case(40, True, 100)])])
    _write(tmp_path / "good.json", good)
    proc = subprocess.run([script, str(tmp_path / "good.json"), "--plot", str(tmp_path / "x.pdf")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "name it *.png" in proc.stderr
    assert not (tmp_path / "x.pdf").exists()


def test_cli_labels_name_a_file_s_rows(repo_root, tmp_path):
    script = str(repo_root / "scripts" / "report")
    rows = lambda: [_file_row(f"{DHC}/agents_04.npz", 4, [_case(40, True, 100)])]  # noqa: E731
    a = _write(tmp_path / "a.json", _evaluation("hscl", rows(), options={"action_temperature": "0.04"}))
    b = _write(tmp_path / "b.json", _evaluation("hscl", rows()))
    proc = subprocess.run([script, str(a), str(b), "--label", f"{a}=hscl, fourth-session rule"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    solvers = [r["solver"] for r in _tables(proc.stdout)["dhc_40x40_d0.3"]]
    assert solvers == ["hscl, fourth-session rule", "hscl"]
    for spec, message in ((f"{tmp_path / 'c.json'}=x", "is not one of the JSON files given"),
                          (str(a), "expected EVAL.json=LABEL"), (f"{a}= ", "expected EVAL.json=LABEL")):
        bad = subprocess.run([script, str(a), "--label", spec], capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and message in bad.stderr, bad.stderr
    # Two files under one label with the same team size would make one row ambiguous: refused.
    same = subprocess.run([script, str(a), str(b), "--label", f"{a}=hscl"], capture_output=True, text=True, timeout=120)
    assert same.returncode == 2 and "appears twice" in same.stderr


# --- end to end: scripts/evaluate then scripts/report ------------------------------------------------
def test_cli_report_on_greedy_benchmark_runs(repo_root, benchmark_dir, tmp_path):
    source = benchmark_dir / "dhc_40x40_d0.3"
    jsons = []
    for agents in (4, 8):
        out = tmp_path / f"greedy_{agents:02d}.json"
        proc = subprocess.run(
            [str(repo_root / "scripts" / "evaluate"), "--solver", "greedy", "--instances",
             str(source / f"agents_{agents:02d}.npz"), "--cases", "3", "--json", str(out)],
            capture_output=True, text=True, timeout=300,
        )
        assert proc.returncode == 0, proc.stderr
        jsons.append(out)
    markdown, picture = tmp_path / "report.md", tmp_path / "report.png"
    proc = subprocess.run(
        [str(repo_root / "scripts" / "report"), *map(str, jsons), "--markdown", str(markdown), "--plot", str(picture)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert markdown.read_text() == proc.stdout

    tables = _tables(proc.stdout)
    assert set(tables) == {"dhc_40x40_d0.3", "Reference figures"}
    rows = tables["dhc_40x40_d0.3"]
    assert [(r["agents"], r["solver"], r["cases"]) for r in rows] == [("4", "greedy", "3"), ("8", "greedy", "3")]
    for row, path, k in zip(rows, jsons, range(2)):
        (summary,) = json.loads(path.read_text())["files"]
        assert row["success"] == f"{summary['success_rate']:.3f}"
        assert row["avg step"] == f"{summary['average_step']:.2f}"
        assert row["mean SoC"] == f"{summary['mean_sum_of_costs']:.1f}"
        assert row["paper counterpart"] == "HSCL (paper)"
        paper_success = PAPER_SUCCESS_RATE["HSCL (paper)"][k]
        paper_step = PAPER_AVERAGE_STEP["HSCL (paper)"][k]
        assert float(row["paper success"]) == paper_success and float(row["paper avg step"]) == paper_step
        assert float(row["Δ success"]) == pytest.approx(summary["success_rate"] - paper_success, abs=5e-4)
        assert float(row["Δ avg step"]) == pytest.approx(summary["average_step"] - paper_step, abs=5e-3)
    assert "Fewer than the benchmark's 200 cases" in proc.stdout

    from PIL import Image

    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(picture) as image:
        image.verify()
    with Image.open(picture) as image:
        assert image.format == "PNG" and image.width >= 800 and image.height >= 400
        pixels = np.asarray(image.convert("L"))
    assert pixels.std() > 10  # something is drawn, not a blank canvas
