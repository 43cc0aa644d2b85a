"""MkDocs hooks of the documentation site: the tutorials, rendered as pages.

The tutorials are jupytext percent-format scripts (``tutorials/NN_name.py``). Each becomes the
page ``tutorials/NN_name.md`` at build time: markdown cells as they are, code cells as Python
blocks. Nothing is executed (the test suite runs the tutorials), so the pages show code and
explanations, not outputs.
"""

from __future__ import annotations

from pathlib import Path

import jupytext
from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
TUTORIALS = ROOT / "tutorials"


def tutorial_markdown(path: Path) -> str:
    """The Markdown page of one jupytext percent-format tutorial."""
    notebook = jupytext.reads(path.read_text(), fmt="py:percent")
    parts: list[str] = []
    for cell in notebook.cells:
        source = cell.source.strip("\n")
        if not source:
            continue
        if cell.cell_type == "markdown":
            parts.append(source)
        elif cell.cell_type == "code":
            parts.append(f"```python\n{source}\n```")
    if parts and parts[0].startswith("# "):  # the title first, then where the file is
        title, _, rest = parts[0].partition("\n")
        parts[0:1] = [title, _source_note(path), *([rest.strip("\n")] if rest.strip() else [])]
    else:
        parts.insert(0, _source_note(path))
    return "\n\n".join(parts) + "\n"


def _source_note(path: Path) -> str:
    name = path.relative_to(ROOT).as_posix()
    return (
        f'!!! note "Source: `{name}`"\n'
        f"    The notebook `{name}` (jupytext percent format), shown without its outputs.\n"
        f"    Run it with `python {name}` or open it as a notebook ([how](index.md)):\n"
        "    `TORCHCONTACT_FAST=1` runs it at small sizes, `TORCHCONTACT_OUT=folder` chooses\n"
        "    where it writes its figures."
    )


def tutorial_index() -> str:
    """The tutorials' overview page: tutorials/README.md with links to the rendered pages."""
    text = (TUTORIALS / "README.md").read_text()
    for path in sorted(TUTORIALS.glob("[0-9][0-9]_*.py")):
        text = text.replace(f"`{path.name}`", f"[`{path.name}`]({path.stem}.md)")
    return text


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the tutorials' pages to the site."""
    files.append(File.generated(config, "tutorials/index.md", content=tutorial_index()))
    for path in sorted(TUTORIALS.glob("[0-9][0-9]_*.py")):
        files.append(
            File.generated(config, f"tutorials/{path.stem}.md", content=tutorial_markdown(path))
        )
    return files
