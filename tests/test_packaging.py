"""The wheel holds the whole library: installed outside the repository, it runs the README's
first example, loads the robots from its own package data and runs the robots tutorial.

The wheel is installed with ``--no-deps`` into a fresh virtual environment that sees the
dependencies of the environment running the tests through a ``.pth`` file: those are resolved
by the project's constraints (installing torch again would take minutes), and the point here is
the package's own contents. That ``.pth`` file only lists directories, so the base
environment's own ``.pth`` files (among them an editable install of this checkout) are not
processed; the children run in isolated mode (``-I``: no ``PYTHONPATH``, no user site, no
script or working directory on ``sys.path``) from a temporary directory, and each asserts that
``torchcontact`` comes from the fresh environment.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

from torchcontact.robots import ROBOT_NAMES

ROOT = Path(__file__).resolve().parents[1]
PIP = (sys.executable, "-m", "pip", "--quiet", "--disable-pip-version-check")
CONSTRAINTS = ("-c", str(ROOT / "constraints.txt"))
#: The environment for pip: no PYTHONPATH (a checkout on it reads as an installed torchcontact).
CLEAN_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"PYTHONNOUSERSITE": "1"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build the wheel from a copy of the sources (the build writes beside them)."""
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    shutil.copytree(
        ROOT / "torchcontact",
        source / "torchcontact",
        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
    )
    dist = tmp_path_factory.mktemp("dist")
    subprocess.run(
        [
            *PIP,
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            *CONSTRAINTS,
            "-w",
            str(dist),
            str(source),
        ],
        env=CLEAN_ENV,
        check=True,
    )
    (path,) = dist.glob("torchcontact-*.whl")
    return path


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment with the wheel installed; returns its interpreter."""
    env = tmp_path_factory.mktemp("venv")
    venv.create(env, with_pip=False)
    python = env / "bin" / "python"
    subprocess.run(
        [
            *PIP,
            "--python",
            str(python),
            "install",
            "--no-deps",
            "--no-index",
            *CONSTRAINTS,
            str(wheel),
        ],
        env=CLEAN_ENV,
        check=True,
    )
    # Only now the dependencies: pip must not take them (or an editable torchcontact among
    # them) for an installed torchcontact.
    purelib = subprocess.run(
        [str(python), "-I", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    dependencies = {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}
    (Path(purelib) / "_torchcontact_test_dependencies.pth").write_text(
        "".join(f"{path}\n" for path in sorted(dependencies))
    )
    return python


def run_outside(python: Path, code: str, tmp_path: Path) -> dict:
    """Run ``code`` in isolated mode from an empty directory, ``tmp_path / "cwd"``.

    Returns:
        The JSON object that ``code`` prints last.
    """
    (tmp_path / "cwd").mkdir()
    (tmp_path / "home").mkdir()
    result = subprocess.run(
        [str(python), "-I", "-c", code],
        capture_output=True,
        text=True,
        cwd=tmp_path / "cwd",
        env={"PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg", "HOME": str(tmp_path / "home")},
        check=False,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


IMPORTED_FROM = (
    "import json, sys, torchcontact; "
    "found = {'file': torchcontact.__file__, 'prefix': sys.prefix, 'path': sys.path}"
)


def assert_from_wheel(found: dict, python: Path) -> None:
    prefix = python.parents[1]
    assert Path(found["prefix"]) == prefix
    assert Path(found["file"]).is_relative_to(prefix), found["file"]
    assert not any(Path(entry) == ROOT for entry in found["path"] if entry)


def test_wheel_holds_every_module_and_the_package_data(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "torchcontact").rglob("*.py")}
    assert modules - names == set(), "modules missing from the wheel (a folder without __init__?)"
    assert {f"torchcontact/models/{name}.urdf" for name in ROBOT_NAMES} <= names
    assert "torchcontact/py.typed" in names
    assert not any(name.startswith(("tests/", "models/", "train/")) for name in names)


def test_readme_example_runs_from_the_installed_wheel(installed: Path, tmp_path: Path) -> None:
    text = (ROOT / "README.md").read_text()
    example = re.search(r"```python\n(.*?)```", text, flags=re.DOTALL)
    assert example is not None, "README has no python example"
    code = (
        f"{IMPORTED_FROM}\n"
        f"exec(compile({example.group(1)!r}, 'README.md', 'exec'), {{}})\n"
        "print(json.dumps(found))\n"
    )
    found = run_outside(installed, code, tmp_path)
    assert_from_wheel(found, installed)
    assert not any((tmp_path / "cwd").iterdir()), "the example wrote into the working directory"


def test_robots_load_from_the_installed_wheel(installed: Path, tmp_path: Path) -> None:
    code = (
        f"{IMPORTED_FROM}\n"
        "from torchcontact import robots\n"
        "robot = robots.load('wam7_bhand')\n"
        "found.update(models=str(robots.models_dir()), dof=robot.dof)\n"
        "print(json.dumps(found))\n"
    )
    found = run_outside(installed, code, tmp_path)
    assert_from_wheel(found, installed)
    assert Path(found["models"]).is_relative_to(installed.parents[1])
    assert found["dof"] == 11


def test_robots_tutorial_runs_from_the_installed_wheel(installed: Path, tmp_path: Path) -> None:
    """Tutorial 06 (the one that reads package data) as a script, in fast mode."""
    (tmp_path / "cwd").mkdir()
    result = subprocess.run(
        [str(installed), "-I", str(ROOT / "tutorials" / "06_robots.py")],
        capture_output=True,
        text=True,
        cwd=tmp_path / "cwd",
        env={"PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg", "HOME": str(tmp_path)}
        | {"TORCHCONTACT_FAST": "1", "TORCHCONTACT_OUT": str(tmp_path / "out")},
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert not any((tmp_path / "cwd").iterdir())
