"""benchmarks/accuracy.py: how the methods of a scene take turns in the timed rounds, the validation scenes' disparity
range, and how a run updates the scoreboard."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("accuracy_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


def test_each_round_starts_one_method_later(bench, monkeypatch):
    monkeypatch.setattr(bench, "TURN_GAP_S", 0.0)
    calls = []
    fns = {name: (lambda name=name: calls.append(name) or name) for name in ("a", "b", "c")}
    seen = []
    runs = bench.timed_in_turns(fns, 4, each=lambda name, out, seconds: seen.append((name, out)))
    # One warm-up call each, then rounds a b c, b c a, c a b, a b c.
    assert calls == list("abc") + list("abc") + list("bca") + list("cab") + list("abc")
    assert seen == [(name, name) for name in calls[3:]]
    assert {name: out for name, (out, _) in runs.items()} == {"a": "a", "b": "b", "c": "c"}
    assert all(seconds >= 0 for _, seconds in runs.values())


def test_ndisp_covers_the_largest_disparity_in_multiples_of_16(bench):
    inf = np.inf
    assert bench.ndisp_from_truth(np.array([[3.0, inf], [73.67, 16.0]], np.float32)) == 80
    assert bench.ndisp_from_truth(np.array([[15.5, inf]], np.float32)) == 16
    assert bench.ndisp_from_truth(np.array([[16.0, 2.0]], np.float32)) == 32  # the range is [0, ndisp)


def test_the_scoreboard_replaces_what_a_run_measured_and_keeps_the_rest(bench, tmp_path):
    board_module = bench.scoreboard
    path = tmp_path / "scoreboard.json"
    board = board_module.load(path)
    first = board_module.new_run(board, command="a", threads=2, repeat=3, versions={}, date="d")
    scenes = {"x": {"bad1.0": 5.0, "seconds": 0.5, "x3way": 1.25}}
    for method in ("m", "pandora"):
        board_module.record(board, method, "v2", run_id=first, average={"bad1.0": 5.0}, scenes=dict(scenes),
                            time={"seconds": 0.5, "mde_per_s": 1.0, "x3way": 1.25}, in_turns=True, keep_times=False)
    board_module.save(board, path)

    board = board_module.load(path)
    second = board_module.new_run(board, command="b", threads=1, repeat=1, versions={}, date="d")
    board_module.record(board, "m", "v2", run_id=second, average={"bad1.0": 4.0},
                        scenes={"x": {"bad1.0": 4.0, "seconds": 9.0, "x3way": 9.0}},
                        time={"seconds": 9.0, "mde_per_s": 1.0, "x3way": 9.0}, in_turns=True, keep_times=True)
    board_module.save(board, path)
    saved = board_module.load(path)
    entry = saved["methods"]["m"]["v2"]
    assert (first, second) == ("run-1", "run-2")
    assert entry["scores_run"] == second and entry["average"] == {"bad1.0": 4.0}
    assert entry["times_run"] == first and entry["time"]["x3way"] == 1.25
    assert entry["scenes"]["x"] == {"bad1.0": 4.0, "seconds": 0.5, "x3way": 1.25}
    assert saved["methods"]["pandora"]["v2"]["scores_run"] == first
    assert set(saved["runs"]) == {first, second}
