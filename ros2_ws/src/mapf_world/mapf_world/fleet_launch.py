"""Start fleet nodes as separate processes, the way `ros2 run` would (launch is not available here).

`node_command("mapf_policy", "policy_node", namespace="/robot_0", params={...})` gives
    [<prefix>/lib/mapf_policy/policy_node, --ros-args, -r, __ns:=/robot_0, --params-file, ..., -p, k:=v]
where <prefix> comes from the ament index, i.e. exactly the executable `ros2 run mapf_policy
policy_node` starts on a full ROS 2 install. `ProcessGroup` runs such commands with one log file
each, stops them with SIGINT (then SIGTERM, then SIGKILL if they hang) and reads their CPU time and
memory from /proc.
"""
from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import yaml

# ROS_DOMAIN_ID claims shared by the ROS tests and the fleet benchmarks on one machine: a lock file per id, so
# concurrent runs never share a domain and every answer comes from the run's own nodes.
DOMAIN_LOCK_DIR = Path("/tmp/mapf_ros_domain_locks")
DOMAIN_IDS = range(100, 230)


def claim_domain_id(from_top: bool = False):
    """(a free ROS_DOMAIN_ID in 100..229, its open lock file: keep it open while the id is in use). The tests
    claim from the bottom, the benchmarks `from_top`, so that the two rarely contend."""
    DOMAIN_LOCK_DIR.mkdir(exist_ok=True)
    for domain in (reversed(DOMAIN_IDS) if from_top else DOMAIN_IDS):
        f = open(DOMAIN_LOCK_DIR / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return domain, f
        except BlockingIOError:
            f.close()
    raise RuntimeError(f"no free ROS_DOMAIN_ID in {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1}")


# The environment every fleet process gets (see fleet_env). Discovery stays on this host, and Fast DDS sends over
# UDP on the loopback instead of its shared-memory transport: with shared memory (Fast DDS 2.14, the PyPI wheels),
# a subscription sometimes matched a publisher process and then never received one of its messages (two
# fresh-clone CI runs recorded no odom and cmd_vel of one robot while the world received them), a failure
# Fast DDS reports for shared-memory ports after processes are killed or stall under load. A caller's own
# setting of either variable wins.
FLEET_ENV_DEFAULTS = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}


