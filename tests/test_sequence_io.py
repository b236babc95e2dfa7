"""``stereocli match`` on sequences end to end: a folder of frames (``--sequence``), two videos,
one side-by-side or top-bottom video, frame outputs by index, ``--video-out``, ``--skip-existing``,
interrupts, and the one-line refusals of inputs that make no sequence."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import REPO, assert_clean
from stereocli.io.images import write_image
from stereocli.io.pfm import read_pfm

#: Frame size and the disparity every synthetic frame has, px.
H, W, D = 48, 96, 6


def textured_frames(n: int, *, height: int = H, width: int = W, disparity: int = D,
                    seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` grey (left, right) frames of a random texture at one disparity, the texture sliding
    one pixel a frame (so the frames differ)."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (height, width + disparity + n + 8), dtype=np.uint8), (3, 3), 0)
    # right(x - d) = left(x): the right view starts d pixels later in the texture.
    return [(base[:, i: i + width].copy(), base[:, i + disparity: i + disparity + width].copy()) for i in range(n)]


def video_codec() -> tuple[str, str]:
    """A (suffix, FourCC) whose videos OpenCV writes and reads back here, lossless first; skips
    the test when none does."""
    for suffix, code in ((".avi", "FFV1"), (".mkv", "FFV1"), (".mp4", "mp4v"), (".avi", "MJPG")):
        probe = Path(os.environ.get("TMPDIR", "/tmp")) / f".stereocli-codec-probe-{os.getpid()}{suffix}"
        try:
            writer = cv2.VideoWriter(str(probe), cv2.VideoWriter_fourcc(*code), 10, (32, 16))
            if not writer.isOpened():
                continue
            for value in (0, 128):
                writer.write(np.full((16, 32, 3), value, np.uint8))
            writer.release()
            capture = cv2.VideoCapture(str(probe), cv2.CAP_FFMPEG)
            count = 0
            while capture.grab():
                count += 1
            capture.release()
            if count == 2:
                return suffix, code
        finally:
            probe.unlink(missing_ok=True)
    pytest.skip("OpenCV writes no video codec it reads back here (FFV1, mp4v, MJPG)")


def write_video(path: Path, frames: list[np.ndarray], *, code: str, fps: float = 12.0) -> Path:
    """``frames`` (grey or RGB uint8, one size) as a video."""
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*code), fps, (width, height))
    assert writer.isOpened()
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame[..., ::-1])
    writer.release()
    return path


def video_frames(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame[..., ::-1])
    capture.release()
    return frames


def write_folder(root: Path, frames, layout: str = "left/right", stems=None) -> Path:
    """The frames as image files of ``layout``: ``left/right`` or ``cam0/cam1`` subfolders, or
    ``side-word`` files (``left_<stem>.png``)."""
    stems = stems or [f"{i:03d}" for i in range(len(frames))]
    for stem, (left, right) in zip(stems, frames):
        if layout == "side-word":
            write_image(root / f"left_{stem}.png", left)
            write_image(root / f"right_{stem}.png", right)
        else:
            a, b = layout.split("/")
            write_image(root / a / f"{stem}.png", left)
            write_image(root / b / f"{stem}.png", right)
    return root


def frame_folders(out: Path) -> list[str]:
    return sorted(p.name for p in out.iterdir() if p.is_dir())


def median_disparity(out: Path, frame: str) -> float:
    disparity = read_pfm(out / frame / "disp0.pfm")
    assert disparity.shape == (H, W) and disparity.dtype == np.float32
    return float(np.median(disparity[:, 2 * D:]))


# --- folders of frames ---------------------------------------------------------------------------


def test_a_folder_sequence_writes_each_frame_by_index_in_stem_order(run_cli, tmp_path):
    # Stems 1, 2, 10: natural order, so frame 000002 is the pair of stem 10.
    root = write_folder(tmp_path / "seq", textured_frames(3), stems=["10", "2", "1"])
    out = tmp_path / "out"
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16", "--npy", "--png16", "256", "--viz",
                "--confidence")
    assert r.code == 0, r.err
    assert frame_folders(out) == ["000000", "000001", "000002"]
    for frame, stem in zip(("000000", "000001", "000002"), ("1", "2", "10")):
        params = json.loads((out / frame / "params.json").read_text())
        assert Path(params["inputs"]["left"]).name == f"{stem}.png"
        assert params["sequence"]["frame"] == int(frame) and params["sequence"]["temporal"] == "on"
        assert params["ndisp"] == 16
        assert abs(median_disparity(out, frame) - D) < 0.1
        for name in ("disp0.npy", "disp0.png", "disp0_viz.png", "conf0.pfm", "time.txt"):
            assert (out / frame / name).is_file()
    record = json.loads((out / "run.json").read_text())
    assert record["summary"] == {"ok": 3, "skipped": 0, "failed": 0}
    sequence = record["sequence"]
    assert sequence["kind"] == "folder" and sequence["frames"] == 3 and sequence["fps"] is None
    assert sequence["survey_frames"] == [0] and sequence["survey_refreshes"] == [] and sequence["matched"] == 3
    assert_clean(out, ("000000", "000001", "000002"))


@pytest.mark.parametrize("layout", ["cam0/cam1", "side-word"])
def test_every_frame_layout_pairs_as_a_sequence(run_cli, tmp_path, layout):
    root = write_folder(tmp_path / "seq", textured_frames(2), layout=layout)
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--ndisp", "16", "--temporal", "off")
    assert r.code == 0, r.err
    assert frame_folders(tmp_path / "out") == ["000000", "000001"]
    assert json.loads((tmp_path / "out" / "000001" / "params.json").read_text())["sequence"]["temporal"] == "off"


def test_two_folders_are_the_left_and_right_views(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(2))
    r = run_cli("match", "--sequence", root / "left", root / "right", "-o", tmp_path / "out", "--ndisp", "16")
    assert r.code == 0, r.err
    assert frame_folders(tmp_path / "out") == ["000000", "000001"]


def test_a_failing_frame_fails_alone_and_the_run_exits_3(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(3))
    (root / "right" / "001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    write_image(root / "left" / "zz.png", textured_frames(1)[0][0])  # no right partner
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--ndisp", "16")
    assert r.code == 3, r.err
    assert "001.png: unreadable or truncated" in r.err and "zz.png: no matching right image" in r.err
    assert "Traceback" not in r.err
    assert frame_folders(tmp_path / "out") == ["000000", "000002"]
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["summary"] == {"ok": 2, "skipped": 0, "failed": 2}


def test_a_frame_of_another_size_fails_naming_both_sizes(run_cli, tmp_path):
    frames = textured_frames(2) + textured_frames(1, width=80)
    root = write_folder(tmp_path / "seq", frames)
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--ndisp", "16")
    assert r.code == 3
    assert "000002: views of 80x48 and 80x48; the sequence's frames are 96x48" in r.err


def test_require_aligned_fails_a_frame_whose_rows_are_out_of_line(run_cli, tmp_path):
    frames = [(left, np.roll(right, 5, axis=0)) for left, right in textured_frames(2, height=192, width=256)]
    root = write_folder(tmp_path / "seq", frames)
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--ndisp", "16", "--require-aligned")
    assert r.code in (1, 3), r.err  # the frames whose survey measures the rows fail; the first one does
    assert "Error: 000000: rows not aligned" in r.err and "(--require-aligned)" in r.err
    assert not (tmp_path / "out" / "000000").exists()
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "warned", "--ndisp", "16")
    assert r.code == 0 and "Warning: 000000: rows not aligned" in r.err


def test_skip_existing_resumes_a_sequence_from_the_frames_to_redo(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(4))
    out = tmp_path / "out"
    assert run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16").code == 0
    first = (out / "000003" / "disp0.pfm").read_bytes()
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16")
    assert r.code == 1 and "--skip-existing to resume" in r.err
    import shutil

    shutil.rmtree(out / "000002")
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16", "--skip-existing")
    assert r.code == 0 and "1 ok, 3 skipped, 0 failed" in r.err, r.err
    record = json.loads((out / "run.json").read_text())
    # The matcher is seeded with frame 1's outputs: frame 2 reuses its survey and its map.
    assert record["sequence"]["matched"] == 1 and record["sequence"]["seeded_from"] == 1
    assert record["sequence"]["survey_frames"] == []
    assert [i["status"] for i in record["items"]] == ["skipped", "skipped", "ok", "skipped"]
    params = json.loads((out / "000002" / "params.json").read_text())
    assert params["sequence"]["survey"] == "reused" and params["ndisp"] == 16
    assert abs(median_disparity(out, "000002") - D) < 0.1
    assert (out / "000003" / "disp0.pfm").read_bytes() == first
    # Other settings make every frame stale: all are redone.
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16", "--skip-existing", "--temporal", "off")
    assert r.code == 0 and "4 ok, 0 skipped" in r.err and "000000: stale outputs redone" in r.err


def test_a_resumed_sequence_reuses_the_estimated_range_and_rows_of_the_frame_before(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(3))
    out = tmp_path / "out"
    assert run_cli("match", "--sequence", root, "-o", out).code == 0
    before = json.loads((out / "000001" / "params.json").read_text())
    import shutil

    shutil.rmtree(out / "000002")
    r = run_cli("match", "--sequence", root, "-o", out, "--skip-existing")
    assert r.code == 0 and "1 ok, 2 skipped, 0 failed" in r.err, r.err
    params = json.loads((out / "000002" / "params.json").read_text())
    assert params["sequence"]["survey"] == "reused"
    assert (params["min_disp"], params["ndisp"]) == (before["min_disp"], before["ndisp"])
    assert params["range"]["source"] == "estimated"
    assert abs(median_disparity(out, "000002") - D) < 0.1


def test_a_frame_without_usable_outputs_before_it_starts_the_matcher_afresh(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(3))
    out = tmp_path / "out"
    assert run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16").code == 0
    (out / "000001" / "disp0.pfm").write_bytes(b"PF\nnot a map")
    import shutil

    shutil.rmtree(out / "000002")
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16", "--skip-existing")
    assert r.code == 0 and "1 ok, 2 skipped, 0 failed" in r.err, r.err
    record = json.loads((out / "run.json").read_text())
    assert record["sequence"]["seeded_from"] is None and record["sequence"]["survey_frames"] == [2]


def test_right_view_maps_come_with_temporal_off(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(2))
    out = tmp_path / "out"
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "16", "--right", "--temporal", "off")
    assert r.code == 0, r.err
    for frame in ("000000", "000001"):
        right = read_pfm(out / frame / "disp1.pfm")
        assert right.shape == (H, W) and abs(float(np.median(right[:, : W - 2 * D])) - D) < 0.1


def test_dry_run_prints_the_frames_and_writes_nothing(run_cli, tmp_path):
    root = write_folder(tmp_path / "seq", textured_frames(2))
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--dry-run")
    assert r.code == 0
    plan = r.json()
    assert plan["sequence"]["kind"] == "folder" and plan["sequence"]["frames"] == 2
    assert [i["name"] for i in plan["items"]] == ["000000", "000001"] and plan["items"][1]["frame"] == 1
    assert plan["items"][0]["ndisp"] == "auto" and plan["items"][0]["range_source"] == "estimated"
    assert not (tmp_path / "out").exists()


# --- videos ---------------------------------------------------------------------------------------


def test_two_videos_give_one_map_per_frame(run_cli, tmp_path):
    suffix, code = video_codec()
    frames = textured_frames(4)
    left = write_video(tmp_path / f"left{suffix}", [f[0] for f in frames], code=code)
    right = write_video(tmp_path / f"right{suffix}", [f[1] for f in frames], code=code)
    out = tmp_path / "out"
    r = run_cli("match", left, right, "-o", out, "--ndisp", "16")
    assert r.code == 0, r.err
    assert frame_folders(out) == [f"{i:06d}" for i in range(4)]
    for frame in frame_folders(out):
        assert abs(median_disparity(out, frame) - D) < 0.5  # the codec may be lossy
    params = json.loads((out / "000001" / "params.json").read_text())
    assert params["inputs"] == {"left": str(left), "right": str(right)}
    sequence = json.loads((out / "run.json").read_text())["sequence"]
    assert sequence["kind"] == "videos" and sequence["frames"] == 4 and sequence["fps"] == pytest.approx(12.0)
    assert sequence["videos"] == [str(left), str(right)]


@pytest.mark.parametrize("layout", ["side-by-side", "top-bottom"])
def test_one_stacked_video_gives_one_map_per_frame(run_cli, tmp_path, layout):
    suffix, code = video_codec()
    axis = 1 if layout == "side-by-side" else 0
    stacked = [np.concatenate([left, right], axis=axis) for left, right in textured_frames(3)]
    video = write_video(tmp_path / f"rig{suffix}", stacked, code=code)
    out = tmp_path / "out"
    r = run_cli("match", f"--{layout}", video, "-o", out, "--ndisp", "16")
    assert r.code == 0, r.err
    assert frame_folders(out) == ["000000", "000001", "000002"]
    for frame in frame_folders(out):
        assert abs(median_disparity(out, frame) - D) < 0.5
    sequence = json.loads((out / "run.json").read_text())["sequence"]
    assert sequence["kind"] == layout and sequence["frames"] == 3


def box_frame(background: int, box: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A (left, right) frame: a textured background at disparity ``background`` and a textured
    box (rows 16-32, columns 40-70) in front at disparity ``box``."""
    rng = np.random.default_rng(seed)
    far = cv2.GaussianBlur(rng.integers(0, 256, (H, W + 32), dtype=np.uint8), (3, 3), 0)
    near = cv2.GaussianBlur(rng.integers(0, 256, (16, 30), dtype=np.uint8), (3, 3), 0)
    left, right = far[:, :W].copy(), far[:, background: background + W].copy()
    left[16:32, 40:70] = near
    right[16:32, 40 - box: 70 - box] = near
    return left, right


