"""Process launcher and pictures of the fleet (mapf_world.fleet_launch, mapf_world.render), no ROS graph."""
import os

import numpy as np
import pytest
import yaml

from mapf_world.fleet_launch import ProcessGroup, executable, node_command, param_value, read_usage


@pytest.mark.parametrize("value", [True, False, 3, -1, 0.5, 10.0, 1e-9, float("inf"), 2.5e+20, "odom", "", "true", "1.5",
                                   "/tmp/a b.mcap", "^/parameter_events$", "a: b", [1, 2], ["x", "y"]])
def test_param_values_parse_back_as_the_same_yaml(value):
    text = param_value(value)
    parsed = yaml.safe_load(text)
    assert parsed == value and type(parsed) is type(value), (value, text, parsed)


def test_param_value_refuses_other_types():
    with pytest.raises(ValueError, match="cannot pass a dict"):
        param_value({"a": 1})


def test_node_command_is_what_ros2_run_starts():
    cmd = node_command("mapf_policy", "policy_node", namespace="/robot_2", params={"torch_threads": 1})
    assert cmd[0].endswith("/lib/mapf_policy/policy_node") and os.access(cmd[0], os.X_OK)
    assert cmd[1:] == ["--ros-args", "-r", "__ns:=/robot_2", "-p", "torch_threads:=1"]
    with pytest.raises(ValueError, match="not installed"):
        executable("no_such_package", "x")
    with pytest.raises(ValueError, match="no executable"):
        executable("mapf_policy", "no_such_node")


def test_process_group_stops_and_measures(tmp_path):
    import sys
    group = ProcessGroup(tmp_path)
    group.start("sleeper", [sys.executable, "-c", "import time; print('sleeper' + ' is up', flush=True); time.sleep(60)"])
    import time
    end = time.monotonic() + 60
    # The log starts with the command line, so wait for the printed line, which it does not contain.
    while "sleeper is up" not in group.log_text("sleeper") and time.monotonic() < end:
        time.sleep(0.05)
    usage = group.usage("sleeper")
    assert usage is not None and usage.rss_mb > 1, (usage, group.log_text("sleeper"))
    assert group.stop("sleeper", timeout=5) == -2   # ended by SIGINT (KeyboardInterrupt in python)
    assert read_usage(group.procs["sleeper"].pid) is None


def test_an_exited_process_not_yet_reaped_has_no_usage():
    # A zombie's /proc status has no VmRSS line; it reads as no reading, not as an RSS of 0.
    import subprocess
    import sys
    import time
    from pathlib import Path
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        end = time.monotonic() + 30
        while Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
            assert time.monotonic() < end, "the child did not exit"
            time.sleep(0.02)
        assert read_usage(proc.pid) is None
    finally:
        proc.wait()


def test_a_process_that_ignores_sigint_and_sigterm_leaves_its_stacks_in_its_log_before_sigkill(tmp_path):
    import sys
    import time
    group = ProcessGroup(tmp_path)
    child = ("import faulthandler, signal, time\n"
             "faulthandler.register(signal.SIGUSR1, all_threads=True)  # as node_main.dump_stacks_on_signal\n"
             "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
             "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
             "def stuck_here():\n"
             "    print('stuck' + ' is up', flush=True)\n"
             "    time.sleep(60)\n"
             "stuck_here()\n")
    group.start("stuck", [sys.executable, "-c", child])
    end = time.monotonic() + 60
    while "stuck is up" not in group.log_text("stuck") and time.monotonic() < end:
        time.sleep(0.05)
    assert group.stop("stuck", timeout=0.5) == -9
    log = group.log_text("stuck")
    assert "[launch] stuck still running after SIGINT and SIGTERM: its stacks (SIGUSR1) follow, then SIGKILL" in log
    assert 'line 7 in stuck_here' in log, log


def test_render_png_and_gif(tmp_path):
    from mapf_world.render import render_gif, render_png
    grid = np.zeros((4, 5), np.uint8)
    grid[1, 1] = 1
    positions = np.array([[[0, 0], [3, 4]], [[0, 1], [3, 3]], [[0, 2], [3, 3]]])
    goals = np.array([[0, 2], [3, 3]])
    png = render_png(tmp_path / "p.png", grid, positions, goals, tracks={0: [(0.0, 0.0), (0.3, 0.0)]}, cell_size=0.3)
    gif = render_gif(tmp_path / "p.gif", grid, positions, goals)
    assert png.read_bytes()[:4] == b"\x89PNG" and gif.read_bytes()[:3] == b"GIF"
    from PIL import Image
    assert Image.open(gif).n_frames == 3
    with pytest.raises(ValueError, match="positions must be"):
        render_png(tmp_path / "x.png", grid, positions[0], goals)
    with pytest.raises(ValueError, match="goals must be"):
        render_png(tmp_path / "x.png", grid, positions, goals[:1])


def test_fleet_env_sets_the_domain_and_keeps_the_callers_choices():
    from mapf_world.fleet_launch import FLEET_ENV_DEFAULTS, fleet_env
    env = fleet_env(117, base={"PATH": "/bin", "ROS_DOMAIN_ID": "3"})
    assert env["ROS_DOMAIN_ID"] == "117" and env["PATH"] == "/bin"
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert set(FLEET_ENV_DEFAULTS) == {"FASTDDS_BUILTIN_TRANSPORTS", "ROS_AUTOMATIC_DISCOVERY_RANGE"}
    chosen = fleet_env(5, base={"FASTDDS_BUILTIN_TRANSPORTS": "DEFAULT", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    assert chosen["FASTDDS_BUILTIN_TRANSPORTS"] == "DEFAULT" and chosen["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
