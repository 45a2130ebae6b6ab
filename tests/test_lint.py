"""Pyflakes checks (ruff, rules in ``pyproject.toml``) over the project's code: an undefined name or a
shadowed import fails only on the path that reaches it, which a test may never take."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_code_passes_pyflakes_checks():
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise", "--no-cache",
                          "benchmark", "methods", "annotations", "tests"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


OWN_PACKAGES = ("benchmark", "methods", "annotations")


def _own_imports(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, absolute module, imported name or None) of every import of the project's own code in ``path``,
    those inside functions too."""
    import ast

    package = list(path.relative_to(ROOT).parts[:-1])
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                module = ".".join(package[:len(package) - node.level + 1] + ([module] if module else []))
            found += [(node.lineno, module, a.name) for a in node.names]
    return [f for f in found if f[1].split(".")[0] in OWN_PACKAGES]


def test_every_import_of_the_projects_code_resolves():
    """An import inside a test that only runs on a GPU (or another path the suite never takes) must still name
    a module and a name that exist: a moved helper otherwise breaks that path unseen."""
    import importlib

    files = [p for d in (*OWN_PACKAGES, "tests") for p in sorted((ROOT / d).rglob("*.py"))]
    broken = []
    for path in files:
        for line, module, name in _own_imports(path):
            try:
                mod = importlib.import_module(module)
            except ModuleNotFoundError as exc:
                if exc.name and exc.name.split(".")[0] in OWN_PACKAGES:
                    broken.append(f"{path.relative_to(ROOT)}:{line}: no module {module}")
                continue
            if name and name != "*" and not hasattr(mod, name):
                try:
                    importlib.import_module(f"{module}.{name}")
                except ModuleNotFoundError:
                    broken.append(f"{path.relative_to(ROOT)}:{line}: {module} has no {name}")
    assert len(files) > 100
    assert not broken, "\n".join(broken)