def test_video_out_has_one_frame_per_map_and_one_colour_range(run_cli, tmp_path):
    from stereocli.viz import disparity_preview, disparity_range

    suffix, code = video_codec()
    # Frame 0 spans disparities 4-10, frame 1 8-16: in one range (frame 0's), frame 1's background
    # (8) is near the top of the colours; in its own range it would be at the bottom.
    root = write_folder(tmp_path / "seq", [box_frame(4, 10, seed=0), box_frame(8, 16, seed=1)])
    out, video = tmp_path / "out", tmp_path / f"disparity{suffix}"
    r = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "24", "--video-out", video, "--temporal", "off")
    assert r.code == 0, r.err
    assert f"{video}: 2 frames at 10 fps" in r.err
    shown = video_frames(video)
    assert len(shown) == 2 and shown[0].shape[1] >= W
    maps = [read_pfm(out / frame / "disp0.pfm") for frame in ("000000", "000001")]
    one_range = disparity_preview(maps[1], *disparity_range(maps[0]))
    own_range = disparity_preview(maps[1])
    background = (slice(2, 12), slice(24, W - 4))

    def distance(a, b):
        return float(np.abs(a[background].reshape(-1, 3).mean(0) - b[background].reshape(-1, 3).mean(0)).max())

    assert distance(own_range, one_range) > 60  # the two colourings differ: the test can tell them apart
    assert distance(shown[1], one_range) < 20
    # --viz-range sets the range; an existing video is refused, --overwrite replaces it.
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "o2", "--ndisp", "16", "--video-out", video)
    assert r.code == 1 and "already exists" in r.err
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "o3", "--ndisp", "16", "--video-out", video,
                "--viz-range", "0:16", "--overwrite")
    assert r.code == 0 and "colours 0 to 16 px" in r.err


