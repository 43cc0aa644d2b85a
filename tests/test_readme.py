"""The README's examples run as written."""

from __future__ import annotations

import re
from pathlib import Path


def test_readme_examples_run() -> None:
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)
    assert len(blocks) >= 2, "README lost its examples"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    assert namespace["exact"].mode.tolist() == [[3, 3]]  # sliding along −x at both corners
    exec(compile(blocks[1], "README.md", "exec"), namespace)
    assert tuple(namespace["run"].q.shape) == (41, 1, 3)
    assert namespace["run"].v[-1].abs().max().item() < 1e-12  # stopped at 0.255 s
