"""Stereo sequences: synthetic sequences with ground truth, survey reuse and refresh, the temporal
reuse (flicker, accuracy, edges), ``temporal="off"`` equal to frame-by-frame matching."""

from __future__ import annotations

import numpy as np
import pytest

import stereocli
from stereocli.errors import ConfigError, DataError
from stereocli.sequence import SequenceMatcher, match_sequence
from stereocli.synth.sequences import make_sequence, paste_object, sequence_from_pair


@pytest.fixture(scope="module")
def moving():
    return make_sequence("moving", frames=8, width=320, height=240, seed=3)


@pytest.fixture(scope="module")
def moving_runs(moving):
    runs = {}
    for temporal in ("off", "on"):
        matcher = SequenceMatcher(temporal=temporal)
        runs[temporal] = [matcher.push(left, right) for left, right in moving.pairs()]
    return runs


def _flicker(maps, seq) -> float:
    changed = total = 0
    for i in range(1, len(maps)):
        static = (np.abs(seq.disparity[i] - seq.disparity[i - 1]) < 0.1) & ~seq.moving[i] & ~seq.moving[i - 1]
        changed += int(np.count_nonzero(~(np.abs(maps[i] - maps[i - 1]) <= 0.5) & static))
        total += int(static.sum())
    return changed / total


def _bad1(maps, seq, where=None) -> float:
    shares = []
    for i, (disparity, gt) in enumerate(zip(maps, seq.disparity)):
        mask = np.isfinite(gt) if where is None else where(i)
        if mask.any():
            shares.append(float(np.mean(~(np.abs(disparity[mask] - gt[mask]) <= 1.0))))
    return 100 * float(np.mean(shares))


# --------------------------------------------------------------------------- synthetic sequences


def test_moving_sequence_ground_truth_follows_the_disc(moving):
    assert len(moving) == 8 and moving.left[0].shape == (240, 320, 3) and moving.left[0].dtype == np.uint8
    top = max(float(gt[~m].max()) for gt, m in zip(moving.disparity, moving.moving))
    for gt, mask in zip(moving.disparity, moving.moving):
        assert mask.sum() == pytest.approx(np.pi * (0.14 * 240) ** 2, rel=0.03)
        assert np.unique(gt[mask]).tolist() == [pytest.approx(top + 0.03 * 320)]
    # The disc moves to the right every frame; the scene behind it holds still.
    centres = [np.flatnonzero(m.any(axis=0)).mean() for m in moving.moving]
    assert all(b > a + 5 for a, b in zip(centres, centres[1:]))
    behind = ~moving.moving[0] & ~moving.moving[-1]
    assert np.array_equal(moving.disparity[0][behind], moving.disparity[-1][behind])
    assert moving.ndisp % 16 == 0 and moving.ndisp > top + 0.03 * 320


def test_pan_shifts_the_whole_scene_by_a_pixel_per_frame():
    pan = make_sequence("pan", frames=3, width=120, height=90, noise=0.0)
    for i in (1, 2):
        assert np.array_equal(pan.disparity[i][:, :-1], pan.disparity[i - 1][:, 1:])
        assert np.array_equal(pan.left[i][:, :-1], pan.left[i - 1][:, 1:])
    assert not any(m.any() for m in pan.moving)


def test_still_sequence_differs_only_by_the_noise():
    still = make_sequence("still", frames=2, width=120, height=90, noise=3.0)
    diff = still.left[1].astype(float) - still.left[0].astype(float)
    assert np.array_equal(still.disparity[0], still.disparity[1])
    assert diff.std() == pytest.approx(3.0 * np.sqrt(2), rel=0.08)


def test_pasted_disc_occludes_the_scene_in_the_right_view():
    h, w = 40, 80
    left = np.full((h, w, 3), 50.0, np.float32)
    texture = np.full((40, 40, 3), 200.0, np.float32)
    _, right, gt, mask = paste_object(left, left.copy(), np.full((h, w), 5.0, np.float32), texture,
                                      centre=(40.0, 20.0), radius=8.0, object_disparity=12.0)
    assert gt[20, 40] == 12.0 and gt[20, 20] == 5.0 and mask[20, 40] and not mask[20, 20]
    # In the right view the disc sits 12 px to the left of where the left view has it.
    assert right[20, 28, 0] == 200.0 and right[20, 40, 0] == 50.0


# --------------------------------------------------------------------------- survey


def test_temporal_off_equals_frame_by_frame_matching(moving_runs, moving):
    results = moving_runs["off"]
    first = stereocli.match(moving.left[0], moving.right[0])
    assert np.array_equal(results[0].disparity, first.disparity)
    for result, (left, right) in list(zip(results, moving.pairs()))[1:4]:
        alone = stereocli.match(left, right, ndisp=first.range.ndisp, min_disp=first.range.min_disp)
        assert np.array_equal(result.disparity, alone.disparity)
        assert result.range.ndisp == first.range.ndisp


