"""Executor options that fail before any work, whether or not Dask is installed."""

from __future__ import annotations

import sys

import pytest

from stereocli.synth.scenes import write_scene


@pytest.fixture()
def scene(tmp_path):
    write_scene(tmp_path / "s0", "planes", width=128, height=96, seed=0)
    return tmp_path / "s0"


def test_scheduler_errors_are_config_errors(run_cli, tmp_path, scene, monkeypatch):
    r = run_cli("match", scene, "-o", tmp_path / "o", "--scheduler", "not an address")
    assert r.code == 2 and "tcp://host:port" in r.err
    r = run_cli("match", scene, "-o", tmp_path / "o", "--split-strips")
    assert r.code == 2 and "--scheduler" in r.err
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    r = run_cli("match", scene, "-o", tmp_path / "o", "--scheduler", "local")
    assert r.code == 2 and 'pip install "stereocli[dask]"' in r.err
    assert len(r.err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
