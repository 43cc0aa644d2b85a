"""A light import graph: the contact solvers load without the optional-looking heavy packages."""

from __future__ import annotations

import subprocess
import sys


def _loaded_after(statement: str, modules: tuple[str, ...]) -> list[str]:
    code = f"import sys\n{statement}\nprint(' '.join(m for m in {modules!r} if m in sys.modules))"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    return result.stdout.split()


HEAVY = ("gymnasium", "pytorch_kinematics", "matplotlib", "qpsolvers", "scipy", "networkx")


def test_importing_the_contact_solvers_loads_no_heavy_package() -> None:
    assert _loaded_after("import torchcontact.contact", HEAVY) == []


def test_subpackages_load_on_first_attribute_access() -> None:
    statement = "import torchcontact\nassert torchcontact.filters.RBPF"
    loaded = _loaded_after(statement, ("torchcontact.filters", "torchcontact.envs", "gymnasium"))
    assert loaded == ["torchcontact.filters"]
