"""Hostile videos for ``stereocli match``: garbage, empty, truncated, mismatched pairs of videos,
stacked frames that do not split. Each gives a one-line message naming the file and the exit
code of the rules (1 data, 2 usage), or a warning saying what is matched."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from test_sequence_io import frame_folders, textured_frames, video_codec, write_video


@pytest.mark.parametrize("content", [b"", b"hello video" * 100, b"\x00\x00\x00\x18ftypmp42" + bytes(500)],
                         ids=["empty", "text", "header-only"])
def test_a_file_that_is_no_video_fails_in_one_line(run_cli, tmp_path, content):
    suffix, code = video_codec()
    good = write_video(tmp_path / f"good{suffix}", [f[1] for f in textured_frames(2)], code=code)
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(content)
    for args in ((bad, good), (good, bad), ("--side-by-side", bad)):
        r = run_cli("match", *args, "-o", tmp_path / "out")
        assert r.code == 1, r.err
        assert re.search(r"bad\.mp4: (cannot be read as a video|no video frame decodes)", r.err), r.err
        assert len(r.err.strip().splitlines()) == 1 and "Traceback" not in r.err
    assert not (tmp_path / "out").exists()


def test_a_truncated_video_matches_the_frames_that_decode_with_a_warning(run_cli, tmp_path):
    suffix, code = video_codec()
    if suffix == ".mp4":
        pytest.skip("a cut MP4 loses its index and does not open at all (covered above)")
    frames = textured_frames(12)
    left = write_video(tmp_path / f"left{suffix}", [f[0] for f in frames], code=code)
    right = write_video(tmp_path / f"right{suffix}", [f[1] for f in frames], code=code)
    data = right.read_bytes()
    right.write_bytes(data[: len(data) // 2])
    r = run_cli("match", left, right, "-o", tmp_path / "out", "--ndisp", "16")
    found = re.search(r"right\.\w+: its header states 12 frames and (\d+) decode; \1 are matched", r.err)
    assert found, r.err
    decoded = int(found.group(1))
    assert 0 < decoded < 12
    assert r.code == 0 and f"the first {decoded} of each are matched" in r.err
    assert len(frame_folders(tmp_path / "out")) == decoded


def test_videos_of_different_sizes_are_refused(run_cli, tmp_path):
    suffix, code = video_codec()
    left = write_video(tmp_path / f"left{suffix}", [f[0] for f in textured_frames(2)], code=code)
    right = write_video(tmp_path / f"right{suffix}", [f[1] for f in textured_frames(2, width=80)], code=code)
    r = run_cli("match", left, right, "-o", tmp_path / "out")
    assert r.code == 1
    assert f"{left} is 96x48 and {right} 80x48: the two views of a stereo video must have one frame size" in r.err


def test_videos_of_different_rates_are_refused(run_cli, tmp_path):
    suffix, code = video_codec()
    frames = textured_frames(2)
    left = write_video(tmp_path / f"left{suffix}", [f[0] for f in frames], code=code, fps=25)
    right = write_video(tmp_path / f"right{suffix}", [f[1] for f in frames], code=code, fps=30)
    r = run_cli("match", left, right, "-o", tmp_path / "out")
    assert r.code == 1 and "runs at 25 and" in r.err and "at 30 frames per second" in r.err


def test_videos_of_different_lengths_match_the_shorter(run_cli, tmp_path):
    suffix, code = video_codec()
    frames = textured_frames(5)
    left = write_video(tmp_path / f"left{suffix}", [f[0] for f in frames], code=code)
    right = write_video(tmp_path / f"right{suffix}", [f[1] for f in frames[:3]], code=code)
    r = run_cli("match", left, right, "-o", tmp_path / "out", "--ndisp", "16")
    assert r.code == 0, r.err
    assert f"Warning: {left} has 5 frames and {right} 3: the first 3 of each are matched" in r.err
    assert frame_folders(tmp_path / "out") == ["000000", "000001", "000002"]
    sequence = json.loads((tmp_path / "out" / "run.json").read_text())["sequence"]
    assert sequence["frames"] == 3 and "the first 3 of each are matched" in sequence["warnings"][0]


@pytest.mark.parametrize("layout,shape", [("side-by-side", (48, 97)), ("top-bottom", (49, 96))])
def test_a_stacked_frame_with_an_odd_side_is_refused(layout, shape):
    # (OpenCV's writers round frame sizes to even numbers, so the frame is made here.)
    from stereocli.errors import DataError
    from stereocli.io.video import split_stacked

    side = "width" if layout == "side-by-side" else "height"
    with pytest.raises(DataError, match=f"^rig.mp4: {layout} frames need an even {side} to split into two views; "
                                        f"this one is {shape[1] if side == 'width' else shape[0]} px$"):
        split_stacked(np.zeros(shape, np.uint8), layout, "rig.mp4")
    left, right = split_stacked(np.arange(4 * 6).reshape(4, 6), layout)
    assert (left.shape, right.shape) == (((4, 3), (4, 3)) if side == "width" else ((2, 6), (2, 6)))
    assert right[0, 0] == (3 if side == "width" else 12)


def test_a_directory_named_like_a_video_is_a_folder(run_cli, tmp_path):
    folder = tmp_path / "clip.mp4"
    (folder / "left").mkdir(parents=True)
    (folder / "right").mkdir()
    r = run_cli("match", folder, "-o", tmp_path / "out")
    assert r.code == 1 and "no stereo pairs found" in r.err
