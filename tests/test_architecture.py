"""The layering rule (DESIGN.md), checked on the source: one import name, one bottom layer,
no arrow pointing up, no import cycle - function-local imports included.

Layers, bottom to top:
  core  (``core/``, the ``facelab`` package's own modules) imports only itself;
  stimuli, analysis  import core and themselves;
  experiment (sessions, CLI)  may import everything.

``python -m tests.test_architecture`` prints the package graph.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
import zipfile
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
PACKAGE_DIRS: dict[str, str] = PYPROJECT["tool"]["setuptools"]["package-dir"]

#: layer of each top-level part of facelab; "core" is the package's own modules
ALLOWED = {
    "core": {"core"},
    "stimuli": {"core", "stimuli"},
    "analysis": {"core", "analysis"},
    "protocols": set(),
    "experiment": {"core", "stimuli", "analysis", "experiment", "protocols"},
}
#: heavy or display-bound libraries and the only modules that may import them
CONFINED = {
    "psychopy": {"facelab.experiment.runner", "facelab.experiment.window"},
    "pyrender": {"facelab.stimuli.render.renderer"},
    "dask": {"facelab.grid"},
    "distributed": {"facelab.grid"},
    "dask_jobqueue": set(),  # the README's SLURM recipe: the user's script, never facelab
}


def _modules() -> dict[str, Path]:
    """Every facelab module name -> its file, from the package-dir mapping."""
    out: dict[str, Path] = {}
    for package, folder in PACKAGE_DIRS.items():
        base = ROOT / folder
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("").parts
            if any(part.startswith(".") for part in rel) or (
                len(rel) > 1 and not (base / Path(*rel[:-1]) / "__init__.py").is_file()
            ):
                continue  # not inside a package (e.g. a data folder)
            parts = rel[:-1] if rel[-1] == "__init__" else rel
            out[".".join([package, *parts])] = path
    return out


MODULES = _modules()


def _part(module: str) -> str:
    """core | stimuli | analysis | experiment | protocols."""
    pieces = module.split(".")
    if len(pieces) > 1 and pieces[1] in ALLOWED and f"facelab.{pieces[1]}" in PACKAGE_DIRS:
        return pieces[1]
    return "core"


def _imports(path: Path) -> list[tuple[str, int]]:
    """(imported name, line) for every import statement in the file, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                out.append((f"<relative import level {node.level}>", node.lineno))
                continue
            base = node.module or ""
            out.append((base, node.lineno))
            # `from facelab.stimuli import avatar` imports the module facelab.stimuli.avatar
            out += [
                (f"{base}.{a.name}", node.lineno)
                for a in node.names
                if f"{base}.{a.name}" in MODULES
            ]
    return out


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        for name, _ in _imports(path):
            if name in MODULES and name != module:
                graph[module].add(name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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
                found.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def package_graph() -> dict[tuple[str, str], int]:
    """(from part, to part) -> number of module-level edges between different parts."""
    edges: dict[tuple[str, str], int] = defaultdict(int)
    for module, targets in _graph().items():
        for target in targets:
            a, b = _part(module), _part(target)
            if a != b:
                edges[(a, b)] += 1
    return dict(sorted(edges.items()))


def test_every_package_folder_is_installed() -> None:
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    assert set(PACKAGE_DIRS) <= listed
    for package in listed:
        assert package == "facelab" or package.startswith("facelab."), package
        parent, _, leaf = package.rpartition(".")
        folder = PACKAGE_DIRS.get(package) or f"{PACKAGE_DIRS[parent]}/{leaf}"
        assert (ROOT / folder / "__init__.py").is_file(), f"{package}: no {folder}/__init__.py"
    for package, folder in PACKAGE_DIRS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            name = ".".join([package, *rel.parts]) if rel.parts else package
            assert name in listed, f"{init.parent} is a package but pyproject does not list {name}"


def test_only_the_facelab_name_is_imported() -> None:
    bare = {"core", "experiment", "stimuli", "analysis", "protocols", "tests"}
    problems = []
    for path in MODULES.values():
        for name, line in _imports(path):
            if name.split(".")[0] in bare or name.startswith("<relative"):
                problems.append(f"{path.relative_to(ROOT)}:{line}: imports {name}")
    for path in sorted((ROOT / "tests").glob("*.py")):
        for name, line in _imports(path):
            if name.split(".")[0] in bare - {"tests"} or name.startswith("<relative"):
                problems.append(f"{path.relative_to(ROOT)}:{line}: imports {name}")
    assert not problems, "\n".join(problems)


def test_layers_point_down_only() -> None:
    problems = []
    for module, path in MODULES.items():
        mine = _part(module)
        for name, line in _imports(path):
            if name != "facelab" and not name.startswith("facelab."):
                continue
            if name == "facelab":
                continue  # the package itself: core
            target = name if name in MODULES else name.rsplit(".", 1)[0]
            theirs = _part(target)
            if theirs != mine and theirs not in ALLOWED[mine]:
                problems.append(
                    f"{path.relative_to(ROOT)}:{line}: {mine} imports {name} ({theirs})"
                )
    assert not problems, "\n".join(problems)


#: the stimulus layer's own order, lowest first: a sub-package (or top-level module) may import
#: its own level and the levels below it. Speech and avatars know nothing of each other; the
#: face-capture data (Z matrices) sit on speech; impression and behaviour models on those;
#: animation methods on all of them; rendering (clips, sheets, inspection) on top; the
#: benchmarks above everything.
STIMULI_LEVELS = {
    "arkit": 0,
    "speech": 1,
    "avatar": 1,
    "capture": 2,
    "impression": 3,
    "behaviour": 3,
    "methods": 4,
    "render": 5,
    "visemes": 5,  # the contract path re-exporting the speech analyser
    "checks": 6,  # the stimulus checks measure rendered clips
    "bench": 7,
}


def _stimuli_part(module: str) -> str | None:
    pieces = module.split(".")
    return pieces[2] if len(pieces) > 2 and pieces[:2] == ["facelab", "stimuli"] else None


def test_stimuli_subpackages_are_layered() -> None:
    """DESIGN.md's sub-packages by job, and the order between them (STIMULI_LEVELS)."""
    problems = []  # a level's parts do not import each other either
    parts = {_stimuli_part(m) for m in MODULES} - {None}
    assert parts == set(STIMULI_LEVELS), f"unlevelled stimuli parts: {parts ^ set(STIMULI_LEVELS)}"
    for module, path in MODULES.items():
        mine = _stimuli_part(module)
        if mine is None:
            continue
        for name, line in _imports(path):
            target = name if name in MODULES else name.rsplit(".", 1)[0]
            theirs = _stimuli_part(target)
            if theirs is not None and STIMULI_LEVELS[theirs] > STIMULI_LEVELS[mine]:
                problems.append(f"{path.relative_to(ROOT)}:{line}: {mine} imports {name}")
            if {mine, theirs} in ({"impression", "behaviour"}, {"speech", "avatar"}):
                problems.append(f"{path.relative_to(ROOT)}:{line}: {mine} imports {name}")
    assert not problems, "\n".join(problems)


def test_no_import_cycles_between_modules() -> None:
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_no_cycles_between_subpackages() -> None:
    edges = package_graph()
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    assert not _cycles(dict(graph)), edges


def test_heavy_libraries_stay_at_the_edges() -> None:
    problems = []
    for module, path in MODULES.items():
        for name, line in _imports(path):
            top = name.split(".")[0]
            if top in CONFINED and module not in CONFINED[top]:
                problems.append(f"{path.relative_to(ROOT)}:{line}: {module} imports {top}")
    assert not problems, "\n".join(problems)


@pytest.mark.slow
def test_the_wheel_installs_one_name_and_carries_the_protocols(tmp_path: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
            str(ROOT),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("facelab-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"facelab"}
    assert "facelab/protocols/kato2021.yaml" in names
    missing = sorted(set(_source_files()) - set(names))
    assert not missing, f"files of the source folders left out of the wheel: {missing}"


def _source_files() -> list[str]:
    """Every file of the package folders (code and the data it reads) as the wheel names it;
    npm's node_modules (installed at set-up) and caches left out."""
    out = []
    for package, folder in PACKAGE_DIRS.items():
        base = ROOT / folder
        for path in base.rglob("*"):
            rel = path.relative_to(base)
            skip = {"__pycache__", "node_modules"}
            if path.is_file() and not any(p in skip or p.startswith(".") for p in rel.parts):
                out.append("/".join([*package.split("."), *rel.parts]))
    return out


if __name__ == "__main__":  # pragma: no cover
    for (a, b), n in package_graph().items():
        print(f"{a} -> {b} ({n} module edges)")
    print("module cycles:", _cycles(_graph()) or "none")
