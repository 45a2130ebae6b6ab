"""The import contract: every module imports only its own layer or a lower one, function-local imports
included (a cycle hidden inside a function is still a cycle).

Layers, lowest first:

0. kernel: ``benchmark.core`` (scene and annotation data models, truth, protocol, errors, atomic writes);
1. data: loaders, the synthetic generator, metrics, the predictions format, the annotation formats
   (``annotations`` but its tool);
2. methods: ``methods`` (they stand on the kernel only: never on data, harness or studies);
3. harness: runner, results, predictions, leaderboard, paper tables, plots; it reaches methods only
   through the registry and the method API (``methods``, ``methods.registry``, ``methods.api``);
4. studies: ``benchmark.studies`` (experiments: ceilings, gaps, ablations, speed measurements);
5. app: the CLI (``benchmark.cli``, ``benchmark.commands``) and the annotation tool.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("benchmark", "methods", "annotations")
LAYER_NAMES = ("kernel", "data", "methods", "harness", "studies", "app")
HARNESS_DOORS = ("methods", "methods.registry", "methods.api")
"""The modules of ``methods`` the harness may import."""


def layer_of(module: str) -> int:
    def under(*prefixes: str) -> bool:
        return any(module == p or module.startswith(p + ".") for p in prefixes)

    if module == "benchmark" or under("benchmark.core"):
        return 0
    if under("benchmark.loaders", "benchmark.synthetic", "benchmark.metrics", "benchmark.predictions"):
        return 1
    if under("annotations.tool", "annotations.assist"):
        return 5
    if under("annotations"):
        return 1
    if under("methods"):
        return 2
    if under("benchmark.studies"):
        return 4
    if under("benchmark.cli", "benchmark.commands"):
        return 5
    if under("benchmark"):
        return 3
    raise AssertionError(f"module {module} has no layer: add it to tests/test_import_layers.py")


def module_name(path: Path) -> tuple[str, bool]:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_package else parts), is_package


def imported_modules(path: Path, source: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute module) of every import of the project in ``path``, wherever it stands."""
    module, is_package = module_name(path)
    out = []
    for node in ast.walk(ast.parse(path.read_text() if source is None else source, filename=str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                names = [".".join(base + ([node.module] if node.module else []))]
                if not node.module:  # "from . import x": x is a module of that package
                    names = [f"{names[0]}.{a.name}" for a in node.names]
            else:
                names = [node.module or ""]
        else:
            continue
        out += [(node.lineno, n) for n in names if n.split(".")[0] in PACKAGES]
    return out


def violations(path: Path, source: str | None = None) -> list[str]:
    module, _ = module_name(path)
    own = layer_of(module)
    found = []
    for line, target in imported_modules(path, source):
        theirs = layer_of(target)
        where = f"{path.relative_to(ROOT)}:{line}: {module} ({LAYER_NAMES[own]}) imports {target}"
        if theirs > own:
            found.append(f"{where} ({LAYER_NAMES[theirs]}): an upward import")
        elif own == 2 and theirs == 1:
            found.append(f"{where} (data): methods stand on the kernel only")
        elif own == 3 and theirs == 2 and target not in HARNESS_DOORS:
            found.append(f"{where}: the harness reaches methods through {', '.join(HARNESS_DOORS)} only")
    return found


def project_files() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_no_module_imports_upward():
    found = [v for p in project_files() for v in violations(p)]
    assert not found, "\n".join(found)


@pytest.mark.parametrize("planted, source", [
    ("benchmark/core/planted_upward.py", "from benchmark.runner import evaluate\n"),
    ("methods/planted_upward.py", "def f():\n    from benchmark.loaders import load_scene\n"),
    ("benchmark/planted_upward.py", "from methods.fields.relevance import relevance_maps\n"),
])
def test_a_planted_upward_import_is_found(planted, source):
    assert violations(ROOT / planted, source)
