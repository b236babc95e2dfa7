"""``stereocli match`` on a stereo sequence: frames -> work items run in order by one
:class:`~stereocli.sequence.SequenceMatcher`, and the colourised disparity video (``--video-out``).

A sequence comes from (:func:`find_sequence`):

* a folder of frames, paired as :mod:`stereocli.io.pairs` pairs them (``left/`` + ``right/``,
  ``cam0/`` + ``cam1/``, ``left01``/``right01`` files, scene folders such as ``rectify`` writes;
  or two folders), in the natural order of the pair names. The first frame's ``calib.txt`` and
  valid masks hold for the whole sequence;
* two videos, the left and the right view. Videos of different frame sizes or rates are refused;
  of different lengths, the frames both have are matched (with a warning);
* one video holding both views, ``side-by-side`` or ``top-bottom`` (left view left / on top).

Frame ``i`` writes ``OUTDIR/<i as 6 digits>/`` (``000000``, ``000001``, ...) with the outputs of a
matched pair (:func:`~stereocli.jobs.match.write_match_outputs`), committed and marked complete as
batch items are (:mod:`stereocli.jobs.items`). The frames run in one process, in order, through
the batch runner's inline executor: interrupts, ``--skip-existing`` and the run record behave as
for batches. A resumed sequence seeds the matcher with the outputs of the frame before the
first it redoes (:meth:`SequenceRun._seed`), else starts it afresh there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, DataError, check_outputs_free
from ..io.pairs import StereoInput, natural_key
from .items import RESUME_HINT, WorkItem, check_output_paths, settings_digest
from .match import match_options, match_outputs, output_settings, resolve_range, write_match_outputs

#: The output folder name of frame ``i``.
FRAME_NAME = "{:06d}"
#: Frames per second of ``--video-out`` for a sequence of image files (which states none).
DEFAULT_FPS = 10.0
#: Largest relative difference between the frame rates of two videos matched together.
FPS_TOLERANCE = 0.01


@dataclass
class SequenceSource:
    """Where the frames of one sequence come from (see the module's docstring).

    ``kind`` is ``folder`` (``pairs``), ``videos`` (``videos`` = left, right) or a stacked
    layout (``side-by-side``, ``top-bottom``; ``videos`` = the one video). ``fps`` is the
    videos' frame rate (None for image files); ``warnings`` are one line each; ``problems`` are
    image files that did not pair (failed items, as in a batch).
    """

    kind: str
    frames: int
    fps: float | None = None
    pairs: list[StereoInput] = field(default_factory=list)
    videos: tuple[str, ...] = ()
    warnings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def shared_inputs(self) -> dict[str, str]:
        """The first frame's ``calib.txt`` and valid masks, which hold for every frame."""
        first = self.pairs[0] if self.pairs else None
        return {key: getattr(first, key) for key in ("calib", "left_valid", "right_valid")
                if first is not None and getattr(first, key)}

    def frame_inputs(self, index: int) -> dict[str, str]:
        """The input files of frame ``index`` (what its completion marker records)."""
        if self.kind == "folder":
            pair = self.pairs[index]
            return {"left": pair.left, "right": pair.right, **self.shared_inputs}
        if self.kind == "videos":
            return {"left": self.videos[0], "right": self.videos[1]}
        return {"video": self.videos[0]}

    def as_record(self) -> dict[str, Any]:
        """The source as the run record states it."""
        record: dict[str, Any] = {"kind": self.kind, "frames": self.frames, "fps": self.fps}
        if self.videos:
            record["videos"] = list(self.videos)
        else:
            record["first"], record["last"] = self.pairs[0].name, self.pairs[-1].name
            record.update(self.shared_inputs)
        if self.warnings:
            record["warnings"] = list(self.warnings)
        return record


def wants_sequence(inputs: list[str] | tuple[str, ...]) -> bool:
    """Whether the command-line ``inputs`` hold a video (which makes them a sequence)."""
    from ..io.video import is_video

    return any(Path(p).is_file() and is_video(p) for p in inputs)


def find_sequence(inputs: list[str] | tuple[str, ...], *, layout: str | None = None) -> SequenceSource:
    """The sequence of the command-line ``inputs`` (one folder or two, two videos, or one
    video of ``layout``). Raises :class:`ConfigError` for inputs that make no sequence, and
    :class:`DataError` for unreadable or mismatched ones, naming the file."""
    from ..io.video import is_video

    for path in inputs:
        if not Path(path).exists():
            raise DataError(f"{path}: no such file or folder")
    videos = [p for p in inputs if Path(p).is_file() and is_video(p)]
    if layout is not None:
        if len(inputs) != 1 or not videos:
            raise ConfigError(f"--{layout} takes one video file holding both views (the left view "
                              f"{'on the left' if layout == 'side-by-side' else 'on top'})")
        return _stacked_video(videos[0], layout)
    if videos:
        others = [p for p in inputs if p not in videos]
        if others:
            raise ConfigError(f"{others[0]}: not a video; a sequence from videos takes two video files (left, right)")
        if len(videos) != 2:
            raise ConfigError(f"{videos[0]}: a video holds one view: give the left and the right view's videos, or "
                              "--side-by-side / --top-bottom for one video holding both" if len(videos) == 1 else
                              f"{len(videos)} videos given; a sequence from videos takes two (left, right)")
        return _two_videos(*videos)
    files = [p for p in inputs if Path(p).is_file()]
    if files or len(inputs) > 2:
        raise ConfigError(f"{files[0] if files else inputs[2]}: --sequence takes one folder of frames (left/ + right/, "
                          "cam0/ + cam1/, left01/right01 files, scene folders) or two folders (left, right)")
    return _folder_frames(inputs)


def _folder_frames(inputs) -> SequenceSource:
    from ..io.pairs import discover_pairs

    pairs, problems = discover_pairs(inputs)
    pairs.sort(key=lambda pair: natural_key(pair.name))
    return SequenceSource("folder", len(pairs), pairs=pairs, problems=problems)


def _two_videos(left: str, right: str) -> SequenceSource:
    from ..io.video import probe_video

    views = [probe_video(left), probe_video(right)]
    a, b = views
    if (a.width, a.height) != (b.width, b.height):
        raise DataError(f"{left} is {a.width}x{a.height} and {right} {b.width}x{b.height}: the two views of a stereo "
                        "video must have one frame size")
    if a.fps and b.fps and abs(a.fps - b.fps) > FPS_TOLERANCE * max(a.fps, b.fps):
        raise DataError(f"{left} runs at {a.fps:g} and {right} at {b.fps:g} frames per second: their frames would "
                        "not pair in time")
    warnings = _truncation_warnings(views)
    frames = min(a.frames, b.frames)
    if a.frames != b.frames:
        warnings.append(f"{left} has {a.frames} frames and {right} {b.frames}: the first {frames} of each are matched")
    return SequenceSource("videos", frames, a.fps or b.fps, videos=(left, right), warnings=warnings)


def _stacked_video(path: str, layout: str) -> SequenceSource:
    from ..io.video import probe_video, split_stacked

    info = probe_video(path)
    split_stacked(np.empty((info.height, info.width), np.uint8), layout, path)  # an odd side is refused here
    return SequenceSource(layout, info.frames, info.fps, videos=(path,), warnings=_truncation_warnings([info]))


def _truncation_warnings(views) -> list[str]:
    return [f"{v.path}: its header states {v.header_frames} frames and {v.frames} decode; {v.frames} are matched"
            for v in views if v.frames < v.header_frames]


def plan_sequence(
    source: SequenceSource,
    outdir: str | Path,
    *,
    config: dict,
    ndisp: int | str | None,
    min_disp: int | None,
    temporal: str = "on",
    right: bool = False,
    png16_scale: float | None = None,
    npy: bool = False,
    viz: bool = False,
    viz_range: tuple[float, float] | None = None,
    confidence: bool = False,
    keep_invalid: bool = False,
    require_aligned: bool = False,
    record_info: dict | None = None,
) -> list[WorkItem]:
    """One :class:`WorkItem` per frame of ``source``, named by its index, with the options of
    :func:`~stereocli.jobs.match.plan_items` (less ``split_strips``) and ``temporal``; ``right``
    (the right view's map) needs ``temporal="off"``.

    The range comes from ``--ndisp``/``--min-disp``, else the first frame's ``calib.txt``, else
    the matcher estimates it on the first frame it matches. Raises :class:`ConfigError` when
    an output would land on an input or outside ``outdir``.
    """
    from ..sequence import TEMPORAL_MODES
    from .match import check_confidence

    if temporal not in TEMPORAL_MODES:
        raise ConfigError(f"--temporal must be one of {', '.join(TEMPORAL_MODES)}, got {temporal!r}")
    if right and temporal == "on":
        raise ConfigError("--right needs --temporal off: the temporal filter steadies the left view's map only")
    outdir = Path(outdir)
    if confidence:
        check_confidence(config)
    lo, nd, info = resolve_range(StereoInput("sequence", "", "", calib=source.shared_inputs.get("calib")),
                                 ndisp, min_disp)
    items = []
    for index in range(source.frames):
        name = FRAME_NAME.format(index)
        folder = outdir / name
        options = match_options(config, lo, nd, info, png16_scale=png16_scale, keep_invalid=keep_invalid,
                                require_aligned=require_aligned, viz_range=viz_range, record_info=record_info)
        options.update(frame=index, temporal=temporal, source=source.kind)
        outputs = match_outputs(folder, png16_scale=png16_scale, npy=npy, viz=viz, confidence=confidence, right=right)
        items.append(WorkItem(name, source.frame_inputs(index), outputs, options, folder=str(folder), command="match",
                              config_digest=settings_digest(output_settings(options))))
    check_output_paths(items, outdir)
    return items


class SequenceRun:
    """The item function of a sequence's frames: decodes frame ``item.options["frame"]``,
    matches it with the one :class:`~stereocli.sequence.SequenceMatcher` of the run and writes
    its outputs. Frames must come in order (the batch runner's inline executor). The matcher
    starts at the first frame it is given; a resumed run (``--skip-existing``) seeds it with the
    frame before's outputs when they are there (its map, range and row alignment), so it goes on
    as the interrupted run would have, else it starts afresh.
    """

    def __init__(self, source: SequenceSource, items: list[WorkItem]) -> None:
        self.source = source
        self.options = items[0].options if items else {}
        self.confidence = bool(items) and "confidence" in items[0].outputs
        self.right = bool(items) and "right" in items[0].outputs
        self.by_frame = {item.options["frame"]: item for item in items}
        self.matcher = None
        self.seeded: int | None = None  # the frame whose outputs seeded the matcher
        self.matched: list[int] = []  # frame indices in the order the matcher took them
        self._readers: dict[str, Any] = {}
        self.size: tuple[int, ...] | None = None  # (H, W) of the first frame decoded

    def __call__(self, item: WorkItem) -> dict:
        from ..features.survey import ROWS_NOT_ALIGNED

        index = item.options["frame"]
        t_load = time.perf_counter()
        left, right = self._views(index)
        load_seconds = time.perf_counter() - t_load
        if self.size is None:
            self.size = left.shape[:2]
        elif left.shape[:2] != self.size or right.shape[:2] != self.size:
            (h, w), (hr, wr) = left.shape[:2], right.shape[:2]
            raise DataError(f"{item.name}: views of {w}x{h} and {wr}x{hr}; the sequence's frames are "
                            f"{self.size[1]}x{self.size[0]}")
        fresh = self.matcher is None
        matcher = self._matcher()
        if fresh and index > 0:
            self._seed(matcher, index - 1)
        result = matcher.push(left, right)
        self.matched.append(index)
        if item.options["require_aligned"]:
            for warning in result.warnings:
                if warning.startswith(ROWS_NOT_ALIGNED):
                    raise DataError(f"{item.name}: {warning} (--require-aligned)")
        note = dict(result.notes.get("sequence", {}), frame=index)
        result = replace(result, notes={k: v for k, v in result.notes.items() if k != "sequence"})
        return write_match_outputs(item, result, load_seconds=load_seconds, notes=self._notes(item),
                                   extra={"sequence": note})

    def _matcher(self):
        if self.matcher is None:
            from ..sequence import SequenceMatcher
            from .match import _config, _load_mask

            opts = self.options
            shared = self.source.shared_inputs
            self.matcher = SequenceMatcher(ndisp=opts["ndisp"], min_disp=opts["min_disp"],
                                           config=_config(opts["config"]),
                                           left_valid=_load_mask(shared.get("left_valid")),
                                           right_valid=_load_mask(shared.get("right_valid")),
                                           confidence=self.confidence, keep_invalid=opts["keep_invalid"],
                                           temporal=opts["temporal"], disparity_right=self.right, warm_up=True)
        return self.matcher

    def _seed(self, matcher, index: int) -> None:
        """Seed ``matcher`` with frame ``index``'s outputs (``disp0.pfm``, and ``params.json``'s
        range and ``row_align`` note) when they are there and readable; else leave it afresh."""
        import json

        from ..io.pfm import read_pfm

        item = self.by_frame.get(index)
        if item is None or not all(Path(item.outputs[k]).is_file() for k in ("disparity", "params")):
            return
        try:
            params = json.loads(Path(item.outputs["params"]).read_text())
            min_disp, ndisp = int(params["min_disp"]), int(params["ndisp"])
            source = str(params.get("range", {}).get("source", "estimated"))
            row_align = (params.get("stage_notes") or {}).get("row_align")
            disparity = read_pfm(item.outputs["disparity"])
            left, right = self._views(index)
            matcher.seed(disparity, left, right, min_disp=min_disp, ndisp=ndisp, row_align=row_align,
                         range_source=source)
        except (OSError, ValueError, KeyError, TypeError, AttributeError, DataError):
            return  # outputs of no use to resume from: the matcher starts afresh at this frame
        self.seeded = index

    def _views(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``'s ``(left, right)`` views: RGB (or grey image files), decoded."""
        from ..io.images import read_image
        from ..io.video import FrameReader, split_stacked
        from ..runtime import side_by_side

        source = self.source
        if source.kind == "folder":
            pair = source.pairs[index]
            return side_by_side(lambda: read_image(pair.left), lambda: read_image(pair.right))
        readers = [self._readers.setdefault(path, FrameReader(path)) for path in source.videos]
        if source.kind == "videos":
            return side_by_side(lambda: readers[0].read(index), lambda: readers[1].read(index))
        return split_stacked(readers[0].read(index), source.kind, source.videos[0])

    def _notes(self, item: WorkItem) -> list[str | None]:
        notes: list[str | None] = [item.options.get("range_note")]
        if self.source.kind == "folder":
            from ..io.exif import orientation_note

            notes = [orientation_note(item.inputs["left"]), orientation_note(item.inputs["right"]), *notes]
        return notes

    def close(self) -> None:
        """Release the open videos."""
        for reader in self._readers.values():
            reader.close()
        self._readers.clear()

    def record(self) -> dict[str, Any]:
        """The run record's ``sequence`` entry: the source (kind, frame count, frame rate), the
        frames this run matched, and the frames whose survey was measured or refreshed."""
        surveyed: list[int] = []
        if self.matcher is not None:
            surveyed = [self.matched[k] for k in self.matcher.survey_frames if k < len(self.matched)]
        return {**self.source.as_record(), "temporal": self.options.get("temporal"), "matched": len(self.matched),
                "seeded_from": self.seeded, "survey_frames": surveyed, "survey_refreshes": surveyed[1:],
                "matcher": self.matcher.record() if self.matcher is not None else None}


def check_video_out(path: str | Path, items: list[WorkItem], *, overwrite: bool) -> None:
    """Refuse (before any work) a ``--video-out`` path of a kind that cannot be written, that is
    an input, or that exists (unless ``overwrite``)."""
    from ..io.video import WRITER_CODECS

    if Path(path).suffix.lower() not in WRITER_CODECS:
        raise ConfigError(f"--video-out {path}: write one of {', '.join(WRITER_CODECS)}")
    check_output_paths([*items, WorkItem("--video-out", {}, {"video": str(path)})])
    check_outputs_free([path], overwrite=overwrite, hint=RESUME_HINT)


def write_sequence_video(path: str | Path, items: list[WorkItem], *, fps: float | None,
                         viz_range: tuple[float, float] | None = None) -> dict[str, Any]:
    """Write the frames' disparity maps (``disp0.pfm`` of each item, in order) as one colour
    video at ``fps`` (:data:`DEFAULT_FPS` when None), coloured as ``--viz`` previews are, with
    ONE range for the whole sequence: ``viz_range``, else the items' ``vmin``/``vmax`` (calib.txt),
    else the 1st-99th percentiles of the first map, kept for every frame. A frame without a map
    (it failed) is black. Returns what was written: ``frames``, ``missing``, ``fps``, ``range``.
    """
    from ..io.pfm import read_pfm
    from ..io.video import open_writer
    from ..viz import disparity_preview, disparity_range

    maps = [item.outputs["disparity"] for item in items]
    present = [p for p in maps if Path(p).is_file()]
    if not present:
        raise DataError(f"--video-out {path}: no frame has a disparity map to show")
    first = read_pfm(present[0])
    lo, hi = viz_range if viz_range is not None else (items[0].options.get("vmin"), items[0].options.get("vmax"))
    if lo is None or hi is None:
        lo, hi = disparity_range(first)
    lo, hi = float(lo), float(hi)
    shape = disparity_preview(first, lo, hi).shape
    size = (shape[1] + shape[1] % 2, shape[0] + shape[0] % 2)  # codecs want even sides
    fps = fps or DEFAULT_FPS
    missing = 0
    with open_writer(path, fps, size) as writer:
        for disparity_path in maps:
            canvas = np.zeros((size[1], size[0], 3), np.uint8)
            disparity = read_pfm(disparity_path) if Path(disparity_path).is_file() else None
            if disparity is not None and disparity.shape == first.shape:
                preview = disparity_preview(disparity, lo, hi)
                canvas[: preview.shape[0], : preview.shape[1]] = preview
            else:
                missing += 1
            writer.write(canvas)
    return {"path": str(path), "frames": len(maps), "missing": missing, "fps": fps, "range": [lo, hi]}
