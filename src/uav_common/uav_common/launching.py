"""Starting installed node executables as processes (what `ros2 run` does), and stopping them cleanly."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path


def find_executable(pkg: str, exe: str) -> str:
    """The executable `ros2 run pkg exe` would start, from the sourced workspace(s)."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if not prefix:
            continue
        for cand in (Path(prefix) / "lib" / pkg / exe, Path(prefix) / pkg / "lib" / pkg / exe):
            if cand.is_file() and os.access(cand, os.X_OK):
                return str(cand)
    here = Path(sys.argv[0]).resolve().parent.parent.parent  # install/<pkg>/lib/<pkg>/exe -> install/
    cand = here / pkg / "lib" / pkg / exe
    if cand.is_file():
        return str(cand)
    found = shutil.which(exe)
    if found:
        return found
    raise FileNotFoundError(f"cannot find executable '{exe}' of package '{pkg}': source install/setup.bash first")


def stop_process(p: subprocess.Popen, timeout_s: float = 60.0) -> int:
    """Ctrl-C to a process started in a session of its own (and its children), SIGKILL after `timeout_s`; its code."""
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return p.returncode


def stop_signals():
    """Ctrl-C and SIGTERM set a flag instead of raising, so a launcher can stop its nodes in order; the
    returned callable tells whether one came."""
    came = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: came.append(True))
    return lambda: bool(came)


def ros_log_dir() -> Path:
    """Where ROS keeps logs: $ROS_LOG_DIR, else $ROS_HOME/log, else ~/.ros/log (as rcl decides)."""
    if os.environ.get("ROS_LOG_DIR"):
        return Path(os.environ["ROS_LOG_DIR"]).expanduser()
    home = os.environ.get("ROS_HOME")
    return (Path(home).expanduser() if home else Path.home() / ".ros") / "log"


def params_args(params_dir: Path | None, name: str) -> list[str]:
    f = params_dir / f"{name}.yaml" if params_dir else None
    return ["--params-file", str(f)] if f and f.is_file() else []


class Processes:
    def __init__(self, log_dir: Path | None = None, quiet: bool = False, env: dict | None = None):
        self.procs: dict[str, subprocess.Popen] = {}
        self.log_dir = log_dir
        self.quiet = quiet
        self.env = env

    def start(self, name: str, pkg: str, exe: str, ros_args: list[str], args: list[str] = ()) -> subprocess.Popen:
        """Start `exe` of `pkg` with its own `args`, then `--ros-args` and `ros_args`."""
        cmd = [find_executable(pkg, exe), *args, "--ros-args", *ros_args]
        out = None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_dir / f"{name}.log", "w")
        elif self.quiet:
            out = subprocess.DEVNULL
        p = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT if out else None, start_new_session=True, env=self.env)
        self.procs[name] = p
        return p

    def stop(self, name: str, timeout_s: float = 60.0) -> int | None:
        p = self.procs.get(name)
        return None if p is None else stop_process(p, timeout_s)

    def stop_all(self, order: list[str] | None = None) -> None:
        for name in order or list(self.procs):
            self.stop(name)
