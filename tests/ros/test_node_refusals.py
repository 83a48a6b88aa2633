"""Bad input: every node refuses to start with a clear message and exit status 2.

All cases start at once (module fixture) to keep the wall time low; each test checks one of them.
"""
from __future__ import annotations

import subprocess
import warnings

import pytest

from fleet_helpers import REPO_ROOT, SMALL_MAP, SMALL_SCEN, fleet_env

pytestmark = [pytest.mark.ros]

W, P, D, R = ("mapf_world", "world_node"), ("mapf_policy", "policy_node"), \
    ("mapf_policy", "drive_executor"), ("mapf_world", "recorder")
SCEN = dict(instance_source="map", map_file=str(SMALL_MAP), scen_file=str(SMALL_SCEN))
SHIPPED_PT, SHIPPED_NPZ = REPO_ROOT / "models" / "hscl.pt", REPO_ROOT / "models" / "hscl.npz"

CASES = {
    "world_unknown_map_file": (W, None, SCEN | dict(map_file="/no/such/file.map"), "map_file '/no/such/file.map' does not exist"),
    "world_unknown_source": (W, None, dict(instance_source="maze"), "instance_source must be one of"),
    "world_more_robots_than_agents": (W, None, SCEN | dict(n_robots=5), "has 3 agents, 5 requested"),
    "world_zero_robots": (W, None, dict(n_robots=0), "n_robots must be a positive integer"),
    "world_negative_cell_size": (W, None, dict(cell_size=-0.3), "cell_size must be a positive number"),
    "world_even_fov": (W, None, dict(fov_size=4), "fov_size must be an odd integer"),
    "world_bad_pose_source": (W, None, dict(pose_source="gps"), "pose_source must be 'odom' or 'pose_topic'"),
    "world_wrong_parameter_type": (W, None, dict(cell_size="wide"), "cell_size"),
    "policy_missing_model": (P, "/robot_0", dict(model_path="/no/such/model.npz"), "model file '/no/such/model.npz' not found"),
    "policy_incompatible_model": (P, "/robot_0", "GARBAGE_MODEL", "not a readable exported model"),
    "policy_torch_model": (P, "/robot_0", dict(model_path=str(SHIPPED_PT)), "is a torch model file; a robot runs its export"),
    "policy_export_of_another_model": (P, "/robot_0", dict(model_path=str(SHIPPED_NPZ), source_sha256="ab" * 32),
                                       "not from the model file with SHA-256 abababababab"),
    "policy_robot_id_disagrees": (P, "/robot_1", dict(robot_id=2), "robot_id 2 disagrees with namespace '/robot_1'"),
    "policy_no_robot_namespace": (P, None, dict(), "does not end in 'robot_<i>'"),
    "policy_negative_robot_id": (P, None, dict(robot_id=-4), "robot_id must be an integer >= 0"),
    "policy_negative_action_temperature": (P, "/robot_0", dict(action_temperature=-0.5),
                                           "action_temperature must be a finite number >= 0"),
    "policy_negative_backtrack_penalty": (P, "/robot_0", dict(backtrack_penalty=-1.0),
                                          "backtrack_penalty must be a finite number >= 0"),
    "drive_zero_speed": (D, "/robot_0", dict(max_linear_speed=0.0), "max_linear_speed must be a positive number"),
    "drive_negative_rtf": (D, "/robot_0", dict(real_time_factor=-2.0), "real_time_factor must be a positive number"),
    "recorder_bad_regex": (R, None, dict(exclude_regex="(", output="/tmp/never.mcap"), "not a valid regular expression"),
}


START_TIMEOUT_S = 60  # a refusal takes a few seconds, even with all the cases starting at once on 2 cores


def finish(proc: subprocess.Popen) -> tuple:
    """(exit status, output, hung) of a node process given START_TIMEOUT_S to refuse."""
    from mapf_world.fleet_launch import STACK_DUMP_SIGNAL
    try:
        text, _ = proc.communicate(timeout=START_TIMEOUT_S)
        return proc.returncode, text, False
    except subprocess.TimeoutExpired:
        # Its threads' stacks first (node_main.dump_stacks_on_signal), so a hang shows where it is.
        proc.send_signal(STACK_DUMP_SIGNAL)
        try:
            text, _ = proc.communicate(timeout=3)
        except subprocess.TimeoutExpired:
            proc.kill()
            text, _ = proc.communicate()
        return proc.returncode, text + f"\n<still running after {START_TIMEOUT_S} s: stacks requested, then killed>", True


@pytest.fixture(scope="module")
def results(module_domain_id, tmp_path_factory):
    from mapf_world.fleet_launch import node_command
    garbage = tmp_path_factory.mktemp("models") / "garbage.npz"
    garbage.write_text("this is not a model\n")

    def start(name):
        (pkg, exe), ns, params, _ = CASES[name]
        if params == "GARBAGE_MODEL":
            params = dict(model_path=str(garbage))
        return subprocess.Popen(node_command(pkg, exe, namespace=ns, params=params), env=fleet_env(module_domain_id),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    procs = {name: start(name) for name in CASES}
    out = {name: finish(proc) for name, proc in procs.items()}
    # A process that hung before it printed anything (CI, 2026-12-05: drive_zero_speed, no output in 90 s, while
    # the other 19 refused; 1 of about 20 local runs, another case) is started once more, alone. Its first
    # output, with the stacks of the hang, goes into a warning, so the hang stays visible in the test report.
    for name, (_, first_text, hung) in list(out.items()):
        if hung:
            code, text, _ = finish(start(name))
            out[name] = (code, text, True)
            warnings.warn(f"{name}: the first start hung; it was started again. Its first output:\n{first_text}")
    return {name: (code, text) for name, (code, text, _) in out.items()}


@pytest.mark.parametrize("case", list(CASES))
def test_node_refuses_to_start(results, case):
    code, text = results[case]
    expected = CASES[case][3]
    assert code == 2, f"exit status {code}, output:\n{text}"
    assert "refusing to start" in text and expected in text, text


@pytest.mark.parametrize("args, expected", [
    (["--robots", "0-3,2", "--nodes", "policy"], "--robots must name each robot once"),
    (["--robots", "0-1", "--nodes", "policy", "--policy-param", "backtrack_penalty:=-1.0"],
     "backtrack_penalty must be a finite number >= 0"),
    (["--robots", "0-1", "--nodes", "drive", "--drive-param", "idle_rate_hz:=-1.0"],
     "idle_rate_hz must be a number >= 0"),
])
def test_robot_container_refuses_to_start(module_domain_id, args, expected):
    from mapf_world.fleet_launch import executable
    proc = subprocess.run([str(executable("mapf_policy", "robot_container"))] + args, env=fleet_env(module_domain_id),
                          capture_output=True, text=True, timeout=90)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "refusing to start" in proc.stderr and expected in proc.stderr, proc.stderr