def test_video_out_writes_failed_frames_black(run_cli, tmp_path):
    suffix, code = video_codec()
    root = write_folder(tmp_path / "seq", textured_frames(3))
    (root / "left" / "001.png").write_bytes(b"not an image")
    video = tmp_path / f"v{suffix}"
    r = run_cli("match", "--sequence", root, "-o", tmp_path / "out", "--ndisp", "16", "--video-out", video)
    assert r.code == 3
    assert f"{video}: 3 frames at 10 fps" in r.err and "1 black (no map)" in r.err
    shown = video_frames(video)
    assert len(shown) == 3 and shown[1].max() < 40 and shown[0].max() > 100


# --- refusals -------------------------------------------------------------------------------------


def test_inputs_that_make_no_sequence_are_refused_in_one_line(run_cli, tmp_path):
    suffix, code = video_codec()
    frames = textured_frames(2)
    video = write_video(tmp_path / f"a{suffix}", [f[0] for f in frames], code=code)
    right_video = write_video(tmp_path / f"b{suffix}", [f[1] for f in frames], code=code)
    image = write_folder(tmp_path / "seq", frames) / "left" / "000.png"
    out = tmp_path / "out"
    cases = [
        (("match", video, "-o", out), 2, "a video holds one view: give the left and the right view's videos"),
        (("match", video, image, "-o", out), 2, "000.png: not a video"),
        (("match", "--sequence", image, image, "-o", out), 2, "--sequence takes one folder of frames"),
        (("match", "--side-by-side", video, video, "-o", out), 2, "--side-by-side takes one video file"),
        (("match", "--top-bottom", tmp_path / "seq", "-o", out), 2, "--top-bottom takes one video file"),
        (("match", "--side-by-side", "--top-bottom", video, "-o", out), 2, "exclude each other"),
        (("match", tmp_path / "seq", "-o", out, "--temporal", "off"), 2, "--temporal applies to sequences"),
        (("match", tmp_path / "seq", "-o", out, "--video-out", tmp_path / "v.avi"), 2,
         "--video-out applies to sequences"),
        (("match", "--sequence", tmp_path / "seq", "-o", out, "--video-out", tmp_path / "v.gif"), 2,
         "--video-out"),
        (("match", video, right_video, "-o", out, "--video-out", right_video), 2, "would replace the input"),
        (("match", "--sequence", tmp_path / "seq", "-o", out, "--right"), 2, "--right needs --temporal off"),
        (("match", "--sequence", tmp_path / "seq", "-o", out, "--jobs", "2"), 2, "--jobs: not available"),
        (("match", "--sequence", tmp_path / "seq", "-o", out, "--retries", "1"), 2, "--retries: not available"),
        (("match", "--sequence", tmp_path / "nowhere", "-o", out), 1, "nowhere: no such file or folder"),
    ]
    for args, exit_code, message in cases:
        r = run_cli(*args)
        assert r.code == exit_code and message in r.err, (args, r.code, r.err)
        assert len(r.err.strip().splitlines()) == 1 and "Traceback" not in r.err, r.err
    assert not out.exists()


