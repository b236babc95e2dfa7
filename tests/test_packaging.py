"""The installed package must contain every subpackage and the presets."""

from __future__ import annotations

import pytest

from conftest import REPO

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11


def test_pyproject_lists_every_package_and_the_presets():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(config["packages"])
    on_disk = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "stereocli").rglob("__init__.py")}
    assert on_disk | {"stereocli.presets"} == listed
    assert config["package-dir"]["stereocli.presets"] == "configs"
    assert (REPO / "configs" / "default.yaml").is_file()
