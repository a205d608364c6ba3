"""The layout's rules, read from the source (ast, nothing imported):

- imports point one way: geomatch (the library) <- geomatch_core <- {service, workers} <- geomatch_app (the
  composition root); service and workers never import each other;
- inside the library, a folder imports only folders ranked below it (RANKS);
- no import loops between modules (lazy imports inside functions count: they load the same code;
  imports under ``if TYPE_CHECKING:`` count too: a loop of annotations is two modules that cannot
  be read apart);
- no module touches another module's private names (``x._name``, ``from m import _name``), except
  the tests of that module (``tests/test_<module>.py``, by the module's name or by its path in
  geomatch with ``_`` for the dots: tests/test_synth_indoor.py for geomatch.synth.indoor) and the
  exceptions listed in ALLOWED.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"geomatch": 0, "geomatch_core": 1, "service": 2, "workers": 2, "geomatch_app": 3}
PACKAGES = tuple(LAYERS)

RANKS = {
    # the utilities: options, images, metadata, memory (byte-bounded caches), the survey report
    "geomatch.options": 0,
    "geomatch.imageio": 0,
    "geomatch.metadata": 0,
    "geomatch.memory": 0,
    "geomatch.report": 0,
    # epipolar geometry: Sampson distances, fundamental matrices
    "geomatch.epipolar": 0,
    # a run's image folder: its files and their decoded pixels
    "geomatch.imagefolder": 0,
    # backbones (whose dense head refines on the epipolar prior); geodesy, GPS, georeferencing
    "geomatch.features": 1,
    "geomatch.geo": 1,
    # one pair (puts the backbones together); many pairs into a model (georeferenced by geo)
    "geomatch.matching": 2,
    "geomatch.sfm": 2,
    # judging a model against ground truth (with sfm's statistics); exporting a model
    "geomatch.eval": 3,
    "geomatch.export": 3,
    # synthetic scenes with ground truth (the indoor pairs score themselves with eval.pose)
    "geomatch.synth": 4,
    # the map of a georeferenced model: DSM and orthophoto (export's frames, the photos)
    "geomatch.ortho": 4,
    # the pipeline's stages over all of it: which images are aerial, the plan, each pair matched
    # and written, the model mapped and georeferenced, the summary; the in-process runner
    "geomatch.pipeline": 5,
    # what runs the pipeline for a user: the demo; drawings of matches
    "geomatch.demo": 6,
    "geomatch.viz": 6,
    # new photos placed in a project's model: a folder over the pipeline's matching and writes
    "geomatch.localize": 6,
    # the commands over all of it, and the package's public names
    "geomatch.cli": 7,
    "geomatch": 7,
}
"""Ranks of the parts of the library: its folders (sub-packages) and its top-level modules.