def test_survey_is_measured_once_and_reused(moving_runs):
    for temporal in ("off", "on"):
        notes = [r.notes["sequence"] for r in moving_runs[temporal]]
        assert [n["frame"] for n in notes] == list(range(8))
        assert [n["survey"] for n in notes] == ["measured"] + ["reused"] * 7
        assert all(n["temporal"] == temporal for n in notes)


def test_survey_refreshed_when_the_scene_comes_nearer_than_its_range():
    rng = np.random.default_rng(5)
    texture = rng.integers(0, 256, (60, 160), dtype=np.uint8)
    far = (texture, np.roll(texture, -4, axis=1))
    near = (texture, np.roll(texture, -40, axis=1))
    matcher = SequenceMatcher(temporal="on")
    results = [matcher.push(*pair) for pair in (far, far, near, near)]
    assert [r.notes["sequence"]["survey"] for r in results] == ["measured", "reused", "refreshed", "reused"]
    assert matcher.survey_frames == [0, 2]
    assert matcher.record()["survey_frames"] == [0, 2]
    assert results[0].range.max_disp < 40 <= results[2].range.max_disp
    assert float(np.median(results[3].disparity[:, 48:])) == pytest.approx(40.0, abs=0.5)


def test_a_given_range_is_reused_and_never_refreshed():
    rng = np.random.default_rng(6)
    texture = rng.integers(0, 256, (48, 96), dtype=np.uint8)
    results = list(match_sequence([(texture, np.roll(texture, -3, axis=1))] * 3, ndisp=16, temporal="on"))
    assert [r.range.ndisp for r in results] == [16, 16, 16]
    assert [r.notes["sequence"]["survey"] for r in results] == ["measured", "reused", "reused"]


# --------------------------------------------------------------------------- temporal reuse


def test_temporal_filter_halves_flicker_without_losing_accuracy(moving_runs, moving):
    off = [r.disparity for r in moving_runs["off"]]
    on = [r.disparity for r in moving_runs["on"]]
    assert _flicker(on, moving) <= 0.5 * _flicker(off, moving)
    assert _bad1(on, moving) <= _bad1(off, moving) + 0.2
    assert _bad1(on, moving, lambda i: moving.moving[i]) <= _bad1(off, moving, lambda i: moving.moving[i]) + 0.2


def test_moving_edges_do_not_trail(moving_runs, moving):
    # Where the disc was and is no longer: the scene behind it must come back at once.
    left_behind = lambda i: moving.moving[i - 1] & ~moving.moving[i] if i else np.zeros_like(moving.moving[0])  # noqa
    off = [r.disparity for r in moving_runs["off"]]
    on = [r.disparity for r in moving_runs["on"]]
    assert _bad1(on, moving, left_behind) <= _bad1(off, moving, left_behind) + 1.0


def test_still_scene_is_matched_whole_every_third_frame_only():
    still = make_sequence("still", frames=7, width=240, height=180, noise=3.0)
    matcher = SequenceMatcher(temporal="on", refresh_every=3)
    notes = [matcher.push(left, right).notes["sequence"] for left, right in still.pairs()]
    assert [n["changed"] for n in notes[1:]] == [0.0] * 6
    # Frames 3 and 6 are matched whole; between them nothing changed, so nothing is matched.
    assert [n["rematched"] for n in notes[1:]] == [0.0, 0.0, 1.0, 0.0, 0.0, 1.0]
    assert [n["whole"] for n in notes[1:]] == [False, False, True, False, False, True]
    # The grey of RGB noise of 3 grey levels per channel has 3 x 0.668 grey levels.
    assert notes[-1]["noise_sigma"] == pytest.approx(3 * 0.668, rel=0.15)
    assert matcher.record()["frames"] == 7


def test_a_changed_region_is_matched_with_the_whole_frames_search(moving):
    # Coarse to fine for the whole frame (55 disparities over 320 x 240 px: 4.2 M cells), not for
    # the disc's crop alone: the crop must search as the whole frame does.
    coarse = {"optimizer.coarse_min_volume": 2.0}
    matcher = SequenceMatcher(set=coarse)
    first, second = (matcher.push(left, right) for left, right in list(moving.pairs())[:2])
    assert second.notes["sequence"]["whole"] is False and second.notes["sequence"]["regions"] == 1
    alone = stereocli.match(moving.left[1], moving.right[1], set=coarse, ndisp=first.range.ndisp,
                            min_disp=first.range.min_disp)
    disc = moving.moving[1]
    # (The full-range search on the crop leaves 0.6 % of the disc's pixels more than 0.5 px off.)
    assert np.mean(np.abs(second.disparity[disc] - alone.disparity[disc]) <= 0.5) >= 0.999


