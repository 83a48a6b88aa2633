"""Instance generator, benchmark .npz I/O, MovingAI .map/.scen loading, and their error messages."""
from __future__ import annotations

import numpy as np
import pytest

from mapf_world.heuristics import UNREACHABLE, distance_maps
from mapf_world.instances import (
    Instance,
    generate_instance,
    load_movingai_map,
    load_movingai_scen,
    load_npz,
    save_npz,
)

TINY_MAP = [
    [0, 0, 1, 0, 0, 0],
    [0, 1, 0, 0, 0, 0],
    [0, 0, 0, 1, 0, 0],
    [0, 0, 0, 0, 0, 0],
]


# --- generator --------------------------------------------------------------------------------
def test_generator_is_seeded_and_valid():
    a = generate_instance(5, size=40, density=0.3, n_agents=16)
    b = generate_instance(np.random.default_rng(5), size=40, density=0.3, n_agents=16)
    c = generate_instance(6, size=40, density=0.3, n_agents=16)
    assert (a.grid == b.grid).all() and (a.starts == b.starts).all() and (a.goals == b.goals).all()
    assert not (a.grid == c.grid).all()
    assert a.grid.shape == (40, 40) and a.grid.dtype == np.uint8 and a.starts.shape == (16, 2)
    cells = np.concatenate([a.starts, a.goals])
    assert len({tuple(x) for x in cells.tolist()}) == 32  # all 2N cells distinct
    assert (a.grid[tuple(cells.T)] == 0).all()
    dist = distance_maps(a.grid, a.goals)
    assert (dist[np.arange(16), a.starts[:, 0], a.starts[:, 1]] < UNREACHABLE).all()


def test_generator_density_and_rectangular_maps():
    rng = np.random.default_rng(0)
    shares = [generate_instance(rng, size=40, density=0.3, n_agents=4).grid.mean() for _ in range(30)]
    assert abs(np.mean(shares) - 0.3) < 0.01
    inst = generate_instance(1, size=12, density=0.2, n_agents=3, height=7)
    assert inst.grid.shape == (7, 12)


def test_generator_many_agents_on_a_small_map():
    inst = generate_instance(3, size=6, density=0.1, n_agents=12)
    assert len({tuple(x) for x in np.concatenate([inst.starts, inst.goals]).tolist()}) == 24


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(density=1.0), "density"),
        (dict(density=-0.1), "density"),
        (dict(n_agents=0), "n_agents"),
        (dict(size=0), "size"),
        (dict(size=3, n_agents=5), "need 10 cells"),
        (dict(size=4, density=0.9, n_agents=6, max_tries=3), "fitted 6 agents in 3 tries"),
    ],
)
def test_generator_bad_arguments(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        generate_instance(0, **kwargs)


def test_generator_rejects_bad_seed():
    with pytest.raises(ValueError, match="seed"):
        generate_instance("0")
    with pytest.raises(ValueError, match="seed"):
        generate_instance(None)


# --- Instance ---------------------------------------------------------------------------------
def test_instance_validates_its_cells():
    grid = np.array(TINY_MAP, dtype=np.uint8)
    with pytest.raises(ValueError, match="starts: agent 0 cell \\(0, 2\\) is on an obstacle"):
        Instance(grid, [[0, 2]], [[0, 0]])
    walled = grid.copy()
    walled[:, 2] = 1
    with pytest.raises(ValueError, match="agent 0: goal \\[0, 5\\] is unreachable"):
        Instance(walled, [[0, 0]], [[0, 5]])


# --- benchmark .npz ---------------------------------------------------------------------------
def test_npz_fixture_and_round_trip(fixtures_dir, tmp_path):
    cases = load_npz(fixtures_dir / "tiny.npz")
    assert len(cases) == 3 and cases[0].grid.shape == (6, 8) and cases[0].n_agents == 3
    assert cases[2].name == "tiny#2"
    out = tmp_path / "copy.npz"
    save_npz(out, cases)
    with np.load(out, allow_pickle=False) as data:
        assert data["maps"].dtype == np.uint8 and data["maps"].shape == (3, 6, 8)
        assert data["starts"].dtype == np.int16 and data["goals"].shape == (3, 3, 2)
    again = load_npz(out)
    for a, b in zip(cases, again):
        assert (a.grid == b.grid).all() and (a.starts == b.starts).all() and (a.goals == b.goals).all()


def _write(path, maps, starts, goals, **extra):
    np.savez(path, maps=maps, starts=starts, goals=goals, **extra)
    return path


def _good(fixtures_dir):
    with np.load(fixtures_dir / "tiny.npz") as d:
        return d["maps"].copy(), d["starts"].copy(), d["goals"].copy()


def test_npz_errors_name_file_case_and_agent(fixtures_dir, tmp_path):
    maps, starts, goals = _good(fixtures_dir)
    bad = starts.copy()
    r, c = np.argwhere(maps[1] == 1)[0]
    bad[1, 2] = (r, c)
    path = _write(tmp_path / "obstacle.npz", maps, bad, goals)
    with pytest.raises(ValueError, match=r"obstacle\.npz: case 1: starts: agent 2 cell .* is on an obstacle"):
        load_npz(path)
    bad = goals.copy()
    bad[2, 1] = bad[2, 0]
    with pytest.raises(ValueError, match=r"case 2: goals: agents \[0, 1\] share cell"):
        load_npz(_write(tmp_path / "dup.npz", maps, starts, bad))
    bad = starts.copy()
    bad[0, 0] = (6, 0)
    with pytest.raises(ValueError, match=r"case 0: starts: agent 0 cell \(6, 0\) is off the 6x8 map"):
        load_npz(_write(tmp_path / "off.npz", maps, bad, goals))


def test_npz_unreachable_goal(tmp_path):
    grid = np.zeros((1, 3, 5), np.uint8)
    grid[0, :, 2] = 1
    path = _write(tmp_path / "walled.npz", grid, np.array([[[0, 0]]], np.int16), np.array([[[0, 4]]], np.int16))
    with pytest.raises(ValueError, match=r"walled\.npz: case 0: agent 0: goal \[0, 4\] is unreachable"):
        load_npz(path)


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda m, s, g: (m[0], s, g), r"maps must be \(K, H, W\)"),
        (lambda m, s, g: (m, s[:2], g), r"starts must be \(3, N, 2\)"),
        (lambda m, s, g: (m, s, g[:, :2]), "differ in shape"),
        (lambda m, s, g: (m, s.astype(float), g), "starts must be integers"),
        (lambda m, s, g: (m * 2, s, g), r"case 0: grid must hold only 0"),
    ],
)
def test_npz_malformed_arrays(fixtures_dir, tmp_path, mutate, pattern):
    path = _write(tmp_path / "bad.npz", *mutate(*_good(fixtures_dir)))
    with pytest.raises(ValueError, match=pattern):
        load_npz(path)


