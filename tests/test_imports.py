"""A light import graph: the contact solvers load without the optional-looking heavy packages."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path


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


def _private_imports(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of each import of ``torchcontact.X._y`` (or ``from torchcontact.X
    import _y``) in ``path``."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if len(parts) >= 3 and parts[0] == "torchcontact" and parts[2].startswith("_"):
                found.append((node.lineno, ".".join(parts[:3])))
    return sorted(set(found))


def test_no_module_imports_another_packages_private_modules() -> None:
    # A module of torchcontact/X (or a test of tests/X) may import X's private modules; every
    # other import goes through a package's public names.
    root = Path(__file__).resolve().parents[1]
    offending = []
    for folder in ("torchcontact", "tests", "benchmarks", "train", "tutorials"):
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root).parts
            own = parts[1] if len(parts) > 2 and folder in ("torchcontact", "tests") else None
            for line, module in _private_imports(path):
                if module.split(".")[1] != own:
                    offending.append(f"{path.relative_to(root)}:{line}: {module}")
    assert offending == []