def test_an_empty_folder_is_no_sequence(run_cli, tmp_path):
    (tmp_path / "seq" / "left").mkdir(parents=True)
    (tmp_path / "seq" / "right").mkdir()
    r = run_cli("match", "--sequence", tmp_path / "seq", "-o", tmp_path / "out")
    assert r.code == 1 and "no stereo pairs found" in r.err


# --- interrupts -----------------------------------------------------------------------------------


def test_sigterm_keeps_the_finished_frames_and_resume_completes(run_cli, tmp_path):
    n = 40
    root = write_folder(tmp_path / "seq", textured_frames(n, height=192, width=256))
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "stereocli", "match", "--sequence", str(root), "-o", str(out),
                             "--ndisp", "32"], stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and not list(out.glob("*/.stereocli-match.done")) and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "the sequence should still be running"
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=30)[1]
    assert proc.returncode == 143, err
    assert "Interrupted (SIGTERM)" in err and "Traceback" not in err
    done = sorted(p.parent.name for p in out.glob("*/.stereocli-match.done"))
    assert 0 < len(done) < n
    assert_clean(out, tuple(done))
    record = json.loads((out / "run.json").read_text())
    assert record["interrupted"] is True and record["planned"] == n and record["sequence"]["frames"] == n
    resumed = run_cli("match", "--sequence", root, "-o", out, "--ndisp", "32", "--skip-existing")
    assert resumed.code == 0 and f"{n - len(done)} ok, {len(done)} skipped, 0 failed" in resumed.err