def fleet_env(domain: int, base: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """The environment of a fleet process on ROS_DOMAIN_ID `domain`: `base` (default os.environ) plus
    FLEET_ENV_DEFAULTS where `base` does not set them."""
    env = dict(os.environ if base is None else base, ROS_DOMAIN_ID=str(domain))
    for key, value in FLEET_ENV_DEFAULTS.items():
        env.setdefault(key, value)
    return env


def executable(package: str, name: str) -> Path:
    """install/<package>/lib/<package>/<name>; ValueError when it is not there."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        prefix = Path(get_package_prefix(package))
    except PackageNotFoundError as exc:
        raise ValueError(f"package {package!r} is not installed (source ros2_ws/install/setup.bash)") from exc
    path = prefix / "lib" / package / name
    if not os.access(path, os.X_OK):
        raise ValueError(f"no executable {path}; is {name!r} a console script of {package}?")
    return path


def config_file(package: str, name: str) -> Path:
    """share/<package>/config/<name> through the ament index."""
    from ament_index_python.packages import get_package_share_directory
    path = Path(get_package_share_directory(package)) / "config" / name
    if not path.is_file():
        raise ValueError(f"no parameter file {path}")
    return path


def param_value(value) -> str:
    """A Python value as the YAML text that `-p name:=value` parses back to the same value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            return {"nan": ".nan", "inf": ".inf", "-inf": "-.inf"}[repr(value)]
        mantissa, e, exponent = repr(value).partition("e")
        # YAML 1.1 reads "1e-09" as a string: the mantissa needs a decimal point.
        return (mantissa if "." in mantissa else mantissa + ".0") + (e + exponent if e else "")
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return value if value and yaml.safe_load(value) == value and ":" not in value else json.dumps(value)
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    raise ValueError(f"cannot pass a {type(value).__name__} as a ROS parameter: {value!r}")


def node_command(package: str, name: str, namespace: Optional[str] = None, params: Optional[dict] = None,
                 params_file: Optional[Path] = None, node_name: Optional[str] = None) -> List[str]:
    cmd = [str(executable(package, name)), "--ros-args"]
    if namespace:
        cmd += ["-r", f"__ns:={namespace}"]
    if node_name:
        cmd += ["-r", f"__node:={node_name}"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    for key, value in (params or {}).items():
        cmd += ["-p", f"{key}:={param_value(value)}"]
    return cmd


@dataclass
class Usage:
    """CPU seconds (user + system) and memory of one process, read from /proc."""
    cpu_s: float
    rss_mb: float
    peak_rss_mb: float


def read_usage(pid: int) -> Optional[Usage]:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
    mem = {}
    for line in status.splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            mem[key] = int(rest.split()[0]) / 1024.0
    if "VmRSS" not in mem:
        # An exiting process (or a zombie not yet reaped) has released its memory and its status has no Vm lines:
        # no reading, rather than an RSS of 0 that a soak's last sample of a world node once reported.
        return None
    return Usage(cpu, mem["VmRSS"], mem.get("VmHWM", mem["VmRSS"]))


# Sent to a process still running after SIGINT and SIGTERM, before SIGKILL: every node registers it to print
# each thread's Python stack into its log (node_main.dump_stacks_on_signal), so a hang leaves its place.
STACK_DUMP_SIGNAL = signal.SIGUSR1


def _default_sigint() -> None:
    """Child side of Popen: SIGINT back to its default action.

    A shell starts background jobs (`scripts/demo &`, nohup) with SIGINT ignored, and children inherit
    that; Python then installs no KeyboardInterrupt handler, so stop()'s SIGINT would do nothing and the
    nodes would only end on the SIGTERM escalation. Restoring it keeps the graceful first step.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class ProcessGroup:
    """Named node processes with one log file each; stop() is SIGINT first, then escalates."""

    def __init__(self, log_dir: Path, env: Optional[Dict[str, str]] = None):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ if env is None else env)
        self.procs: Dict[str, subprocess.Popen] = {}
        self._logs = {}

    def start(self, name: str, cmd: List[str]) -> subprocess.Popen:
        if name in self.procs and self.procs[name].poll() is None:
            raise ValueError(f"process {name!r} is already running")
        log = open(self.log_dir / f"{name}.log", "ab")
        log.write((" ".join(cmd) + "\n").encode())
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=self.env, stdin=subprocess.DEVNULL,
                                preexec_fn=_default_sigint)
        self.procs[name] = proc
        self._logs[name] = log
        return proc

    def log_text(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def usage(self, name: str) -> Optional[Usage]:
        proc = self.procs.get(name)
        return read_usage(proc.pid) if proc is not None and proc.poll() is None else None

    def send(self, name: str, sig: int) -> None:
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(sig)

    def stop(self, name: str, sig: int = signal.SIGINT, timeout: float = 10.0,
             sent_before: Tuple[str, ...] = ()) -> Optional[int]:
        """Signal one process and wait; escalate to SIGTERM, then STACK_DUMP_SIGNAL (a node prints its threads'
        stacks to its log; a process without that handler ends by it), then SIGKILL. Returns its exit code."""
        proc = self.procs.get(name)
        if proc is None:
            return None
        sent = list(sent_before)  # signals already sent (stop_all's first), for the message below
        for s, wait in ((sig, timeout), (signal.SIGTERM, 5.0), (STACK_DUMP_SIGNAL, 2.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            if s == STACK_DUMP_SIGNAL:
                self._logs[name].write(f"[launch] {name} still running after {' and '.join(sent)}: "
                                       f"its stacks ({STACK_DUMP_SIGNAL.name}) follow, then SIGKILL\n".encode())
                self._logs[name].flush()
            proc.send_signal(s)
            sent.append(signal.Signals(s).name)
            try:
                proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        self._logs[name].close()
        return proc.returncode

    def stop_all(self, names: Optional[List[str]] = None, sig: int = signal.SIGINT, timeout: float = 10.0) -> Dict[str, Optional[int]]:
        """Signal all (or the named) processes at once, then wait for each."""
        names = list(self.procs) if names is None else names
        for name in names:
            if self.procs[name].poll() is None:
                self.procs[name].send_signal(sig)
        deadline = time.monotonic() + timeout
        codes = {}
        for name in names:
            try:
                self.procs[name].wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            codes[name] = self.stop(name, signal.SIGTERM, sent_before=(signal.Signals(sig).name,))
        return codes