def test_npz_malformed_files(fixtures_dir, tmp_path):
    raw = (fixtures_dir / "tiny.npz").read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"trunc\.npz: not a readable \.npz"):
        load_npz(tmp_path / "trunc.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(ValueError, match=r"text\.npz"):
        load_npz(tmp_path / "text.npz")
    maps, starts, goals = _good(fixtures_dir)
    np.savez(tmp_path / "missing.npz", maps=maps, starts=starts)
    with pytest.raises(ValueError, match=r"missing\.npz: missing arrays \['goals'\]"):
        load_npz(tmp_path / "missing.npz")
    np.savez(tmp_path / "pickled.npz", maps=maps, starts=np.array([object()] * 3, dtype=object), goals=goals)
    with pytest.raises(ValueError, match=r"pickled\.npz"):
        load_npz(tmp_path / "pickled.npz")
    np.save(tmp_path / "single.npy", maps)
    with pytest.raises(ValueError, match="single array"):
        load_npz(tmp_path / "single.npy")
    with pytest.raises(FileNotFoundError):
        load_npz(tmp_path / "nowhere.npz")


def test_save_npz_rejects_mixed_cases(tmp_path):
    a = generate_instance(0, size=8, n_agents=2)
    b = generate_instance(1, size=8, n_agents=3)
    with pytest.raises(ValueError, match="case 1 has"):
        save_npz(tmp_path / "x.npz", [a, b])
    with pytest.raises(ValueError, match="no instances"):
        save_npz(tmp_path / "x.npz", [])


# --- MovingAI ---------------------------------------------------------------------------------
def test_movingai_map_fixture(fixtures_dir):
    grid = load_movingai_map(fixtures_dir / "tiny.map")
    assert grid.dtype == np.uint8 and grid.tolist() == TINY_MAP


def test_movingai_scen_fixture_converts_x_y_to_row_col(fixtures_dir):
    inst = load_movingai_scen(fixtures_dir / "tiny.scen", 3)
    assert inst.grid.tolist() == TINY_MAP
    assert inst.starts.tolist() == [[0, 0], [1, 4], [0, 5]]
    assert inst.goals.tolist() == [[3, 5], [3, 0], [2, 2]]
    # The scenario's optimal lengths agree with BFS on the converted cells.
    lines = (fixtures_dir / "tiny.scen").read_text().splitlines()[1:4]
    dist = distance_maps(inst.grid, inst.goals)
    for i, line in enumerate(lines):
        assert float(line.split("\t")[8]) == dist[i][tuple(inst.starts[i])]
    four = load_movingai_scen(fixtures_dir / "tiny.scen", 4, grid=np.array(TINY_MAP))
    assert four.n_agents == 4 and four.starts[3].tolist() == [3, 1]


MAP_HEAD = "type octile\nheight 2\nwidth 3\nmap\n"


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("type octile\nheight 2\n", "line 3: file ends before the 'width' header"),
        ("type grid\nheight 2\nwidth 3\nmap\n...\n...\n", "line 1: unsupported map type 'grid'"),
        ("type octile\nheight two\nwidth 3\nmap\n", "line 2: height must be a positive integer"),
        ("type octile\nwidth 3\nheight 2\nmap\n", "line 2: expected 'height <value>'"),
        ("type octile\nheight 2\nwidth 3\nmop\n...\n...\n", "line 4: expected 'map'"),
        (MAP_HEAD + "...\n..\n", "line 6: expected 3 characters, got 2"),
        (MAP_HEAD + "...\n.x.\n", "line 6, column 2: unknown map character 'x'"),
        (MAP_HEAD + "...\n", "line 6: expected 2 map rows, found 1"),
        (MAP_HEAD + "...\n...\n...\n", "line 7: expected 2 map rows, found 3"),
    ],
)
def test_movingai_map_malformed(tmp_path, text, pattern):
    path = tmp_path / "bad.map"
    path.write_text(text)
    with pytest.raises(ValueError, match=f"bad.map: {pattern}"):
        load_movingai_map(path)


