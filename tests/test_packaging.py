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
