"""The layout's rules, checked on the source: layers only import downwards, areas name their API.

``LAYERS`` is the order of ``docs/architecture.md``, lowest first. Each entry is a unit: a
top-level module of the framework or a whole area folder. A module may import its own unit and
units listed before it, never one listed after; imports inside functions count, since a lazy
import is still a dependency. A new module or folder must be placed in ``LAYERS`` deliberately.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

import ctpipe

PACKAGE = Path(ctpipe.__file__).parent

LAYERS = (
    # foundation: no ctpipe imports beyond this group
    "ctpipe._version", "ctpipe.errors", "ctpipe._shared", "ctpipe.model", "ctpipe.geometry",
    "ctpipe.images",
    # the framework's contracts: data passed between stages, stages, registry, hooks, configuration
    "ctpipe.data", "ctpipe.stages", "ctpipe.registry", "ctpipe.hookspecs", "ctpipe.config",
    # loading plugins by name (stages and scan formats); it imports no plugin module itself
    "ctpipe.plugins",
    # the areas, each a folder
    "ctpipe.io", "ctpipe.recon", "ctpipe.features", "ctpipe.sim", "ctpipe.solve", "ctpipe.builtin",
    # assembly: running a pipeline
    "ctpipe.execution", "ctpipe.pipeline",
    # the device choice's public face, and the check of the GPU kernels against the CPU's
    "ctpipe.gpu",
    # what uses a whole pipeline: evaluation, helpers for tests and benchmarks, entry points
    "ctpipe.evaluate", "ctpipe.testing", "ctpipe.cli", "ctpipe",
)

AREAS = ("ctpipe.builtin", "ctpipe.solve", "ctpipe.sim", "ctpipe.recon", "ctpipe.io", "ctpipe.evaluate", "ctpipe.features")


def _modules() -> dict[str, Path]:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


MODULES = _modules()


def _unit(module: str) -> str:
    for unit in sorted(LAYERS, key=len, reverse=True):
        if module == unit or module.startswith(unit + "."):
            return unit
    raise AssertionError(f"{module} is in no layer of LAYERS; place it there deliberately")


def _imports(module: str, path: Path) -> set[str]:
    """ctpipe modules that ``module`` imports, anywhere in its body."""
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "ctpipe")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[:len(base) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "ctpipe":
                continue
            for alias in node.names:
                # 'from ctpipe.x import y' imports the submodule ctpipe.x.y when there is one.
                found.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in MODULES else target)
    return found


@pytest.mark.parametrize("module", sorted(MODULES))
def test_modules_import_only_their_own_layer_and_the_layers_below(module):
    rank = {unit: i for i, unit in enumerate(LAYERS)}
    own = _unit(module)
    upward = sorted(f"{target} ({_unit(target)})" for target in _imports(module, MODULES[module])
                    if target in MODULES and rank[_unit(target)] > rank[own])
    assert not upward, f"{module} (layer {own}) imports higher layers: {', '.join(upward)}"


def test_no_plugin_imports_another_plugin():
    # A plugin may be blocked: another that imported it would load it anyway, and a stage that
    # needs another stage gets it from the registry (a nested stage spec), not by import.
    # Private adapters (ctpipe.builtin._opencv) are shared infrastructure, not plugins.
    from ctpipe.plugins import BUILTIN_PLUGINS

    for plugin in BUILTIN_PLUGINS:
        others = sorted(t for t in _imports(plugin, MODULES[plugin]) if t in BUILTIN_PLUGINS and t != plugin)
        assert not others, f"plugin {plugin} imports plugins {others}"
        siblings = sorted(t for t in _imports(plugin, MODULES[plugin]) if t != plugin
                          and t.startswith("ctpipe.builtin.") and not t.rsplit(".", 1)[1].startswith("_"))
        assert not siblings, f"plugin {plugin} imports stage modules {siblings}"


def test_no_import_cycles_between_modules():
    graph = {module: {t for t in _imports(module, path) if t in MODULES and t != module}
             for module, path in MODULES.items()}
    # A package's __init__ importing its own submodules is how it names its API, not a cycle.
    for module in graph:
        graph[module] = {t for t in graph[module] if not (MODULES[t].name == "__init__.py" and module.startswith(t + "."))}
    state: dict[str, int] = {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt] if nxt in stack else [node, nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


@pytest.mark.parametrize("area", AREAS)
def test_every_area_names_its_api_with_a_docstring(area):
    package = importlib.import_module(area)
    assert package.__doc__ and len(package.__doc__.split()) >= 30, f"{area}: needs a paragraph of docstring"
    assert package.__all__, f"{area}: __all__ is empty"
    missing = [name for name in package.__all__ if not hasattr(package, name)]
    assert not missing, f"{area}.__all__ names what it does not define: {missing}"
    assert len(set(package.__all__)) == len(package.__all__), f"{area}.__all__ has duplicates"
    # A name equal to a submodule's would shadow it: 'import ctpipe.recon.feldkamp as m' must give the module.
    submodules = {info.name for info in pkgutil.iter_modules(package.__path__)}
    assert not submodules & set(package.__all__), f"{area}: __all__ shadows submodules {submodules & set(package.__all__)}"


@pytest.mark.parametrize("area", AREAS)
def test_every_public_name_of_an_area_module_is_in_the_area_api_or_private(area):
    package = importlib.import_module(area)
    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{area}.{info.name}")
        own = [name for name in getattr(module, "__all__", ())
               if getattr(getattr(module, name), "__module__", module.__name__) == module.__name__]
        missing = sorted(set(own) - set(package.__all__) - _INTERNAL.get(module.__name__, set()))
        assert not missing, f"{module.__name__} exports {missing}, which {area}.__all__ does not name"


# Names a module exports for its neighbours in the area (or for tests), not for users.
_INTERNAL = {
    "ctpipe.sim.primitives": {"KINDS", "unit_interval", "local_maps"},
    "ctpipe.sim.phantoms": {"OBJECT_KINDS", "rotation_from_deg"},
    "ctpipe.sim.jitter": {"JitterModel", "GaussianJitter", "RandomWalkJitter", "PeriodicJitter", "JumpJitter"},
    "ctpipe.sim.simulator": {"check_simulation_fits"},
    "ctpipe.solve.bundle": {"pair_graph_angles"},
    "ctpipe.solve.tracks": {"descriptor_distances", "verified_match_distances"},
    "ctpipe.solve.camera": {"projection_jacobians"},
    "ctpipe.solve.reprojection": {"reconstruction_grid", "tangential_derivative", "band_pass", "as_line_integrals"},
    "ctpipe.evaluate.synthetic": {"project", "PIXEL_NORMALISED"},
    "ctpipe.builtin.surf": {"surf"},
    # ctpipe.io: the CLI's output plumbing, the calibration-frame helpers, the corrected angle
    # logs (written through each format's corrected_angle_log), the scan folder's constants
    "ctpipe.io.outputs": {"atomic_write", "write_json", "write_csv", "write_files", "staged_folder", "json_bytes",
                          "csv_bytes", "to_jsonable", "check_output_dir", "check_output_file", "write_keypoints",
                          "keypoints_writer", "leftovers"},
    "ctpipe.io.flatfield": {"mean_frame", "MAX_DEAD_FRACTION"},
    "ctpipe.io.nikon": {"write_nikon_angles"},
    "ctpipe.io.waygate": {"write_waygate_angles"},
    "ctpipe.io.scan_folder": {"check_scan_folder_free", "SCAN_FORMAT", "VALUE_KINDS"},
}


def test_the_package_exposes_what_a_user_needs_first():
    for name in ("Pipeline", "Geometry", "open_scan", "read_scan", "simulate", "fdk", "VolumeGrid", "load_phantom",
                 "run_validate"):
        assert name in ctpipe.__all__
        assert getattr(ctpipe, name).__name__ == name
    assert ctpipe.fdk is importlib.import_module("ctpipe.recon.feldkamp").fdk
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ctpipe.nope


def test_importing_ctpipe_loads_neither_numba_nor_opencv():
    # The 'ctpipe' command imports the package first; its --help must not pay for numba and cv2.
    code = ("import sys, ctpipe, ctpipe.execution; "
            "print(sorted(m for m in ('numba', 'cv2', 'scipy', 'dask', 'distributed') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_architecture_figure_names_modules_that_exist():
    script = Path(__file__).resolve().parents[1] / "docs" / "architecture_figure.py"
    spec = importlib.util.spec_from_file_location("architecture_figure", script)
    figure = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(figure)
    for source, target, modules, _ in figure.ARROWS:
        assert source in figure.DATA and target in figure.DATA, (source, target)
        for module in modules:
            assert module in MODULES, f"docs/architecture_figure.py names {module}, which does not exist"
    assert (script.parent / "architecture.png").is_file()


def _resolve(dotted: str):
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for part in parts[i:]:
            obj = getattr(obj, part)
        return obj
    raise ImportError(dotted)


def test_every_ctpipe_name_the_docs_cite_exists():
    root = Path(__file__).resolve().parents[1]
    pages = [root / "README.md", *sorted((root / "docs").glob("*.md")), *sorted((root / "plugins").glob("*/README.md"))]
    missing = []
    for page in pages:
        text = page.read_text(encoding="utf-8")
        cited = set(re.findall(r"\b(ctpipe(?:\.\w+)+)", text))
        for module, names in re.findall(r"^\s*from (ctpipe[\w.]*) import ([\w, ]+)$", text, re.M):
            cited.update(f"{module}.{name.strip()}" for name in names.split(","))
        # ctpipe.phantoms_data is the wheel's name for the top-level phantoms/ folder; an editable
        # install may not map it (ctpipe.sim.phantoms falls back to the folder).
        for dotted in sorted(cited - {"ctpipe.phantoms_data"}):
            try:
                _resolve(dotted)
            except (ImportError, AttributeError):
                missing.append(f"{page.relative_to(root)}: {dotted}")
    assert not missing, "the docs cite names that do not exist:\n" + "\n".join(missing)
