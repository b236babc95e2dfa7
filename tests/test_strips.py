"""Row strips: prepare / run_strip / finish equal match_pair, strips equal the whole image for
local methods, and one pair's strips spread over Dask workers stitch to the same bytes."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from stereocli.io.images import read_image
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import finish, match_pair, prepare, run_strip, strip_input
from stereocli.synth.scenes import write_scene

STRIPS = ["runtime.strip_rows=32", "runtime.strip_overlap=16"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("strip_scenes")
    write_scene(root / "curved", "curved", width=160, height=120, seed=3)
    write_scene(root / "planes", "planes", width=160, height=120, seed=4)
    return root


def _pair(scene: Path, name: str = "curved"):
    return read_image(scene / name / "im0.png"), read_image(scene / name / "im1.png")


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


@pytest.mark.parametrize("preset", ["fast", "default"])
def test_phases_in_any_order_equal_match_pair(scene, preset):
    config = build_config([preset], STRIPS)
    left, right = _pair(scene)
    whole = match_pair(left, right, config, ndisp=48, want_right=True)
    assert whole.strips == 4
    prepared = prepare(left, right, config, ndisp=48, want_right=True)
    assert prepared.strips == [(0, 32), (32, 64), (64, 96), (96, 120)]
    # Strips are independent: run them in reverse, each on a pickled copy (as a worker would).
    results = {}
    for y0, y1 in reversed(prepared.strips):
        sub = pickle.loads(pickle.dumps(strip_input(prepared, y0, y1)))
        results[y0] = pickle.loads(pickle.dumps(run_strip(sub, config, y0, y1)))
    split = finish(prepared, [results[y0] for y0, _ in prepared.strips], config)
    for field in ("disparity", "disparity_right", "confidence"):
        assert _same(getattr(split, field), getattr(whole, field)), field
    assert set(split.timings) == set(whole.timings)


LOCAL = """\
cost: {name: census, window: [5, 5]}
aggregation: [{name: box, window: [7, 7]}]
optimizer: {name: wta}
refinement: [{name: subpixel}, {name: lr_check, max_diff: 1.0}, {name: fill}]
"""


def test_local_method_strips_equal_whole_image(scene, tmp_path):
    # Census 5x5 + box 7x7 + WTA read at most 5 rows of context: a 16-row overlap hides the seams.
    (tmp_path / "local.yaml").write_text(LOCAL)
    cfg = str(tmp_path / "local.yaml")
    left, right = _pair(scene, "planes")
    whole = match_pair(left, right, build_config([cfg], []), ndisp=48, want_right=True)
    strips = match_pair(left, right, build_config([cfg], STRIPS), ndisp=48, want_right=True)
    assert whole.strips == 1 and strips.strips == 4
    assert _same(strips.disparity, whole.disparity) and _same(strips.disparity_right, whole.disparity_right)


def test_finish_rejects_results_of_another_plan(scene):
    config = build_config(["fast"], STRIPS)
    left, right = _pair(scene)
    prepared = prepare(left, right, config, ndisp=48)
    y0, y1 = prepared.strips[0]
    with pytest.raises(ValueError, match="strip plan"):
        finish(prepared, [run_strip(strip_input(prepared, y0, y1), config, y0, y1)], config)


def test_strips_split_over_dask_workers_equal_in_process(run_cli, tmp_path, scene):
    import distributed  # the test extra installs Dask

    sets = [a for s in STRIPS for a in ("--set", s)]
    args = ("-c", "fast", "--right", "--png16", "256", *sets)
    assert run_cli("match", scene, "-o", tmp_path / "inline", *args).code == 0
    assert run_cli("match", scene, "-o", tmp_path / "pool", *args, "--jobs", "2").code == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40, env={"NUMBA_NUM_THREADS": "1"}) as cluster, \
            distributed.Client(cluster, set_as_default=False) as client:
        with distributed.get_task_stream(client) as stream:
            r = run_cli("match", scene, "-o", tmp_path / "split", *args, "--scheduler", cluster.scheduler_address,
                        "--split-strips")
        assert r.code == 0, r.err
        strip_tasks = [t for t in stream.data if str(t["key"]).startswith("strip_task")]
        assert len(strip_tasks) == 2 * 4  # two pairs of four strips, each strip a task
        assert len({t["worker"] for t in strip_tasks}) == 2  # spread over both workers
        r = run_cli("match", scene, "-o", tmp_path / "nosplit", *args, "--scheduler", cluster.scheduler_address,
                    "--no-split-strips")
        assert r.code == 0, r.err
    for name in ("curved", "planes"):
        for f in ("disp0.pfm", "disp0.png", "disp1.pfm"):
            ref = (tmp_path / "inline" / name / f).read_bytes()
            for label in ("pool", "split", "nosplit"):
                assert (tmp_path / label / name / f).read_bytes() == ref, (label, name, f)
