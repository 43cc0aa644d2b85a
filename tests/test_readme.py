"""The README's example runs as written and tracks the box as the README says.

tests/test_packaging.py runs the same (first) block from an installed wheel.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import torch


def test_readme_example_tracks_the_box_through_the_occlusion() -> None:
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)
    assert blocks, "README lost its example"
    namespace: dict = {}
    threads = torch.get_num_threads()
    try:
        exec(compile(blocks[0], "README.md", "exec"), namespace)
    finally:
        torch.set_num_threads(threads)  # the example runs on one thread; the next tests not
    error, y, box = namespace["error"], namespace["y"], namespace["box"]
    assert error.shape == (60,)
    assert bool(torch.isfinite(error).all())
    hidden = torch.isnan(y[:, 0])
    assert hidden.nonzero().flatten().tolist() == list(range(8, 18))
    sigma = 5.0  # mm, the camera's noise per axis
    # The camera's own position error, E|e| = σ √(π/2) ≈ 6.3 mm for a 2-D Gaussian error.
    camera = 1e3 * (y[~hidden, :2] - box[~hidden, :2]).norm(dim=-1)
    assert abs(camera.mean().item() - sigma * math.sqrt(math.pi / 2)) < 1.5
    # The filter averages the camera and knows the dynamics: below σ on average, and below σ
    # while hidden, although the box moves more than 3σ in that time (holding the last pose
    # would be that far off).
    assert error.mean().item() < sigma
    assert error[hidden].max().item() < sigma
    assert 1e3 * (box[17, 0] - box[7, 0]).item() > 3 * sigma
