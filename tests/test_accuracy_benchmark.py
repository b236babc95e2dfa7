"""benchmarks/accuracy.py: how the methods of a scene take turns in the timed rounds."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

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
