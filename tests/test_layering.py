"""The import graph runs one way (DESIGN.md, "Modules"): no upward edge, no cycle; a layer alone loads only lower ones.

The table below is DESIGN.md's, lowest layer first, with two readings stated: the error types
and the Gaussian state type (with the RNG seeding, which imports nothing from qtl) are the
foundation every layer may use, the data and the task included (with ``qtl.health``, the counts of numerical
trouble that the parts report and the loop records); and ``qtl.checkpoint`` (tensors
and primitives on disk, importing only the errors) sits below transfer, which reads its source
runs from checkpoints. A unit (a top-level module or subpackage of ``qtl``, ``qtl.envs`` included) may import
units of lower layers, and of its own layer only where SAME_LAYER says so. A unit missing from the
table counts as top level: nothing below may import it.
"""

from __future__ import annotations

import ast
import graphlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Where each package lives in the tree: ``qtl.envs`` is the top-level ``envs/`` directory, installed under qtl.
PACKAGES = {"qtl": "qtl", "qtl.envs": "envs"}

LAYERS: list[tuple[str, set[str]]] = [
    ("envs", {"qtl.envs"}),
    ("foundation", {"qtl.errors", "qtl.gaussian", "qtl.seeding", "qtl.health"}),
    ("data, task", {"qtl.data", "qtl.task", "qtl.env_wrappers", "qtl.constraints"}),
    ("maths", {"qtl.kernels", "qtl.lbfgs", "qtl.plateau"}),
    ("parts", {"qtl.features", "qtl.models", "qtl.policies", "qtl.rewards"}),
    ("policy search", {"qtl.policy_search"}),
    ("propagation", {"qtl.propagation"}),
    ("checkpoint files", {"qtl.checkpoint"}),
    ("transfer", {"qtl.transfer"}),
    ("record", {"qtl.recorder", "qtl.metrics", "qtl.hparams", "qtl.report", "qtl.video"}),
    ("algorithm", {"qtl.loop", "qtl.run_state", "qtl.build", "qtl.episodes", "qtl.config", "qtl.runs", "qtl.frames"}),
    ("top", {"qtl.train", "qtl.demo", "qtl.launch", "qtl.__main__", "qtl.pipeline", "qtl.bench", "qtl.play",
             "qtl.exported_policy"}),
]
RANK = {unit: rank for rank, (_, units) in enumerate(LAYERS) for unit in units}
TOP = len(LAYERS) - 1
# Layers whose units may import each other freely (acyclically); elsewhere only the listed pairs.
OPEN_LAYERS = {"record", "algorithm", "top"}
SAME_LAYER = {("qtl.policies", "qtl.features"), ("qtl.rewards", "qtl.features"), ("qtl.task", "qtl.env_wrappers"),
              ("qtl.task", "qtl.constraints")}

# Imported alone in a fresh interpreter, each of these may load only what the table allows it.
ALONE = [
    "qtl.gaussian", "qtl.errors", "qtl.kernels", "qtl.lbfgs", "qtl.features", "qtl.data", "qtl.task", "qtl.models",
    "qtl.env_wrappers", "qtl.policies", "qtl.rewards", "qtl.propagation", "qtl.policy_search", "qtl.transfer",
    "qtl.envs", "qtl.constraints",
]


def unit(module: str) -> str:
    """The layer unit of a module: ``qtl`` (the root package) or ``qtl.<first part>`` (``qtl.envs`` too)."""
    parts = module.split(".")
    return parts[0] if len(parts) == 1 else ".".join(parts[:2])


def rank(name: str) -> int:
    """The layer index of a unit (top for one the table does not name)."""
    return RANK.get(name, TOP)


def may_import(importer: str, imported: str) -> bool:
    """Whether unit ``importer`` may depend on unit ``imported`` by the table."""
    if importer == imported:
        return True
    if imported == "qtl":  # the root package: its __init__ holds only the version
        return True
    if rank(imported) < rank(importer):
        return True
    same = rank(imported) == rank(importer)
    return same and (LAYERS[rank(importer)][0] in OPEN_LAYERS or (importer, imported) in SAME_LAYER)


def source_files() -> dict[str, Path]:
    """Every module of the packages by dotted name (a package by its ``__init__.py``)."""
    modules = {}
    for package, directory in PACKAGES.items():
        for path in sorted((ROOT / directory).rglob("*.py")):
            parts = path.relative_to(ROOT / directory).with_suffix("").parts
            modules[".".join([package, *(parts[:-1] if parts[-1] == "__init__" else parts)])] = path
    return modules


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The package modules one file imports anywhere in it (functions and TYPE_CHECKING blocks included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                module = ".".join([*base, node.module] if node.module else base)
            else:
                module = node.module or ""
            for alias in node.names:
                submodule = f"{module}.{alias.name}"
                found.add(submodule if submodule in known else module)
    return {m for m in found if m.split(".")[0] == "qtl"}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    """Module → the package modules it imports, over every file of ``qtl`` and ``qtl.envs``."""
    files = source_files()
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def test_the_table_names_each_unit_once_and_the_scan_finds_the_layers(graph):
    named = [u for _, units in LAYERS for u in units]
    assert len(named) == len(set(named))
    assert {"qtl.envs", "qtl.gaussian", "qtl.kernels", "qtl.propagation", "qtl.transfer", "qtl.loop"} <= {
        unit(m) for m in graph
    }
    # The scan sees real edges (a broken parser would make every check below pass vacuously).
    assert "qtl.kernels.exp_sum" in graph["qtl.kernels.moments"]
    assert "qtl.policies.base" in graph["qtl.propagation.moment_matching"]


def test_may_import_states_the_layering():
    assert may_import("qtl.propagation", "qtl.policies") and may_import("qtl.policies", "qtl.kernels")
    assert not may_import("qtl.policies", "qtl.propagation") and not may_import("qtl.kernels", "qtl.models")
    assert may_import("qtl.envs", "qtl") and not may_import("qtl.envs", "qtl.gaussian")
    assert not may_import("qtl.features", "qtl.policies") and not may_import("qtl.transfer", "qtl.recorder")
    assert not may_import("qtl.gaussian", "qtl.unlisted_newcomer")


def test_no_module_imports_a_higher_layer(graph):
    upward = sorted(
        f"{module} → {target}"
        for module, targets in graph.items()
        for target in targets
        if not may_import(unit(module), unit(target))
    )
    assert not upward, "imports against the layering:\n" + "\n".join(upward)


def test_the_module_import_graph_is_acyclic(graph):
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as err:
        pytest.fail(f"import cycle: {' → '.join(err.args[1])}")


@pytest.mark.parametrize("package", ALONE)
def test_importing_a_layer_alone_loads_only_lower_layers(package):
    probe = (
        f"import {package}, sys, json; "
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] == 'qtl')))"
    )
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert package in loaded
    importer = unit(package)
    above = sorted(m for m in loaded if not may_import(importer, unit(m)))
    assert not above, f"importing {package} alone loads {above}"
