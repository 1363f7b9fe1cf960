"""Every subpackage of ctpipe ships in the wheel: pyproject lists packages by hand."""

from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_every_ctpipe_subpackage_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(init.parent.relative_to(ROOT).parts) for init in (ROOT / "ctpipe").rglob("__init__.py")
             if "__pycache__" not in init.parts}
    missing = found - listed
    assert not missing, f"subpackages missing from pyproject.toml [tool.setuptools] packages: {sorted(missing)}"


def test_the_dask_backend_is_an_extra_that_the_test_extra_brings():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(r.startswith("dask[distributed]") for r in extras["dask"])
    # The suite runs a 2-worker LocalCluster; without this it would skip, not fail.
    assert any(r.startswith("dask[distributed]") for r in extras["test"])
    from ctpipe.execution import INSTALL_DASK

    assert INSTALL_DASK == "pip install 'ctpipe[dask]'"


def test_numba_caches_ctpipes_kernels_outside_the_package(tmp_path):
    """An installed package must not gain folders at run time: after an uninstall they would be
    left behind as a namespace package ``ctpipe`` that shadows the next install."""
    import os
    import subprocess
    import sys

    code = ("from ctpipe.solve.reprojection import _difference_of_gaussians as kernel, band_pass; "
            "import numpy; band_pass(numpy.ones((1, 8, 8), numpy.float32), 0.7, 2.0); "
            "print(kernel._cache._cache_path)")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    path = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                          timeout=300).stdout.strip()
    assert Path(path).is_relative_to(tmp_path / "cache") and not Path(path).is_relative_to(ROOT / "ctpipe")
    assert any(Path(path).glob("*.nbi")), "the kernel was not cached"
    # A folder the user names still wins.
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    path = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                          timeout=300).stdout.strip()
    assert Path(path).is_relative_to(tmp_path / "mine")
