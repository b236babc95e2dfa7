"""The ``quality`` preset on real scenes: more accurate than the default, by the official rules."""

from __future__ import annotations

import pytest

from stereocli.evaluation.api import EvalOptions, evaluate_pair
from stereocli.evaluation.datasets import load_scene
from stereocli.io.images import read_image
from stereocli.io.middlebury import read_calib_txt
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair


def _bad(folder, preset: str, sets: tuple[str, ...] = ()) -> tuple[float, float]:
    """MiddEval3-Q nonocc bad 2.0 and 4.0 % (0.5 and 1 px at Q, invalid counted bad) of
    ``preset`` (with ``--set`` assignments ``sets``) on a scene."""
    ndisp = read_calib_txt(folder / "calib.txt").ndisp
    disparity = match_pair(read_image(folder / "im0.png"), read_image(folder / "im1.png"),
                           build_config([preset], list(sets)), ndisp=ndisp).disparity
    result = evaluate_pair(disparity, load_scene(folder, resolution="Q"),
                           options=EvalOptions(resolution="Q", threshold_units="full"))
    return result.metrics["nonocc"]["bad2.0"], result.metrics["nonocc"]["bad4.0"]


# Guards, not scores (benchmarks/results/scoreboard.json has those): a regression that loses
# half of quality's lead over the default on these scenes fails.
@pytest.mark.parametrize("scene, at_most, gain", [("Adirondack", 9.0, 1.2), ("Teddy", 8.0, 1.2)])
def test_quality_beats_the_default_on_real_scenes(shared_data, scene, at_most, gain):
    folder = shared_data / "middlebury2014" / "trainingQ" / scene
    default, quality = _bad(folder, "default")[0], _bad(folder, "quality")[0]
    assert quality <= at_most, (scene, quality)
    assert quality <= default - gain, (scene, default, quality)


def test_quality_is_no_worse_than_the_default_on_any_middeval3_scene(shared_data):
    # Measured: bad-2.0 2.13 (MotorcycleE) to 6.44 (Playtable) points better on every scene;
    # bad-4.0 0.73 (MotorcycleE) to 6.23 (PianoL) points better.
    scenes = sorted(p for p in (shared_data / "middlebury2014" / "trainingQ").iterdir() if (p / "calib.txt").is_file())
    assert len(scenes) >= 15
    worse = {}
    for folder in scenes:
        default, quality = _bad(folder, "default"), _bad(folder, "quality")
        for metric, d, q in zip(("bad2.0", "bad4.0"), default, quality):
            if q > d:
                worse[f"{folder.name} {metric}"] = (d, q)
    assert not worse, worse


def _gain(shared_data, scene: str, without: str) -> tuple[float, float]:
    """How many points of bad-2.0 and bad-4.0 ``quality`` gains on a MiddEval3-Q scene over
    ``quality`` with the ``--set`` assignment ``without``."""
    folder = shared_data / "middlebury2014" / "trainingQ" / scene
    (base2, base4), (q2, q4) = _bad(folder, "quality", (without,)), _bad(folder, "quality")
    return base2 - q2, base4 - q4


def test_reassigning_what_the_mirrored_map_contradicts_removes_gross_errors(shared_data):
    # On Jadeplant, quality's reassignment removes gross errors (a gain of about half a point of
    # bad-2.0 and bad-4.0); the guard asks for a clear gain, not today's figure.
    gain2, gain4 = _gain(shared_data, "Jadeplant", "refinement.mirror_fusion.reassign_above=0")
    assert gain4 >= 0.2 and gain2 >= 0.15, (gain2, gain4)


def test_interpolating_mismatched_rejects_gains_on_artl(shared_data):
    # Measured on ArtL: bad-2.0 12.08 -> 11.69 and bad-4.0 7.42 -> 7.21 with `interpolate` instead
    # of quality's scanline fill: a pixel the LR check rejects that some right-view pixel maps onto
    # is a mismatch, not an occlusion, and takes the median of its neighbours. (Not on the
    # validation scenes, so quality keeps the fill.)
    folder = shared_data / "middlebury2014" / "trainingQ" / "ArtL"
    (fill2, fill4), (interpolated2, interpolated4) = _bad(folder, "quality"), _bad(folder, "quality",
                                                                                    ("refinement.4.name=interpolate",))
    assert fill2 - interpolated2 > 0.1 and fill4 - interpolated4 > 0.0, (fill2, fill4, interpolated2, interpolated4)
