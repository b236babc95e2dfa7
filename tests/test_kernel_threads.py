"""The chunk kernels' thread pool: every chunk runs once, errors reach the caller."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from stereocli import runtime


@pytest.fixture(params=[1, 2, 3])
def threads(request, monkeypatch):
    monkeypatch.setattr(runtime, "kernel_threads", lambda: request.param)
    return request.param


def test_every_row_range_runs_once_and_covers_the_rows(threads):
    seen = np.zeros(103, np.int64)
    lock = threading.Lock()

    def rows(out, y0, y1):
        with lock:
            out[y0:y1] += 1

    runtime.for_rows(rows, 103, seen)
    np.testing.assert_array_equal(seen, 1)


def test_every_chunk_runs_once(threads):
    calls = []
    runtime.for_chunks(lambda tag, chunk: calls.append((tag, chunk)), 7, "x")
    assert sorted(calls) == [("x", c) for c in range(7)]


def test_an_error_in_any_chunk_reaches_the_caller(threads):
    def chunk(c):
        if c == 5:
            raise ValueError("chunk 5")

    with pytest.raises(ValueError, match="chunk 5"):
        runtime.for_chunks(chunk, 8)
    runtime.for_chunks(lambda c: None, 8)  # the pool still works afterwards


def test_calls_with_fewer_chunks_than_threads_keep_the_pool(monkeypatch):
    monkeypatch.setattr(runtime, "kernel_threads", lambda: 3)
    runtime.for_rows(lambda y0, y1: None, 50)
    pool = runtime._HELPERS.executor
    runtime.for_chunks(lambda c: None, 2)  # two stripes on three threads
    runtime.for_rows(lambda y0, y1: None, 50)
    assert runtime._HELPERS.executor is pool
