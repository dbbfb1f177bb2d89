"""The wheel installs one top-level package, ``convoy``: its parts import as ``convoy.*`` and ``import api`` fails.

The wheel is built offline with this environment's setuptools and unpacked into a bare folder; the imports then run
in a fresh interpreter from another directory with this checkout's editable finder taken out, so they can only
succeed from the wheel's files.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow

PROBE = """
import sys
sys.meta_path = [f for f in sys.meta_path if "editable" not in getattr(f, "__module__", "").lower()]
sys.path_hooks = [h for h in sys.path_hooks if "editable" not in getattr(h, "__module__", "").lower()]
sys.path_importer_cache.clear()
sys.path.insert(0, sys.argv[1])
import convoy.envs, convoy.learner, convoy.api, convoy.cli.main, convoy.algos.ma_mesn
assert convoy.envs.__file__.startswith(sys.argv[1]), convoy.envs.__file__
assert convoy.api.__file__.startswith(sys.argv[1]), convoy.api.__file__
for generic in ("api", "envs", "learner", "services", "protocol", "actors", "algos", "analysis"):
    try:
        __import__(generic)
    except ModuleNotFoundError:
        continue
    raise SystemExit(f"import {generic} worked: the wheel leaked a generic top-level module")
print("ok")
"""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    src = out / "src"  # a copy: an in-tree build would leave build/ and egg-info in the checkout
    folders = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"].values()
    for folder in ("convoy", *folders):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)]
    subprocess.run(cmd, check=True, cwd=out, timeout=300, capture_output=True)
    (found,) = out.glob("convoy-*.whl")
    return found


def test_the_wheel_holds_only_the_convoy_package(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/", 1)[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"convoy"}, tops
    for part in ("envs/treadmill/engine.py", "api/routes/jobs.py", "api/static/index.html", "algos/ma_mesn.py"):
        assert f"convoy/{part}" in names, part


def test_installed_code_imports_as_convoy_and_not_as_generic_names(wheel: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, str(site)], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stdout + proc.stderr
