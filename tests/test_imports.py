"""Every module of ours imports, and every import of ours names something that exists.

Two checks, so that a module moved or renamed leaves no stale path behind:

- each module of the packages is imported (importlib), generated gRPC code aside;
- each file of the packages, of bench/, docker/ and tests/ is read as source (ast, nothing run) and
  every import in it, at any depth (inside functions and under ``if TYPE_CHECKING:`` too), that
  names one of our packages must resolve: ``import a.b`` and ``from a.b import c`` need the module
  ``a.b`` (``importlib.util.find_spec``), and ``c`` must be an attribute or a submodule of it.
  Lazy imports run only on some paths, so only reading them finds them all.
"""

from __future__ import annotations

import ast
import importlib
import importlib.machinery
import importlib.util
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("geomatch", "geomatch_core", "service", "workers", "geomatch_app")
GENERATED = ("_pb2.py", "_pb2_grpc.py")
# modules that do a process's work when imported, so they are read here but not imported:
# geomatch_app.asgi builds the service (storage folders, the database, worker threads) for uvicorn
NOT_IMPORTED = {"geomatch_app.asgi": "builds the service on import"}


def _files(folders: tuple[str, ...]) -> Iterator[Path]:
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if not path.name.endswith(GENERATED):
                yield path


def _module_name(path: Path) -> str | None:
    """The dotted name of a file of our packages (None for bench/, docker/ and tests/ files)."""
    if not path.is_relative_to(ROOT):
        return None
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[0] not in PACKAGES:
        return None
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = [name for path in _files(PACKAGES) if (name := _module_name(path)) is not None]
SOURCES = list(_files((*PACKAGES, "bench", "docker", "tests")))


def _ours(module: str) -> bool:
    return module.split(".")[0] in PACKAGES


def _imports(path: Path) -> Iterator[tuple[int, str, str | None]]:
    """(line, module, name) for every import of ours in the file, at any depth; ``name`` is None
    for ``import module``."""
    name = _module_name(path)
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if _ours(alias.name):
                    yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if name is None:  # tests/ and bench/ import their own helpers relatively
                    continue
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if path.name == "__init__.py" else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if _ours(module):
                for alias in node.names:
                    yield node.lineno, module, alias.name


def _here(module: str) -> importlib.machinery.ModuleSpec | None:
    """The module's spec when it is a file of this checkout: an editable install of another
    checkout on sys.path would otherwise answer for a module that is gone from this one."""
    try:
        spec = importlib.util.find_spec(module)
    except ModuleNotFoundError:  # a parent package is missing
        return None
    if spec is None or spec.origin is None or not Path(spec.origin).is_relative_to(ROOT):
        return None
    return spec


def _missing(module: str, name: str | None) -> str | None:
    """Why ``module`` (and ``name`` from it) does not resolve, or None when it does."""
    spec = _here(module)
    if spec is None:
        return f"no module {module}"
    if name is None or name == "*":
        return None
    if spec.submodule_search_locations is not None and _here(f"{module}.{name}") is not None:
        return None
    if hasattr(importlib.import_module(module), name):
        return None
    return f"{module} has no {name}"


@pytest.mark.parametrize("module", MODULES)
def test_module_imports(module: str) -> None:
    if module in NOT_IMPORTED:
        pytest.skip(NOT_IMPORTED[module])
    imported = importlib.import_module(module)
    missing = [n for n in getattr(imported, "__all__", ()) if not hasattr(imported, n)]
    assert not missing, f"{module}.__all__ names what it does not have: {missing}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_resolve(path: Path) -> None:
    bad = []
    for line, module, name in _imports(path):
        why = _missing(module, name)
        if why is not None:
            spelled = f"from {module} import {name}" if name is not None else f"import {module}"
            bad.append(f"{path.relative_to(ROOT)}:{line}: {spelled}: {why}")
    assert not bad, "stale imports:\n" + "\n".join(bad)


def test_the_check_sees_a_stale_path(tmp_path: Path) -> None:
    """The check itself: a lazy import of a module that is not there, and of a name that is not."""
    stale = tmp_path / "stale.py"
    stale.write_text(
        "def f():\n    from geomatch.viewgraph import filter_database\n"
        "    from geomatch.sfm.viewgraph import no_such_name\n"
    )
    found = [_missing(module, name) for _, module, name in sorted(_imports(stale))]
    assert found == ["no module geomatch.viewgraph", "geomatch.sfm.viewgraph has no no_such_name"]
