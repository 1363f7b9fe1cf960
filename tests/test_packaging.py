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
