"""The GPU route: which device runs, how a refused GPU falls back, and the kernels' answers.

The kernels are compared with the CPU's through numba-cuda's simulator (``NUMBA_ENABLE_CUDASIM=1``,
in a subprocess: numba reads the variable when it is imported), so they are checked on machines
without a GPU; on a GPU machine ``python -m ctpipe.gpu.check`` runs the same comparison there.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

from ctpipe import Pipeline, gpu
from ctpipe._shared import device
from ctpipe.cli import main
from ctpipe.errors import ConfigError, InputError
from ctpipe.gpu.check import RELATIVE_TOLERANCE

HAS_NUMBA_CUDA = importlib.util.find_spec("numba_cuda") is not None


def test_cpu_is_taken_at_its_word():
    with gpu.use("cpu") as selection:
        assert (selection.device, gpu.active()) == ("cpu", "cpu")


def test_a_request_is_restored_after_its_block():
    before = gpu.requested()
    with gpu.use("cpu"):
        with gpu.use("auto"):
            assert gpu.requested() == "auto"
        assert gpu.requested() == "cpu"
    assert gpu.requested() == before


@pytest.mark.parametrize("bad", ["gpu", "", None, 1])
def test_an_unknown_device_is_one_clear_error(bad):
    with pytest.raises(InputError, match="device: must be one of auto, cpu, cuda"):
        gpu.check_device(bad)


def test_auto_never_picks_the_simulator(monkeypatch):
    monkeypatch.setattr(device, "_cuda_status", lambda: (True, True, ""))
    gpu.select.cache_clear()
    try:
        assert gpu.select("auto").device == "cpu"
        assert gpu.select("cuda").device == "cuda"
    finally:
        gpu.select.cache_clear()


def test_a_refused_gpu_falls_back_to_the_cpu_with_the_reason(monkeypatch, capsys):
    monkeypatch.setattr(device, "_cuda_status", lambda: (False, False, "no CUDA device or driver was found"))
    gpu.select.cache_clear()
    try:
        selection = gpu.select("cuda")
    finally:
        gpu.select.cache_clear()
    assert (selection.device, selection.reason) == ("cpu", "no CUDA device or driver was found")
    assert "a GPU was asked for but cannot be used: no CUDA device or driver was found; running on the CPU" in (
        capsys.readouterr().err)


def test_the_pipeline_key_is_checked():
    assert Pipeline.from_config({"device": "cpu"}).device == "cpu"
    assert Pipeline.from_config(None).config.to_dict()["device"] == "auto"
    with pytest.raises(ConfigError, match=r"pipeline\.device: must be one of 'auto', 'cpu', 'cuda', got 'gpu'"):
        Pipeline.from_config({"device": "gpu"})


def test_the_cli_refuses_an_unknown_device_in_one_line(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--device", "gpu", "plugins"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--device" in err and "'cuda'" in err


def test_the_cli_asks_for_its_device_while_it_runs_only():
    before = gpu.requested()
    assert main(["--device", "cpu", "plugins"]) == 0
    assert gpu.requested() == before


@pytest.mark.skipif(not HAS_NUMBA_CUDA, reason="numba-cuda is not installed (pip install 'ctpipe[gpu]')")
def test_every_kernel_gives_the_cpu_answer_in_the_simulator():
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    done = subprocess.run([sys.executable, "-m", "ctpipe.gpu.check", "6"], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.stdout.strip(), done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert set(report) == {"forward", "forward_pair", "back", "fdk", "fdk_wide_extended", "fdk_wide_extended_direct_filter",
                           "fdk_short_scan", "analytic"}
    for name, entry in report.items():
        assert entry["max_abs"] > 0.1, name   # the scene reaches every kernel
        assert entry["max_abs_diff"] <= RELATIVE_TOLERANCE * entry["max_abs"], (name, entry)
    assert done.returncode == 0


def test_a_bad_device_in_the_environment_is_one_line_before_any_work(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv("CTPIPE_DEVICE", "gpu")
    out = tmp_path / "out"
    assert main(["validate", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == "ctpipe: error: CTPIPE_DEVICE: must be one of auto, cpu, cuda, got 'gpu'\n"
    assert not out.exists()
