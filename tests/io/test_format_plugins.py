"""Scan formats are plugins like stages: entry points, duplicates, blocking, workers."""

from __future__ import annotations

import pickle
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ctpipe.errors import InputError, PluginError
from ctpipe.io import open_scan
from ctpipe.plugins import BUILTIN_FORMAT_PLUGINS, collect_formats, get_formats, get_plugin_manager

#: A third-party package that reads a whole scan from one ``.npzscan`` file (an npz archive).
_PLUGIN_SOURCE = '''
from pathlib import Path

import numpy as np

from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io import ScanFiles, ViewStack


def detect(path):
    return Path(path).suffix == ".npzscan"


def open_npz(path):
    with np.load(path) as archive:
        views = archive["views"]
        angles = archive["angles_deg"]
        geometry = Geometry(**{k: float(archive[k]) for k in ("source_to_object_mm", "source_to_detector_mm",
                                                             "pixel_pitch_u_mm", "pixel_pitch_v_mm")},
                            detector_rows=views.shape[1], detector_cols=views.shape[2])
    stack = ViewStack(lambda i: views[i], len(views), views.shape[1:], name=str(path))
    return ScanFiles(format="npz-scan", path=Path(path), geometry=geometry, nominal_angles_deg=angles,
                     projections=stack)


@hookimpl
def ctpipe_register_formats(registry):
    registry.add_format("npz-scan", detect, open_npz, "one .npzscan archive (views, angles_deg, distances)")
'''

_CLASH_SOURCE = '''
from ctpipe.hookspecs import hookimpl


@hookimpl
def ctpipe_register_formats(registry):
    registry.add_format("nikon", lambda path: False, lambda path: None, "someone else's nikon")
'''


def _install(tmp_path, monkeypatch, name: str, source: str) -> None:
    """Install a distribution called ``name`` with a ``ctpipe`` entry point, the way pip would."""
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(source))
    dist = tmp_path / f"{name}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[ctpipe]\n{name} = {name}\n")
    monkeypatch.syspath_prepend(str(tmp_path))


@pytest.fixture
def npz_scan(tmp_path, monkeypatch):
    _install(tmp_path, monkeypatch, "ctpipe_npz_scan", _PLUGIN_SOURCE)
    views = np.random.default_rng(0).random((6, 8, 10)).astype(np.float32)
    path = tmp_path / "part.npzscan"
    with open(path, "wb") as handle:
        np.savez(handle, views=views, angles_deg=np.arange(6) * 60.0, source_to_object_mm=100.0,
                 source_to_detector_mm=400.0, pixel_pitch_u_mm=0.2, pixel_pitch_v_mm=0.2)
    return path, views


def test_a_third_party_format_registers_through_an_entry_point(npz_scan):
    path, views = npz_scan
    info = get_formats()["npz-scan"]
    assert info.plugin == "ctpipe_npz_scan"
    assert get_formats().names()[:len(BUILTIN_FORMAT_PLUGINS)] == ["ctpipe", "nikon", "zeiss", "bruker", "waygate",
                                                                  "nsi", "tiff-yaml"]
    scan = open_scan(path)
    assert scan.format == "npz-scan" and scan.geometry.detector_cols == 10
    np.testing.assert_array_equal(scan.projections[3], views[3])
    # A worker reopens the scan by name through the same registry.
    reference = pickle.loads(pickle.dumps(scan.projections.reference()))
    assert reference.format == "npz-scan"
    np.testing.assert_array_equal(reference.open()[5], views[5])


def test_blocking_a_third_party_format_leaves_its_files_unread(npz_scan):
    path, _ = npz_scan
    with pytest.raises(InputError, match="not a scan in any format ctpipe reads"):
        open_scan(path, blocked=("ctpipe_npz_scan",))


def test_a_format_name_taken_twice_is_refused_naming_both_plugins(tmp_path, monkeypatch):
    _install(tmp_path, monkeypatch, "ctpipe_clash", _CLASH_SOURCE)
    with pytest.raises(PluginError, match="format 'nikon' is registered twice: by plugin 'ctpipe.io.nikon' and by "
                                          "plugin 'ctpipe_clash'; block one of them"):
        get_formats()
    assert "nikon" in get_formats(blocked=("ctpipe_clash",))


def test_ctpipe_register_formats_records_the_providing_plugin():
    class Plugin:
        from ctpipe.hookspecs import hookimpl

        @hookimpl
        def ctpipe_register_formats(self, registry):
            registry.add_format("toy", lambda path: False, lambda path: None, "a toy")

    pm = get_plugin_manager(entry_points=False)
    pm.register(Plugin(), name="toy-plugin")
    formats = collect_formats(pm)
    assert formats["toy"].plugin == "toy-plugin" and formats.names()[-1] == "toy"
    assert formats["nikon"].plugin == "ctpipe.io.nikon"


def test_a_format_needs_callables_and_a_description():
    from ctpipe.registry import FormatRegistry

    registrar = FormatRegistry().registrar("p")
    with pytest.raises(PluginError, match="plugin 'p': format 'x': open must be callable"):
        registrar.add_format("x", lambda path: False, "not callable", "x")
    with pytest.raises(PluginError, match="plugin 'p': format 'y' needs a description"):
        registrar.add_format("y", lambda path: False, lambda path: None, " ")
    with pytest.raises(PluginError, match="format name 'Bad Name' must match"):
        registrar.add_format("Bad Name", lambda path: False, lambda path: None, "z")


def test_blocked_plugin_modules_are_never_imported():
    # --block-plugin keeps a module, and what it imports, out of the process; opening a scan
    # imports no stage module at all (so neither OpenCV nor numba).
    code = textwrap.dedent('''
        import sys
        from ctpipe.plugins import get_formats, get_registry
        names = get_formats(blocked=("ctpipe.io.nikon",)).names()
        loaded = sorted(m for m in ("ctpipe.io.nikon", "ctpipe.builtin.surf", "cv2", "numba") if m in sys.modules)
        get_registry(blocked=("ctpipe.builtin.opencv_detectors",))
        print(names, loaded, "ctpipe.builtin.opencv_detectors" in sys.modules)
    ''')
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "['ctpipe', 'zeiss', 'bruker', 'waygate', 'nsi', 'tiff-yaml'] [] False"


def test_ctpipe_plugins_lists_the_formats_with_their_plugins(npz_scan, capsys):
    import json

    from ctpipe.cli import main

    assert main(["plugins"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.split()[:3] == ["format", "npz-scan", "ctpipe_npz_scan"] for line in lines)
    assert any(line.split()[:3] == ["format", "nikon", "ctpipe.io.nikon"] for line in lines)
    assert main(["--block-plugin", "ctpipe_npz_scan", "plugins", "--json"]) == 0
    formats = json.loads(capsys.readouterr().out)["formats"]
    assert [f["name"] for f in formats] == ["ctpipe", "nikon", "zeiss", "bruker", "waygate", "nsi", "tiff-yaml"]