Why: a folder is a family of modules a reader takes in as one (hloc-style). Ranked, the families
form a chain a reader can climb from the bottom, each one understood without the ones above it,
and a change to a family can break only the families above it. A part imports only parts ranked
below it; two folders of one rank (matching and sfm: one pair / many pairs into a model) never
import each other. Top-level modules of one rank may import each other (metadata reads imageio's
error, cli runs pipeline and demo): they are single modules, whose loops test_no_import_loops
forbids. A new folder or top-level module fails test_every_part_has_a_rank until it is ranked here.
"""


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path.name.endswith(("_pb2.py", "_pb2_grpc.py")):  # generated
                continue
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> Iterator[tuple[str, int]]:
    """(imported module of ours, line) for every import in the file, at any depth (under
    ``if TYPE_CHECKING:`` too)."""
    is_pkg = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _ours(alias.name)
                if target:
                    yield target, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for alias in node.names:
                target = _ours(f"{module}.{alias.name}") or _ours(module)
                if target:
                    yield target, node.lineno


def _ours(dotted: str) -> str | None:
    parts = dotted.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in MODULES:
            return candidate
        parts.pop()
    return None


def _graph() -> dict[str, dict[str, int]]:
    graph: dict[str, dict[str, int]] = {}
    for name, path in MODULES.items():
        edges = graph.setdefault(name, {})
        for target, line in _imports(name, path):
            if target != name:
                edges.setdefault(target, line)
    return graph


def _package(module: str) -> str:
    return module.split(".")[0]


def test_imports_point_one_way() -> None:
    bad = []
    for source, targets in _graph().items():
        for target, line in targets.items():
            a, b = _package(source), _package(target)
            if a == b:
                continue
            if LAYERS[b] >= LAYERS[a]:
                bad.append(f"{MODULES[source].relative_to(ROOT)}:{line}: {source} imports {target}")
    assert not bad, "imports against the layering " + str(LAYERS) + ":\n" + "\n".join(bad)


def _part(module: str) -> str:
    """The part of the library a module of geomatch belongs to: its folder, or itself at the top."""
    parts = module.split(".")
    if len(parts) > 2 or (len(parts) == 2 and MODULES[module].name == "__init__.py"):
        return ".".join(parts[:2])
    return module


def _folder(part: str) -> bool:
    return part.count(".") == 1 and (ROOT / Path(*part.split("."))).is_dir()


def test_every_part_has_a_rank() -> None:
    unranked = sorted({_part(m) for m in MODULES if _package(m) == "geomatch"} - set(RANKS))
    assert not unranked, f"parts of geomatch without a rank in RANKS: {unranked}"


def test_folders_import_only_folders_below() -> None:
    bad = []
    for source, targets in _graph().items():
        if _package(source) != "geomatch":
            continue
        a = _part(source)
        for target, line in targets.items():
            b = _part(target)
            if _package(target) != "geomatch" or a == b or RANKS[b] < RANKS[a]:
                continue
            if RANKS[b] == RANKS[a] and not _folder(a) and not _folder(b):
                continue  # top-level modules of one rank
            bad.append(
                f"{MODULES[source].relative_to(ROOT)}:{line}: {source} (rank {RANKS[a]}) imports "
                f"{target} (rank {RANKS[b]})"
            )
    assert not bad, "imports against the ranks of geomatch's parts:\n" + "\n".join(bad)


def test_no_import_loops() -> None:
    graph = _graph()
    # Tarjan's strongly connected components
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    loops: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                loops.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not loops, "import loops:\n" + "\n".join(" <-> ".join(c) for c in loops)


# -- privates ------------------------------------------------------------------------------------
def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _defined_privates(tree: ast.AST) -> set[str]:
    """Private names a file defines: functions, classes, assignments, attributes set on objects."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
        elif isinstance(node, ast.alias):
            names.add(node.asname or node.name.split(".")[0])
    return {n for n in names if _private(n)}


_PRIVATES: dict[str, set[str]] = {}


def _module_privates() -> dict[str, set[str]]:
    if not _PRIVATES:
        _PRIVATES.update(
            {name: _defined_privates(ast.parse(path.read_text())) for name, path in MODULES.items()}
        )
    return _PRIVATES


# Known exceptions: argparse has no public way to list a parser's subcommands.
ALLOWED = {
    ("tests/test_deploy.py", "_actions"),
}


def _files() -> Iterator[Path]:
    for folder in (*PACKAGES, "bench", "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if not path.name.endswith(("_pb2.py", "_pb2_grpc.py")):
                yield path


def _under_test(path: Path, privates: dict[str, set[str]]) -> set[str]:
    """What tests/test_<module>.py may touch: the privates of the library module it is named after,
    by its own name or by its path under geomatch with ``_`` for the dots (tests/test_viewgraph.py:
    geomatch.sfm.viewgraph; tests/test_synth_indoor.py: geomatch.synth.indoor)."""
    if not (path.is_relative_to(ROOT / "tests") and path.name.startswith("test_")):
        return set()
    name = path.stem.removeprefix("test_")
    out: set[str] = set()
    for module, names in privates.items():
        parts = module.split(".")
        if parts[0] == "geomatch" and len(parts) > 1 and name in (parts[-1], "_".join(parts[1:])):
            out |= names
    return out


@pytest.mark.parametrize("path", list(_files()), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_foreign_privates(path: Path) -> None:
    tree = ast.parse(path.read_text(), str(path))
    rel = path.relative_to(ROOT).as_posix()
    own = _defined_privates(tree) | _under_test(path, _module_privates())
    allowed = {name for where, name in ALLOWED if where == rel}
    own |= allowed
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr) and node.attr not in own:
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            bad.append(f"{node.lineno}: .{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            bad += [
                f"{node.lineno}: import {a.name}"
                for a in node.names
                if _private(a.name) and a.name not in allowed
            ]
    assert not bad, f"{path.relative_to(ROOT)} touches other modules' private names:\n" + "\n".join(bad)
