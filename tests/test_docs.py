"""The documentation site builds in strict mode, and its API reference is complete.

``mkdocs build --strict`` fails on a broken link or cross-reference, a page missing from the
navigation and a docstring that mkdocstrings cannot parse. The API pages render each
subpackage from its docstrings; every name of the subpackage's ``__all__`` must get its own
entry there (an anchor ``torchcontact.<subpackage>.<name>``).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES = ("contact", "sim", "geometry", "filters", "states", "rl", "envs", "robots")
SUBPACKAGES += ("experiments",)
TUTORIALS = sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py"))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site, built once from the checkout into a temporary folder."""
    out = tmp_path_factory.mktemp("site")
    start = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=os.environ | {"NO_MKDOCS_2_WARNING": "1"},
        timeout=120,
        check=False,
    )
    elapsed = time.monotonic() - start
    assert result.returncode == 0, result.stderr[-5000:]
    assert elapsed < 60, f"the strict build took {elapsed:.0f} s"
    return out


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_api_page_lists_every_public_name(site: Path, name: str) -> None:
    module = importlib.import_module(f"torchcontact.{name}")
    html = (site / "api" / name / "index.html").read_text()
    anchors = set(re.findall(r'id="(torchcontact\.[\w.]+)"', html))
    missing = [n for n in module.__all__ if f"torchcontact.{name}.{n}" not in anchors]
    assert not missing, f"api/{name}.md does not document {missing}"


def test_every_tutorial_is_a_page(site: Path) -> None:
    assert TUTORIALS
    for path in TUTORIALS:
        page = site / "tutorials" / path.stem / "index.html"
        assert page.is_file(), f"{path.name} was not rendered"
        assert 'class="highlight"' in page.read_text()  # its code cells


def test_pages_show_the_figures(site: Path) -> None:
    figures = {
        "": "triangle_grasp.png",
        "experiments/triangle-grasp": "triangle_grasp.png",
        "experiments/peg-in-hole": "peg_planning.png",
    }
    for page, figure in figures.items():
        assert f"images/{figure}" in (site / page / "index.html").read_text()
        assert (site / "images" / figure).is_file()


def test_no_reference_to_files_outside_the_repository() -> None:
    texts = [ROOT / "README.md", ROOT / "mkdocs.yml", *sorted((ROOT / "docs").rglob("*.md"))]
    for path in texts:
        text = path.read_text()
        for pattern in ("DESIGN.md", "STYLE.md", "the issue"):
            assert pattern not in text, f"{path.relative_to(ROOT)} mentions {pattern!r}"


def test_hand_written_constants_match_the_code() -> None:
    """docs/api/envs.md lists the constants that mkdocstrings cannot see (tuple assignments)."""
    envs = importlib.import_module("torchcontact.envs")
    rows = re.findall(r"`(\w+)` \| (\d+) \|", (ROOT / "docs" / "api" / "envs.md").read_text())
    assert len(rows) == 6
    for name, value in rows:
        assert getattr(envs, name) == int(value), name


PAGES_WITH_CODE = ("getting-started.md", "guide/contact.md", "guide/simulator.md")
PAGES_WITH_CODE += ("guide/filters.md", "guide/robots.md", "logs.md", "api/geometry.md")


@pytest.mark.parametrize("page", PAGES_WITH_CODE)
def test_page_examples_run(page: str) -> None:
    """The Python blocks of a page run in order, as one script."""
    text = (ROOT / "docs" / page).read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)
    assert blocks, f"{page} lost its examples"
    threads = torch.get_num_threads()
    try:
        exec(compile("\n".join(blocks), page, "exec"), {})
    finally:
        torch.set_num_threads(threads)


def test_every_page_with_python_is_run() -> None:
    pages = {
        path.relative_to(ROOT / "docs").as_posix()
        for path in (ROOT / "docs").rglob("*.md")
        if "```python" in path.read_text()
    }
    assert pages == set(PAGES_WITH_CODE)


def test_rst_markup_becomes_markdown() -> None:
    """The griffe extension of the API pages (docs/_ext/griffe_rst.py)."""
    spec = importlib.util.spec_from_file_location("griffe_rst", ROOT / "docs/_ext/griffe_rst.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    convert = module.convert
    assert convert(":class:`Gaussian`") == "`Gaussian`"
    assert convert(":func:`~torchcontact.contact.solve_mode`") == (
        '<autoref identifier="torchcontact.contact.solve_mode" optional>'
        "<code>solve_mode()</code></autoref>"
    )
    assert convert("so :math:`x^2`.") == "so $x^2$."
    block = "Step:\n\n.. math::\n\n    a &= b \\\\\n    c &= d\n\nwhere"
    assert convert(block) == (
        "Step:\n\n$$\n\\begin{aligned}\na &= b \\\\\nc &= d\n\\end{aligned}\n$$\n\nwhere"
    )
    assert convert(".. math:: y = F x\n\nso") == "$$\ny = F x\n$$\n\nso"