def test_movingai_map_obstacle_letters(tmp_path):
    path = tmp_path / "letters.map"
    path.write_text(MAP_HEAD + ".GS\n@TW\n")
    assert load_movingai_map(path).tolist() == [[0, 0, 0], [1, 1, 1]]
    path.write_text(MAP_HEAD + "O..\n...\r\n")
    assert load_movingai_map(path).tolist() == [[1, 0, 0], [0, 0, 0]]


def _scen(tmp_path, rows, header="version 1"):
    path = tmp_path / "bad.scen"
    path.write_text(header + "\n" + "\n".join("\t".join(map(str, r)) for r in rows) + "\n")
    return path


ROW0 = [0, "tiny.map", 6, 4, 0, 0, 5, 3, 8]
ROW1 = [0, "tiny.map", 6, 4, 4, 1, 0, 3, 6]


@pytest.mark.parametrize(
    "rows, n, pattern",
    [
        ([ROW0], 2, "has 1 agents, 2 requested"),
        ([ROW0, ROW1[:8]], 2, "line 3: expected 9 columns, got 8"),
        ([ROW0, ROW1[:4] + ["a"] + ROW1[5:]], 2, "line 3: sizes and coordinates must be integers"),
        ([ROW0, [0, "tiny.map", 4, 6, 4, 1, 0, 3, 6]], 2, r"line 3: the scenario.s map is 4 wide, 6 high"),
        ([ROW0, [0, "tiny.map", 6, 4, 2, 0, 0, 3, 6]], 2, r"line 3: starts: agent 1 cell \(0, 2\) is on an obstacle"),
        ([ROW0, [0, "tiny.map", 6, 4, 7, 1, 0, 3, 6]], 2, r"line 3: starts: agent 1 cell \(1, 7\) is off"),
        ([ROW0, [0, "tiny.map", 6, 4, 0, 0, 0, 3, 6]], 2, r"line 3: starts: agents \[0, 1\] share cell"),
        ([ROW0], 0, "n_agents must be a positive integer"),
    ],
)
def test_movingai_scen_malformed(tmp_path, rows, n, pattern):
    path = _scen(tmp_path, rows)
    with pytest.raises(ValueError, match=pattern):
        load_movingai_scen(path, n, grid=np.array(TINY_MAP))


def test_movingai_scen_header_and_missing_map(tmp_path):
    with pytest.raises(ValueError, match="bad.scen: line 1: expected 'version 1'"):
        load_movingai_scen(_scen(tmp_path, [ROW0], header="version 2"), 1, grid=np.array(TINY_MAP))
    with pytest.raises(ValueError, match="line 2: map file .*tiny.map not found"):
        load_movingai_scen(_scen(tmp_path, [ROW0]), 1)
