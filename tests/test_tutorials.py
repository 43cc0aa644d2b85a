"""Every tutorial (jupytext percent-format ``.py``) runs as a notebook, in fast mode, as a user
of the installed package would run it: from an empty working directory outside the repository,
against the torchcontact these tests import, writing only under the folder it is given
(``TORCHCONTACT_OUT``) or, without one, under a new temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jupytext
import nbclient
import nbformat
import pytest

import torchcontact

TUTORIALS = sorted((Path(__file__).resolve().parents[1] / "tutorials").glob("[0-9][0-9]_*.py"))
PACKAGE = Path(torchcontact.__file__).resolve()


def test_tutorials_exist() -> None:
    assert TUTORIALS, "no tutorials found"


def same_package_cell() -> nbformat.NotebookNode:
    """A first cell that fails unless the kernel imports the torchcontact the tests import."""
    return nbformat.v4.new_code_cell(
        "import os\n"
        "import torchcontact\n"
        f"expected = {str(PACKAGE)!r}\n"
        "assert os.path.realpath(torchcontact.__file__) == expected, (\n"
        "    f'the kernel imports {torchcontact.__file__}, the tests import {expected}: '\n"
        "    'install this checkout (pip install -e .) or put it on PYTHONPATH'\n"
        ")\n"
    )


@pytest.mark.parametrize("path", TUTORIALS, ids=[p.stem for p in TUTORIALS])
def test_tutorial_executes(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cwd, out = tmp_path / "cwd", tmp_path / "out"
    cwd.mkdir()
    monkeypatch.setenv("TORCHCONTACT_FAST", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("TORCHCONTACT_OUT", str(out))
    notebook = jupytext.read(path)
    notebook.cells.insert(0, same_package_cell())
    client = nbclient.NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}
    )
    client.execute()
    assert not any(cwd.iterdir()), "the tutorial wrote into its working directory"
    if "savefig" in path.read_text():
        assert any(out.glob("*.png")), f"no figure in {out}"


@pytest.mark.parametrize(
    "path",
    [p for p in TUTORIALS if "TORCHCONTACT_OUT" in p.read_text()],
    ids=lambda p: p.stem,
)
def test_tutorial_output_defaults_to_a_new_temporary_folder(path: Path, tmp_path: Path) -> None:
    """The tutorial's cells up to the one that picks ``OUT``, without ``TORCHCONTACT_OUT``."""
    cells = [cell.source for cell in jupytext.read(path).cells if cell.cell_type == "code"]
    setup = next(i for i, source in enumerate(cells) if "TORCHCONTACT_OUT" in source)
    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("TORCHCONTACT_")}
    env.update(TMPDIR=str(tmp), MPLBACKEND="Agg", PYTHONPATH=str(PACKAGE.parents[1]))
    code = "\n".join([*cells[: setup + 1], "print(OUT.resolve())"])
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, env=env, check=False
    )
    assert result.returncode == 0, result.stderr
    out = Path(result.stdout.splitlines()[-1])
    assert out.is_dir()
    assert out.parent == tmp.resolve()
    assert not any(cwd.iterdir())
