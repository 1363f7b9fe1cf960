import dataclasses
import inspect

import pytest

from ctpipe import hookspecs
from ctpipe.errors import ConfigError, PluginError
from ctpipe.hookspecs import hookimpl
from ctpipe.plugins import (BUILTIN_FORMAT_PLUGINS, BUILTIN_PLUGINS, BUILTIN_STAGE_PLUGINS, collect_stages,
                            get_plugin_manager, get_registry)
from ctpipe.stages import Estimator, param
from ctpipe.testing import check_stage


def test_builtin_stages_are_registered_by_their_plugins():
    registry = get_registry()
    assert {"sift", "orb", "akaze", "brisk", "kaze"} <= set(registry.names("detector"))
    assert {"brute-force", "flann"} <= set(registry.names("matcher"))
    assert {"ransac-1pt", "histogram", "median", "opencv-5pt"} <= set(registry.names("estimator"))
    assert {"least-squares"} <= set(registry.names("refiner"))
    assert registry.get("estimator", "ransac-1pt").plugin == "ctpipe.builtin.estimators"
    assert all(info.description for info in registry)


@pytest.mark.parametrize("info", list(get_registry()), ids=lambda i: f"{i.kind}:{i.name}")
def test_every_registered_stage_passes_conformance(info):
    check_stage(info.cls())


def test_blocking_a_builtin_plugin_removes_its_stages():
    registry = get_registry(blocked=("ctpipe.builtin.estimators",))
    assert registry.names("estimator") == []
    with pytest.raises(ConfigError, match="unknown estimator 'ransac-1pt'; registered estimators: \\(none"):
        registry.get("estimator", "ransac-1pt")


def test_unknown_stage_lists_the_registered_names():
    with pytest.raises(ConfigError, match="unknown detector 'sfit'; registered detectors: .*sift"):
        get_registry().get("detector", "sfit")


@dataclasses.dataclass(frozen=True)
class _ConstantEstimator(Estimator):
    """Always answers the same angle (test plugin)."""

    angle_rad: float = param(0.0, doc="the answer")

    def estimate(self, q_a, q_b, *, rng):  # pragma: no cover - never called
        raise AssertionError


class _ThirdParty:
    @hookimpl
    def ctpipe_register_stages(self, registry):
        registry.add_estimator("constant", _ConstantEstimator)


class _Clash:
    @hookimpl
    def ctpipe_register_stages(self, registry):
        registry.add_estimator("ransac-1pt", _ConstantEstimator)


def test_ctpipe_register_stages_hook_records_the_providing_plugin():
    pm = get_plugin_manager(entry_points=False)
    pm.register(_ThirdParty(), name="third-party")
    info = collect_stages(pm).get("estimator", "constant")
    assert info.plugin == "third-party" and info.description == "Always answers the same angle (test plugin)."


def test_a_duplicate_name_is_an_error_naming_both_plugins():
    pm = get_plugin_manager(entry_points=False)
    pm.register(_Clash(), name="clashing-plugin")
    with pytest.raises(PluginError, match="'ctpipe.builtin.estimators' and by plugin 'clashing-plugin'"):
        collect_stages(pm)


def test_every_hook_has_a_test_and_a_docs_entry():
    hooks = [name for name, _ in inspect.getmembers(hookspecs, inspect.isfunction) if name.startswith("ctpipe_")]
    assert hooks == ["ctpipe_register_formats", "ctpipe_register_stages"]
    source = open(__file__).read() + open(__file__.replace("test_plugins.py", "io/test_format_plugins.py")).read()
    docs = open(__file__.replace("tests/test_plugins.py", "docs/plugins.md")).read()
    for hook in hooks:
        assert f"def test_{hook}" in source
        assert hook in docs


