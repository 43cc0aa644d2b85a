"""A griffe extension: the reStructuredText markup in the library's docstrings, as Markdown.

The docstrings are Google style, with a few Sphinx roles (``:class:`~torchcontact.x.Y```,
``:func:``, ``:meth:``, ``:attr:``, ``:data:``, ``:mod:``), inline math (``:math:`...```) and
``.. math::`` blocks. mkdocstrings renders Markdown, so before the docstrings are parsed:

- a role becomes inline code, linked to the object's API entry when that entry exists (an
  optional cross-reference: a name the API pages do not document stays plain code);
- inline math becomes ``$...$`` and a ``.. math::`` block ``$$...$$`` (rendered by MathJax).
"""

from __future__ import annotations

import re
import textwrap
from typing import Any

from griffe import Extension, Object

ROLE = re.compile(r":(?:class|func|meth|attr|data|mod|obj|exc):`(~?)([^`]+)`")
MATH = re.compile(r":math:`([^`]+)`")
MATH_BLOCK = re.compile(
    r"^([ \t]*)\.\. math::[ \t]*(.*)\n((?:[ \t]*\n|\1[ \t]+\S.*\n)*)", re.MULTILINE
)


def _role(match: re.Match[str]) -> str:
    short, target = match.group(1) == "~", match.group(2)
    target = target.rstrip("()")
    shown = target.rsplit(".", 1)[-1] if short else target
    if match.group(0).startswith((":func:", ":meth:")):
        shown += "()"
    if target.startswith("torchcontact."):
        return f'<autoref identifier="{target}" optional><code>{shown}</code></autoref>'
    return f"`{shown}`"


def _math_block(match: re.Match[str]) -> str:
    indent, first, rest = match.group(1), match.group(2).strip(), match.group(3)
    body = "\n".join(filter(None, (first, textwrap.dedent(rest).strip("\n"))))
    if "&" in body or "\\\\" in body:  # several aligned lines: one aligned environment
        body = f"\\begin{{aligned}}\n{body}\n\\end{{aligned}}"
    return f"{indent}$$\n{textwrap.indent(body, indent)}\n{indent}$$\n\n"


def convert(text: str) -> str:
    """The docstring ``text`` with its reStructuredText markup in Markdown."""
    text = MATH_BLOCK.sub(_math_block, text if text.endswith("\n") else text + "\n")
    text = MATH.sub(lambda m: f"${m.group(1)}$", text)
    return ROLE.sub(_role, text).rstrip("\n")


class RstToMarkdown(Extension):
    """Convert every docstring of the loaded package (see the module docstring)."""

    def on_object(self, *, obj: Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value)
