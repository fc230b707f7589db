"""The package as a user gets it: a wheel, installed into a fresh virtual environment.

The wheel must carry the typing marker, the reference config (``alignctl demo`` with no
``--config`` uses it, from any folder) and the licence; the console scripts must run. The
fresh venv takes alignd's dependencies from this environment (a ``.pth`` file) so the test
needs no download beyond the build backend, and ``pip install --no-index`` still checks the
wheel's declared requirements against them.
"""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def run(*cmd: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def test_wheel_installs_in_a_fresh_venv_and_runs_from_any_folder(tmp_path: Path) -> None:
    dist = tmp_path / "dist"
    run(sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", dist, ROOT,
        cwd=tmp_path)
    (wheel,) = dist.glob("alignd-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        assert {"alignd/py.typed", "drivers/py.typed", "alignd/data/sim.yaml"} <= names
        assert zf.read("alignd/data/sim.yaml") == (ROOT / "configs" / "sim.yaml").read_bytes()
        meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
        text = zf.read(meta).decode()
        assert "License-Expression: MIT" in text and "Requires-Dist: pyserial" in text
        assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)

    venv = tmp_path / "venv"
    run(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp_path)  # this pip installs
    vpy = venv / "bin" / "python"
    site = run(vpy, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])",
               cwd=tmp_path).stdout.strip()
    (Path(site) / "deps_from_test_env.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    run(sys.executable, "-m", "pip", "--python", vpy, "install", "--quiet", "--no-index", wheel,
        cwd=tmp_path)

    elsewhere = tmp_path / "elsewhere"  # no configs/ here: the packaged config is used
    elsewhere.mkdir()
    assert "alignctl demo" in run(venv / "bin" / "alignctl", "demo", "--help",
                                  cwd=elsewhere).stdout
    assert "--config" in run(venv / "bin" / "alignd", "--help", cwd=elsewhere).stdout
    probe = ("import alignd, alignd.cli.demo_cmd as d, alignd.config as c\n"
             "with d.config_path(None) as p:\n"
             "    print(alignd.__file__); print(p); print(c.load_config(p).name)\n")
    where, cfg_path, name = run(vpy, "-c", probe, cwd=elsewhere).stdout.split()
    assert where.startswith(site) and cfg_path.startswith(site)  # the installed copy
    assert name == yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())["name"]