def test_builtins_are_listed_in_one_tuple():
    assert BUILTIN_STAGE_PLUGINS == ("ctpipe.builtin.opencv_detectors", "ctpipe.builtin.surf", "ctpipe.builtin.beads",
                                     "ctpipe.builtin.matchers", "ctpipe.builtin.estimators", "ctpipe.builtin.refiners",
                                     "ctpipe.builtin.projection_matching", "ctpipe.builtin.bundle",
                                     "ctpipe.builtin.ball_calibration")
    assert BUILTIN_FORMAT_PLUGINS == ("ctpipe.io.scan_folder", "ctpipe.io.nikon", "ctpipe.io.zeiss", "ctpipe.io.bruker",
                                      "ctpipe.io.waygate", "ctpipe.io.nsi", "ctpipe.io.tiff_stack")
    assert BUILTIN_PLUGINS == BUILTIN_STAGE_PLUGINS + BUILTIN_FORMAT_PLUGINS


def test_stage_parameters_are_validated_on_construction():
    from ctpipe.builtin.estimators import Ransac1ptEstimator

    with pytest.raises(ConfigError, match=r"Ransac1ptEstimator.sampson_threshold: must be a number > 0 and <= 1, got -1"):
        Ransac1ptEstimator(sampson_threshold=-1)


def test_opencv_detectors_missing_from_the_cv2_build_are_not_registered(monkeypatch):
    # A plain opencv-python wheel installed over the contrib one has no KAZE/AKAZE/BRISK factories.
    from ctpipe.builtin import _opencv

    real = _opencv._factory
    monkeypatch.setattr(_opencv, "_factory", lambda kind: None if kind == "kaze" else real(kind))
    detectors = {info.name for info in get_registry() if info.kind == "detector"}
    assert "kaze" not in detectors
    assert {"sift", "orb"} <= detectors
    with pytest.raises(RuntimeError, match="KAZE_create"):
        _opencv._create("kaze", {})


def test_a_plugin_that_fails_to_import_is_named_in_one_line(monkeypatch, capsys):
    import importlib.metadata

    from ctpipe.cli import main

    broken = importlib.metadata.EntryPoint(name="broken", value="ctpipe_no_such_module", group="ctpipe")
    real = importlib.metadata.entry_points
    monkeypatch.setattr(importlib.metadata, "entry_points",
                        lambda **kw: (*real(**kw), broken) if kw.get("group") == "ctpipe" else real(**kw))
    with pytest.raises(PluginError, match="plugin 'broken' \\(ctpipe_no_such_module\\) failed to load: "
                                          "ModuleNotFoundError.*--block-plugin broken"):
        get_registry()
    assert "sift" in get_registry(blocked=("broken",)).names("detector")
    assert main(["plugins"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ctpipe: error: plugin 'broken'")


def test_a_broken_opencv_is_one_line_and_blocking_its_plugins_keeps_it_out():
    import subprocess
    import sys

    run = ("import sys; sys.modules['cv2'] = None; from ctpipe.cli import main; code = main({argv!r}); "
           "print(code, 'cv2' in sys.modules and sys.modules['cv2'] is not None)")
    broken = subprocess.run([sys.executable, "-c", run.format(argv=["plugins"])], capture_output=True, text=True)
    assert broken.stdout.split() == ["2", "False"]
    assert broken.stderr.count("\n") == 1
    assert broken.stderr.startswith("ctpipe: error: plugin 'ctpipe.builtin.opencv_detectors' failed to load: "
                                    "ModuleNotFoundError")
    assert "--block-plugin ctpipe.builtin.opencv_detectors" in broken.stderr
    argv = ["--block-plugin", "ctpipe.builtin.opencv_detectors", "--block-plugin", "ctpipe.builtin.matchers", "plugins"]
    kept_out = subprocess.run([sys.executable, "-c", run.format(argv=argv)], capture_output=True, text=True)
    assert kept_out.stdout.splitlines()[-1] == "0 False"
    names = {line.split()[1] for line in kept_out.stdout.splitlines()[:-1]}
    assert {"ransac-1pt", "surf", "beads", "projection-matching"} <= names and "sift" not in names
