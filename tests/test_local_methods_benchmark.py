"""benchmarks/local_methods.py: the derived depth-discontinuity mask used by ``--breakdown``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "local_methods.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("local_methods_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_disc_mask_is_a_dilated_band_around_jumps(bench):
    gt = np.full((20, 40), 5.0, np.float32)
    gt[:, 20:] = 10.0  # a 5 px jump between columns 19 and 20
    nonocc = np.ones(gt.shape, bool)
    disc = bench.derive_disc_mask(gt, nonocc)
    expected = np.zeros(gt.shape, bool)
    expected[:, 15:25] = True  # both jump pixels, widened by 4 px on each side (9-wide window)
    np.testing.assert_array_equal(disc, expected)


def test_disc_mask_ignores_small_steps_and_unknown_gt(bench):
    gt = np.full((12, 30), 5.0, np.float32)
    gt[:, 10:] = 7.0  # a 2 px step is not a discontinuity (jump must exceed 2 px)
    gt[:, 25:] = np.inf  # unknown GT next to known GT is no jump either
    assert not bench.derive_disc_mask(gt, np.ones(gt.shape, bool)).any()


def test_disc_mask_stays_inside_nonocc(bench):
    gt = np.zeros((15, 15), np.float32)
    gt[7:, :] = 9.0  # a horizontal edge: vertical neighbours jump
    nonocc = np.ones(gt.shape, bool)
    nonocc[:, :5] = False
    disc = bench.derive_disc_mask(gt, nonocc)
    assert not disc[:, :5].any()
    assert disc[2:12, 5:].all() and not disc[:2].any() and not disc[12:].any()
