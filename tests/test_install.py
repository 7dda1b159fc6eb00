"""`pip install .` into a venv without ROS: the core imports and works."""

from __future__ import annotations

import subprocess
import sys
import venv
from pathlib import Path

import pytest

from .conftest import REPO


@pytest.mark.slow
def test_core_installs_and_imports_without_ros(tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    install = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(REPO)],
                             capture_output=True, text=True, timeout=600)
    assert install.returncode == 0, install.stderr[-3000:]
    code = ("import importlib.util, motor_driver, can_config, virtual_can\n"
            "assert importlib.util.find_spec('rclpy') is None, 'ROS leaked into the core install'\n"
            "from can_config import load_config\n"
            "from virtual_can import SimService\n"
            "from motor_driver import MotorDriver\n"
            "from can_config import with_bus_overrides\n"
            "from rovercan.cli import build_parser\n"
            "build_parser()  # every bench command's module imports\n"
            "cfg = load_config()\n"
            "with SimService.from_config(cfg, port=0) as sim:\n"
            "    with MotorDriver(with_bus_overrides(cfg, port=sim.port)) as d:\n"
            "        d.start(); j = d.drive('motor'); j.enable(); j.move_to(12.0, wait=True)\n"
            "        print(j.cache.angle_deg)\n")
    run = subprocess.run([str(py), "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert abs(float(run.stdout) - 12.0) < 0.15  # 'target reached' holds within the position window
    assert sys.executable != str(py)