def test_temporal_off_gives_right_view_maps_and_warm_up_changes_nothing(moving):
    results = list(match_sequence(list(moving.pairs())[:2], temporal="off", disparity_right=True, warm_up=True))
    alone = stereocli.match(moving.left[1], moving.right[1], ndisp=results[0].range.ndisp,
                            min_disp=results[0].range.min_disp, disparity_right=True)
    assert np.array_equal(results[1].disparity, alone.disparity)
    assert np.array_equal(results[1].disparity_right, alone.disparity_right)
    with pytest.raises(ConfigError, match="disparity_right needs temporal='off'"):
        SequenceMatcher(temporal="on", disparity_right=True)


def test_seed_resumes_after_a_matched_frame(moving):
    first = stereocli.match(moving.left[0], moving.right[0])
    matcher = SequenceMatcher(temporal="on")
    matcher.seed(first.disparity, moving.left[0], moving.right[0], min_disp=first.range.min_disp,
                 ndisp=first.range.ndisp, frame=0, row_align=first.notes.get("row_align"))
    result = matcher.push(moving.left[1], moving.right[1])
    assert result.notes["sequence"]["frame"] == 1 and result.notes["sequence"]["survey"] == "reused"
    assert result.range.ndisp == first.range.ndisp
    assert _bad1([result.disparity], sequence_from_pair(moving.left[1], moving.right[1], moving.disparity[1],
                                                        frames=1, noise=0.0, moving=False)) < 8.0


def test_bad_options_and_frames_are_refused():
    with pytest.raises(ConfigError, match="temporal must be one of on, off"):
        SequenceMatcher(temporal="sometimes")
    with pytest.raises(ConfigError, match="refresh_every must be a whole number >= 1"):
        SequenceMatcher(refresh_every=0)
    rng = np.random.default_rng(2)
    texture = rng.integers(0, 256, (48, 96), dtype=np.uint8)
    matcher = SequenceMatcher(ndisp=16, name="clip")
    matcher.push(texture, np.roll(texture, -3, axis=1))
    with pytest.raises(DataError, match="clip: frame 1 is 48x96; the sequence's frames are 96x48"):
        matcher.push(texture.T.copy(), texture.T.copy())


def test_whole_frame_refreshes_search_around_the_previous_map_but_every_third(monkeypatch):
    import stereocli.matching.warmup as warmup
    from stereocli.sequence import WIDE_REFRESH_EVERY

    narrowed = []
    original = warmup.with_coarse_level

    def counted(config, coarse_level):
        narrowed.append(coarse_level)
        return original(config, coarse_level)

    monkeypatch.setattr(warmup, "with_coarse_level", counted)
    still = make_sequence("still", frames=7, width=240, height=180, noise=3.0)
    matcher = SequenceMatcher(refresh_every=1)  # every later frame is a whole-frame refresh
    results = [matcher.push(left, right) for left, right in still.pairs()]
    assert WIDE_REFRESH_EVERY == 3
    assert len(narrowed) == 4  # refreshes 1, 2, 4 and 5 narrowed; 3 and 6 searched the full range
    assert all(r.notes["sequence"]["whole"] for r in results[1:])
    assert _bad1([r.disparity for r in results], still) <= _bad1([results[0].disparity], still) + 0.5


def test_the_previous_map_narrows_only_pixels_away_from_a_change():
    from stereocli.matching.state import MatchState
    from stereocli.sequence import PRIOR_MARGIN, _prior_coarse_level

    disparity = np.full((40, 60), 12.0, np.float32)
    disparity[5, 5] = np.inf
    changed = np.zeros((40, 60), bool)
    changed[20, 30] = True
    state = MatchState(np.zeros((40, 60), np.float32), np.zeros((40, 60), np.float32), 0, 32)
    coarse = _prior_coarse_level(disparity, changed)(state, None, None)
    assert coarse.shape == (20, 30) and coarse.dtype == np.float32
    near = np.zeros((40, 60), bool)
    near[20 - PRIOR_MARGIN:21 + PRIOR_MARGIN, 30 - PRIOR_MARGIN:31 + PRIOR_MARGIN] = True
    near[5, 5] = True  # invalid: no prior
    expected = np.where(near, np.inf, 6.0)[::2, ::2]  # coarse px: half the disparity
    np.testing.assert_array_equal(coarse, expected.astype(np.float32))
    # A strip's rows: the prior's rows from its offset.
    strip = MatchState(np.zeros((16, 60), np.float32), np.zeros((16, 60), np.float32), 0, 32, row_offset=16)
    np.testing.assert_array_equal(_prior_coarse_level(disparity, changed)(strip, None, None), expected[8:16])
