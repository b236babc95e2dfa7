"""Stereo sequences: one rig, many frames (``stereocli match --sequence`` and video input).

:class:`SequenceMatcher` matches the frames of one sequence in order and carries what the rig
and the scene keep from frame to frame: the survey (row alignment and disparity range) is made
once and refreshed when its evidence drifts, and where the scene holds still the previous
frames' disparities stand between whole-frame refreshes and are averaged with them
(``temporal="on"``; ``"off"`` gives frame-by-frame results).

Every frame's :class:`~stereocli.api.MatchResult` has ``notes["sequence"]``: the frame index,
whether the survey was ``measured``, ``reused`` or ``refreshed`` for it, and what the temporal
reuse did (e.g. the share of pixels matched again).

The reuse rule (``temporal="on"``; ``docs/design.md`` states it for users):

* **Survey.** The first frame is matched as :func:`stereocli.match` matches a pair: the range is
  estimated (unless given) and the rows measured. Later frames reuse both: the range as it is,
  the rows through the preprocess stages' ``repeated_params`` (``row_align`` applies the first
  frame's plane without tracking). The survey is refreshed (range estimated and rows measured
  again, the frame matched again with them) when more than :data:`RANGE_END_SHARE` of a frame's
  pixels lie at the ends of an estimated range: something came nearer or went farther than the
  range holds. A range given by the caller is never refreshed.
* **Change.** Each view is compared, 3 x 3 box-blurred, with the view the pixel's value was last
  measured on; a pixel has changed where the difference exceeds :data:`GATE_SIGMAS` standard
  deviations of the blurred noise. The noise level is estimated from the frame differences
  (median absolute difference, and the median of their Laplacian-like response, whichever is
  smaller, the smallest over the sequence), so the gate needs no setting. Specks below 3 x 3 px
  are dropped (noise), right-view changes are carried to the left pixels that match there, and
  the mask grows by :data:`RESET_RADIUS` px (the census window and the edge's blur), so the
  place an object left and the place it reached both count as changed: edges do not trail.
* **Where the image changed** the pixels are matched again over the full range: each run of
  changed rows is cut out with :data:`CONTEXT` px of context (and the range's width to the left,
  so every match stays inside the cut) and matched with the sequence's config. A crop searches
  as the whole frame does (:func:`~stereocli.matching.config.small_twin`): its smaller cost
  volume would otherwise turn the coarse-to-fine search off, and the full-range search alone
  gives worse values on real scenes (5 to 9 points of bad 1 on a band of Adirondack's rows).
  The pixels whose left view changed take the new values as they are (the filter restarts
  there); those whose match in the right view changed go through the filter.
* **Where the scene holds still** the previous value stands, and every ``refresh_every``-th frame
  (:data:`REFRESH_EVERY`) is matched whole; its still pixels' values go through the filter, so
  they average the whole-frame measurements. A whole-frame refresh searches each pixel around
  the previous map (``narrow``, as tSGM narrows its per-pixel ranges: the map at half resolution
  is the coarse level of the coarse-to-fine search), except within :data:`PRIOR_MARGIN` px of a
  change or where the map is invalid, which search the full range; every
  :data:`WIDE_REFRESH_EVERY`-th refresh searches as a frame on its own, so no value stays only
  because the narrowed searches kept it.
* **Temporal filter.** A still pixel's value is the running mean of its measurements that agree
  with it within :data:`AGREE_PX` (at most :data:`MAX_WEIGHT` frames' worth, so a slow drift
  still comes through); a measurement that disagrees lowers the pixel's weight, and at weight 0
  the new value replaces it (a value that was wrong, or a change too faint for the gate).
* When the changed regions cover more than :data:`WHOLE_FRAME_SHARE` of the frame, the whole
  frame is matched again (still pixels still go through the filter).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Iterable, Iterator

import numpy as np

from .errors import ConfigError, DataError, named

if TYPE_CHECKING:
    from .api import Assignments, ConfigLike, MatchResult, PathLike
    from .io.middlebury import MiddleburyCalib
    from .matching.config import PipelineConfig

__all__ = ["TEMPORAL_MODES", "SequenceMatcher", "match_sequence"]

#: Values of ``temporal=``.
TEMPORAL_MODES = ("on", "off")

#: Every this-many-th frame is matched whole (``refresh_every=``): the still pixels' new evidence.
REFRESH_EVERY = 5
#: A pixel has changed where its blurred difference exceeds this many standard deviations of the
#: blurred noise (one false alarm in about 10^5 pixels, before the speck filter drops them).
GATE_SIGMAS = 4.5
#: px the change mask grows by: the census window's half (2) and an edge's blur.
RESET_RADIUS = 4
#: px around a changed pixel that search the full range on a whole-frame refresh (the previous
#: map narrows the others): the SGM windows' coarse neighbourhood (2 coarse px) and one more.
PRIOR_MARGIN = 6
#: Every this-many-th whole-frame refresh searches as a frame on its own (the full range, coarse
#: to fine) instead of around the previous map, so a value the narrowed searches keep is put to
#: the whole range again.
WIDE_REFRESH_EVERY = 3
#: px of context around a region matched again (SGM paths, the aggregation windows).
CONTEXT = 16
#: px around the changed pixels whose new values go through the filter.
PASTE_MARGIN = 6
#: A measurement within this many px of the filtered value agrees with it.
AGREE_PX = 1.0
#: A changed pixel's new value within this many px of the old one is averaged with it.
RESTART_PX = 0.5
#: Most frames of evidence a still pixel's running mean holds.
MAX_WEIGHT = 8
#: Share of a frame's pixels at an end of an estimated range that refreshes the survey.
RANGE_END_SHARE = 0.02
#: Frames after a survey before the range's evidence may refresh it again.
REFRESH_COOLDOWN = 10
#: Changed regions covering more than this share of the frame: the whole frame is matched again.
WHOLE_FRAME_SHARE = 0.7
#: The noise is estimated on this many frames, then on every this-many-th.
NOISE_FRAMES = 8
#: Smallest noise level the gate assumes, grey levels (8-bit rounding alone gives 0.3).
MIN_SIGMA = 0.5


class SequenceMatcher:
    """Match the frames of one stereo sequence in order (see the module docstring).

    Parameters
    ----------
    ndisp, min_disp, preset, config, set, threads, calib, left_valid, right_valid, confidence, keep_invalid :
        As for :func:`stereocli.match`; they hold for every frame.
    warm_up : bool, default False
        As for :func:`stereocli.match`, on the first frame: its ``seconds`` exclude loading or
        compiling the kernels.
    disparity_right : bool, default False
        Also return each frame's right-view disparity (``temporal="off"`` only: the temporal
        filter steadies the left view's map).
    temporal : {"on", "off"}, default "on"
        ``"on"`` reuses the previous frames (still pixels kept, temporal filter); ``"off"``
        matches each frame on its own (the survey is still reused): each frame's map is
        :func:`stereocli.match`'s with the sequence's range.
    name : str, optional
        The sequence's name, put before error messages and warnings.
    refresh_every : int, default 5
        ``temporal="on"``: every ``refresh_every``-th frame is matched whole (1: every frame);
        the frames between match only the regions that changed.
    narrow : bool, default True
        ``temporal="on"``: a whole-frame refresh searches each still pixel around the previous
        map (the full range near a change, where the map is invalid, and on every
        :data:`WIDE_REFRESH_EVERY`-th refresh); False: every refresh searches as a frame on its own.

    Examples
    --------
    >>> import numpy as np
    >>> from stereocli.sequence import SequenceMatcher
    >>> rng = np.random.default_rng(0)
    >>> left = rng.integers(0, 256, (48, 96), dtype=np.uint8)
    >>> matcher = SequenceMatcher(ndisp=16)
    >>> results = [matcher.push(left, np.roll(left, -5, axis=1)) for _ in range(3)]
    >>> [r.notes["sequence"]["frame"] for r in results]
    [0, 1, 2]
    >>> float(np.median(results[-1].disparity[:, 16:]))
    5.0
    """

    def __init__(self, *, ndisp: int | str | None = None, min_disp: int | None = None, preset: str = "default",
                 config: ConfigLike = None, set: Assignments = None, threads: int | None = None,
                 calib: PathLike | MiddleburyCalib | None = None, left_valid: np.ndarray | None = None,
                 right_valid: np.ndarray | None = None, confidence: bool = False, keep_invalid: bool = False,
                 temporal: str = "on", name: str = "", refresh_every: int = REFRESH_EVERY, warm_up: bool = False,
                 disparity_right: bool = False, narrow: bool = True) -> None:
        from .api import match_config

        if temporal not in TEMPORAL_MODES:
            raise ConfigError(f"temporal must be one of {', '.join(TEMPORAL_MODES)}, got {temporal!r}")
        if isinstance(refresh_every, bool) or not isinstance(refresh_every, (int, np.integer)) or refresh_every < 1:
            raise ConfigError(f"refresh_every must be a whole number >= 1, got {refresh_every!r}")
        if disparity_right and temporal == "on":
            raise ConfigError(named(name, "disparity_right needs temporal='off': the temporal filter steadies the "
                                          "left view's map only"))
        self.config = match_config(preset, config, set, threads)
        self.temporal = temporal
        self.name = name
        self.refresh_every = int(refresh_every)
        self.narrow = bool(narrow)
        self._refreshes = 0  # whole frames matched since the first
        self._since_whole = 0  # frames matched since the last whole-frame match
        self._notes: dict = {}  # the pipeline's notes on the last frame whose views were prepared
        self._range: tuple[int | None, int | str | None] = (min_disp, ndisp)
        self._source: str | None = None  # the range's source once known
        self._calib = calib
        self._masks = (left_valid, right_valid)
        self._flags = {"confidence": confidence, "keep_invalid": keep_invalid}
        self._right = bool(disparity_right)
        self._warm_up = bool(warm_up)  # until the first frame is matched
        self.frame = 0
        #: Frame indices whose survey was measured (the first) or refreshed.
        self.survey_frames: list[int] = []
        self.previous: MatchResult | None = None
        self._state: _TemporalState | None = None
        self._repeat: PipelineConfig | None = None  # the config that repeats the survey's rows
        self._alignment: dict | None = None
        self._shape: tuple[int, int] | None = None
        self._surveyed = False
        self._reads_colour = _reads_colour(self.config)
        self._ends_at_survey = 0.0  # share of pixels at the range's ends on the surveyed frame

    # ------------------------------------------------------------------ public

    def push(self, left: np.ndarray, right: np.ndarray) -> MatchResult:
        """Match the next frame, ``left``/``right`` as :func:`stereocli.match` takes them."""
        from .api import _as_image

        left, right = _as_image(left, "left", self.name), _as_image(right, "right", self.name)
        if self._shape is not None and left.shape[:2] != self._shape:
            h, w = self._shape
            raise DataError(named(self.name, f"frame {self.frame} is {left.shape[1]}x{left.shape[0]}; the "
                                             f"sequence's frames are {w}x{h}"))
        if not self._surveyed:
            survey = "measured"
            result = self._match_whole(left, right, survey=True)
        elif self.temporal == "off" or self._state is None:
            survey = "reused"
            result = self._match_whole(left, right, survey=False)
        else:
            survey = "reused"
            result = self._match_reusing(left, right)
        if survey == "reused" and self._range_drifted(result.disparity):
            survey = "refreshed"
            result = self._match_whole(left, right, survey=True)
        self._shape = left.shape[:2]
        if self.temporal == "on" and (survey != "reused" or self._state is None):
            self._restart(left, right, result)
        sequence = {"frame": self.frame, "survey": survey, "temporal": self.temporal}
        if self.temporal == "on":
            sequence.update(self._state.last if self._state is not None and survey == "reused" else
                            {"rematched": 1.0, "changed": 1.0})
            if self._state is not None and self._state.gate.sigma is not None:
                sequence["noise_sigma"] = round(float(self._state.gate.sigma), 3)
        result.notes["sequence"] = sequence
        self.previous = result
        self.frame += 1
        return result

    def record(self) -> dict[str, Any]:
        """What the sequence did so far, for the run record (frames, survey refreshes)."""
        out: dict[str, Any] = {"frames": self.frame, "survey_frames": list(self.survey_frames),
                               "temporal": self.temporal}
        if self.previous is not None:
            out["range"] = {"min_disp": self.previous.range.min_disp, "ndisp": self.previous.range.ndisp,
                            "source": self.previous.range.source}
        if self._state is not None and self._state.gate.sigma is not None:
            out["noise_sigma"] = round(float(self._state.gate.sigma), 3)
        return out

    def seed(self, disparity: np.ndarray, left: np.ndarray, right: np.ndarray, *, min_disp: int, ndisp: int,
             frame: int | None = None, row_align: dict | None = None, range_source: str = "estimated") -> None:
        """Resume after a frame matched earlier (e.g. ``--skip-existing``): its map ``disparity``
        ((H, W) float32, +inf invalid), its views and its range ``[min_disp, min_disp + ndisp)``
        become the previous frame's. ``frame``: that frame's index (the next push is
        ``frame + 1``); ``row_align``: its ``row_align`` note, so later frames repeat its rows
        (without it the next frame measures them again); ``range_source``: where the range came
        from (``"estimated"``: a drift refreshes it; else it is kept).

        The range counts as reused: the survey is not measured again for the next frame.
        """
        from .api import _as_image

        left, right = _as_image(left, "left", self.name), _as_image(right, "right", self.name)
        disparity = np.asarray(disparity, np.float32)
        if disparity.shape != left.shape[:2] or left.shape[:2] != right.shape[:2]:
            raise DataError(named(self.name, f"seed: disparity {disparity.shape} and views {left.shape[:2]}, "
                                             f"{right.shape[:2]} differ in size"))
        self._range = (int(min_disp), int(ndisp))
        self._source = range_source
        self._surveyed = True
        self._calib = None
        self._shape = left.shape[:2]
        if frame is not None:
            self.frame = int(frame) + 1
        self._repeat = self._repeating_config({"row_align": row_align} if row_align is not None else None)
        if self.temporal == "on":
            self._state = _TemporalState(_grey(left), _grey(right), disparity.copy())
            self._since_whole = 0

    # ------------------------------------------------------------------ whole frames

    def _match_whole(self, left: np.ndarray, right: np.ndarray, *, survey: bool) -> MatchResult:
        """The frame matched as :func:`stereocli.match` matches it: with the sequence's range, or
        with ``survey`` the range estimated (unless given) and the rows measured anew."""
        from .api import match

        min_disp, ndisp = self._range
        if survey and self._source == "estimated":
            min_disp, ndisp = None, "auto"
        calib = self._calib if survey else None
        result = match(left, right, ndisp=ndisp, min_disp=min_disp, config=self.config, calib=calib,
                       left_valid=self._masks[0], right_valid=self._masks[1], name=self.name,
                       disparity_right=self._right, warm_up=self._warm_up, confidence=self._flags["confidence"],
                       keep_invalid=self._flags["keep_invalid"])
        self._warm_up = False
        if survey:
            self.survey_frames.append(self.frame)
            self._range = (result.range.min_disp, result.range.ndisp)
            self._source = result.range.source
            self._calib = None
            self._alignment = result.alignment
            self._surveyed = True
            self._ends_at_survey = self._share_at_ends(result.disparity)
            if self.temporal == "on":
                self._repeat = self._repeating_config(result.notes)
        return result

    def _repeating_config(self, notes: dict | None) -> PipelineConfig | None:
        """The config whose preprocess stages repeat what they did on the surveyed frame
        (``repeated_params``), or None when ``notes`` are unknown (the rows are measured)."""
        from .matching.pipeline import preprocess_given

        if notes is None:
            return None
        return replace(self.config, preprocess=preprocess_given(self.config, notes, "repeated_params"))

    def _share_at_ends(self, disparity: np.ndarray) -> float:
        """Share of the pixels (every other row and column) within half a pixel of an end of the range."""
        min_disp, ndisp = self._range
        assert isinstance(min_disp, int) and isinstance(ndisp, int)
        sample = disparity[::2, ::2]
        ends = (sample <= min_disp + 0.5) | ((sample >= min_disp + ndisp - 1.5) & np.isfinite(sample))
        return float(np.count_nonzero(ends)) / max(sample.size, 1)

    def _range_drifted(self, disparity: np.ndarray) -> bool:
        """Whether the survey's evidence drifted: an estimated range with more than
        :data:`RANGE_END_SHARE` of the pixels at its ends, and more than twice as many as on the
        surveyed frame (a range the estimate cannot do better with is not refreshed again and again)."""
        if self._source != "estimated":
            return False
        share = self._share_at_ends(disparity)
        return share > max(RANGE_END_SHARE, 2.0 * self._ends_at_survey)

    def _restart(self, left: np.ndarray, right: np.ndarray, result: MatchResult) -> None:
        """Start the temporal state over from a whole frame's ``result``."""
        self._since_whole = 0
        self._notes = dict(result.notes)
        self._state = _TemporalState(_grey(left), _grey(right), result.disparity.copy(),
                                     None if result.confidence is None else result.confidence.copy())

    # ------------------------------------------------------------------ reuse

    def _match_reusing(self, left: np.ndarray, right: np.ndarray) -> MatchResult:
        """A later frame with ``temporal="on"``: the changed regions (or, every ``refresh_every``-th
        frame, the whole frame) over the full range, the temporal filter over what was matched."""
        from .api import MatchRange, MatchResult
        from .matching.config import small_twin
        from .matching.pipeline import match_pair, prepare, release_config
        from .matching.warmup import with_coarse_level

        state = self._state
        assert state is not None
        min_disp, ndisp = self._range
        assert isinstance(min_disp, int) and isinstance(ndisp, int)
        t0 = time.perf_counter()
        grey_l, grey_r = _grey(left), _grey(right)
        moved, changed = state.gate.changed(grey_l, grey_r, state.disparity)
        h, w = changed.shape
        whole = self._since_whole + 1 >= self.refresh_every
        regions = [] if whole else _changed_regions(changed, min_disp, ndisp)
        if whole or sum(r.area for r in regions) > WHOLE_FRAME_SHARE * h * w:
            regions = [_Region(slice(0, h), slice(0, w), slice(0, h), slice(0, w))]
            self._since_whole = 0
        else:
            self._since_whole += 1
        config = self._repeat or self.config
        # A crop searches as the whole frame does (see the module docstring).
        crop_config = small_twin(replace(config, preprocess=[]), h, w, ndisp)
        timings: dict[str, float] = {}
        memory = 0.0
        warnings: list[str] = []
        if not self._reads_colour:  # the pipeline would take the same luma of each view again
            left, right = grey_l, grey_r
        notes = self._notes
        if regions or self._repeat is None:  # else nothing changed: no view is needed
            try:
                prepared = prepare(left, right, config, min_disp=min_disp, ndisp=ndisp, left_valid=self._masks[0],
                                   right_valid=self._masks[1], keep_invalid=self._flags["keep_invalid"],
                                   want_confidence=self._flags["confidence"])
            finally:
                release_config()
            timings.update(prepared.timings)
            views = prepared.state
            notes = self._notes = dict(views.notes)
            if self._repeat is None:  # the rows were measured on this frame: repeat them from now on
                self._repeat = self._repeating_config(views.notes)
        rematched = np.zeros(changed.shape, bool)
        whole_frame = len(regions) == 1 and regions[0].area == h * w
        if whole_frame:
            self._refreshes += 1
        if whole_frame and self.narrow and self._refreshes % WIDE_REFRESH_EVERY:
            # The previous frame narrows each still pixel's search (its coarse level); a changed
            # or invalid pixel, and every WIDE_REFRESH_EVERY-th refresh, search the full range.
            crop_config = with_coarse_level(crop_config, _prior_coarse_level(state.disparity, changed))
        for region in regions:
            rows, cols = region.rows, region.cols
            part = match_pair(region.crop(views.left), region.crop(views.right), crop_config, min_disp=min_disp,
                              ndisp=ndisp, left_valid=region.crop_mask(views.left_valid),
                              right_valid=region.crop_mask(views.right_valid), keep_invalid=self._flags["keep_invalid"],
                              want_confidence=self._flags["confidence"])
            for key, seconds in part.timings.items():
                timings[key] = timings.get(key, 0.0) + seconds
            memory = max(memory, part.memory_estimate_gb)
            inner = (slice(region.paste_rows.start - rows.start, region.paste_rows.stop - rows.start),
                     slice(region.paste_cols.start - cols.start, region.paste_cols.stop - cols.start))
            measured = part.disparity[inner]
            target = (region.paste_rows, region.paste_cols)
            # Pixels whose match in the right view changed (not their view) go through the filter:
            # keeping their old value wherever that match is now hidden made real scenes worse.
            state.update(target, measured, moved[target], None if part.confidence is None else part.confidence[inner])
            rematched[target] = True
        state.gate.accept(moved)
        state.last = {"rematched": round(float(rematched.mean()), 4), "changed": round(float(moved.mean()), 4),
                      "regions": len(regions), "whole": self._since_whole == 0}
        seconds = time.perf_counter() - t0
        return MatchResult(disparity=state.disparity.copy(),
                           range=MatchRange(min_disp, ndisp, self._source or "given"),
                           confidence=None if state.confidence is None else state.confidence.copy(),
                           timings=timings, notes=dict(notes), alignment=self._alignment, warnings=warnings,
                           seconds=seconds, memory_estimate_gb=memory, config=self.config)


def match_sequence(frames: Iterable[tuple[np.ndarray, np.ndarray]], **options: Any) -> Iterator[MatchResult]:
    """Match ``(left, right)`` frames in order; yields one :class:`~stereocli.api.MatchResult` per frame.

    ``options`` are :class:`SequenceMatcher`'s.

    Examples
    --------
    >>> import numpy as np
    >>> import stereocli
    >>> rng = np.random.default_rng(1)
    >>> left = rng.integers(0, 256, (48, 96), dtype=np.uint8)
    >>> frames = [(left, np.roll(left, -4, axis=1))] * 2
    >>> [float(np.median(r.disparity[:, 16:])) for r in stereocli.match_sequence(frames, ndisp=16)]
    [4.0, 4.0]
    """
    matcher = SequenceMatcher(**options)
    for left, right in frames:
        yield matcher.push(left, right)


# --------------------------------------------------------------------------- helpers


def _prior_coarse_level(disparity: np.ndarray, changed: np.ndarray):
    """A coarse level (``coarse_level=`` of the SGM stage) from the previous frame's map: its
    disparities at half resolution in coarse px, ``+inf`` where the image changed or the map is
    invalid (those pixels search the full range)."""
    import cv2

    # Grown by the coarse neighbourhood a window spans (PRIOR_MARGIN px), so no pixel near a
    # change takes its window from the still pixels around it alone.
    size = 2 * PRIOR_MARGIN + 1
    near_change = cv2.dilate(changed.view(np.uint8), np.ones((size, size), np.uint8)).view(bool)
    prior = np.where(near_change, np.float32(np.inf), disparity)[::2, ::2] / np.float32(2)

    def coarse_level(state, params, cost) -> np.ndarray:
        h, w = -(-state.shape[0] // 2), -(-state.shape[1] // 2)
        y0 = state.row_offset // 2
        return np.ascontiguousarray(prior[y0:y0 + h, :w], dtype=np.float32)

    return coarse_level


def _grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey of a view (uint8, uint16 or float; RGB or grey), 0..255: the luma the
    pipeline matches when no stage reads colour."""
    from .matching.pipeline import working_image

    return working_image(image, grey=True)


def _reads_colour(config: PipelineConfig) -> bool:
    """Whether a stage of ``config`` reads a view's colour (else the pipeline matches the views' luma)."""
    from .matching.pipeline import _reads_colour as reads_colour

    calls = [*config.preprocess, config.cost, *config.aggregation, config.optimizer, *config.refinement]
    return reads_colour(calls, "left") or reads_colour(calls, "right")


def _blur(grey: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.blur(grey, (3, 3), borderType=cv2.BORDER_REFLECT)


@dataclass
class _Region:
    """A region matched again: the crop (``rows``, ``cols``) and the pixels whose new values count
    (``paste_rows``, ``paste_cols``, inside the crop)."""

    rows: slice
    cols: slice
    paste_rows: slice
    paste_cols: slice

    def crop(self, image: np.ndarray) -> np.ndarray:
        """``image``'s crop (contiguous)."""
        return np.ascontiguousarray(image[self.rows, self.cols])

    def crop_mask(self, mask: np.ndarray | None) -> np.ndarray | None:
        """``mask``'s crop, or None for None."""
        return None if mask is None else self.crop(mask)

    @property
    def area(self) -> int:
        return (self.rows.stop - self.rows.start) * (self.cols.stop - self.cols.start)


def _changed_regions(changed: np.ndarray, min_disp: int, ndisp: int) -> list[_Region]:
    """One region per run of rows with changed pixels (runs closer than twice the context
    merged): the changed columns, with :data:`CONTEXT` px around and the range's width on the
    side the matches lie (so every changed pixel's match stays inside the crop)."""
    h, w = changed.shape
    rows = np.flatnonzero(changed.any(axis=1))
    if rows.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(rows) > 2 * CONTEXT)
    starts = np.concatenate([[rows[0]], rows[breaks + 1]])
    stops = np.concatenate([rows[breaks], [rows[-1]]]) + 1
    regions = []
    max_disp = min_disp + ndisp - 1
    for y0, y1 in zip(starts.tolist(), stops.tolist()):
        cols = np.flatnonzero(changed[y0:y1].any(axis=0))
        x0, x1 = int(cols[0]), int(cols[-1]) + 1
        c0 = max(0, x0 - max(max_disp, 0) - CONTEXT)
        c1 = min(w, x1 + max(-min_disp, 0) + CONTEXT)
        if c1 - c0 > 0.75 * w:  # little to save: the whole rows, without a cut near the pixels
            c0, c1 = 0, w
        regions.append(_Region(slice(max(0, y0 - CONTEXT), min(h, y1 + CONTEXT)), slice(c0, c1),
                               slice(max(0, y0 - PASTE_MARGIN), min(h, y1 + PASTE_MARGIN)),
                               slice(max(c0, x0 - PASTE_MARGIN), min(c1, x1 + PASTE_MARGIN))))
    return regions


class _ChangeGate:
    """Which pixels changed since their value was last measured (the module docstring's rule)."""

    #: A Laplacian-like kernel whose response to white noise of std s has std 6 s (Immerkær 1996)
    #: and to smooth image content little.
    _NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)

    def __init__(self, grey_l: np.ndarray, grey_r: np.ndarray) -> None:
        self.reference = [_blur(grey_l), _blur(grey_r)]  # the views each pixel's value was measured on
        self.latest = grey_l  # the left view of the frame before, for the noise estimate
        self.estimates = 0
        self.blurred: list[np.ndarray] = []
        self.changed_right: np.ndarray | None = None
        self.sigma: float | None = None

    def _noise(self, grey: np.ndarray, before: np.ndarray) -> float:
        """Noise standard deviation of one view (grey levels) from its difference with the frame before."""
        import cv2

        diff = grey[::2, ::2] - before[::2, ::2]
        by_median = float(np.median(np.abs(diff))) / (0.6745 * np.sqrt(2.0))
        response = cv2.filter2D(np.ascontiguousarray(diff), -1, self._NOISE_KERNEL)
        # The subsampled difference is white noise too; the kernel's response to it has std 6 s√2.
        by_kernel = float(np.median(np.abs(response[1:-1, 1:-1]))) / (0.6745 * 6.0 * np.sqrt(2.0))
        return max(min(by_median, by_kernel), MIN_SIGMA)

    def changed(self, grey_l: np.ndarray, grey_r: np.ndarray,
                disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(moved, changed)``, (H, W) bool in left coordinates, grown by :data:`RESET_RADIUS` px:
        the pixels whose left view changed (something else is there now), and those or the
        pixels whose match in the right view (at ``x - disparity``) changed (the same surface,
        matched again: it may be hidden in the right view now, or seen again)."""
        import cv2

        if self.estimates < NOISE_FRAMES or self.estimates % NOISE_FRAMES == 0:
            estimate = self._noise(grey_l, self.latest)
            self.sigma = estimate if self.sigma is None else min(self.sigma, estimate)
        self.estimates += 1
        self.latest = grey_l
        assert self.sigma is not None
        # Two blurred noisy views differ with std s·√2/3 (3 x 3 box); one grey level more for rounding.
        threshold = GATE_SIGMAS * self.sigma * np.sqrt(2.0) / 3.0 + 1.0
        self.blurred = [_blur(grey_l), _blur(grey_r)]
        speck = np.ones((3, 3), np.uint8)
        masks = []
        for now, before in zip(self.blurred, self.reference):
            moved = (cv2.absdiff(now, before) > threshold).astype(np.uint8)
            masks.append(cv2.morphologyEx(moved, cv2.MORPH_OPEN, speck))
        left, right = masks
        grow = np.ones((2 * RESET_RADIUS + 1, 2 * RESET_RADIUS + 1), np.uint8)
        self.changed_right = cv2.dilate(right, grow).view(bool)
        moved = cv2.dilate(left, grow).view(bool)
        rows = np.flatnonzero(right.any(axis=1))
        if rows.size == 0:
            return moved, moved
        # The right mask read at each left pixel's match (x - d; the pixel itself where d is
        # unknown), on the rows with right-view changes only.
        band = slice(int(rows[0]), int(rows[-1]) + 1)
        values = disparity[band]
        columns = np.arange(values.shape[1], dtype=np.float32)[None, :] - np.where(np.isfinite(values), values, 0)
        rows_map = np.broadcast_to(np.arange(values.shape[0], dtype=np.float32)[:, None], values.shape)
        matched = left.copy()
        matched[band] |= cv2.remap(right[band], columns, np.ascontiguousarray(rows_map), cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_REPLICATE)
        return moved, cv2.dilate(matched, grow).view(bool)

    def accept(self, changed: np.ndarray) -> None:
        """The changed pixels' values were measured on this frame's views: they are the new reference."""
        np.copyto(self.reference[0], self.blurred[0], where=changed)
        if self.changed_right is not None:
            np.copyto(self.reference[1], self.blurred[1], where=self.changed_right)


class _TemporalState:
    """The filtered map and each pixel's weight (frames of agreeing evidence), with the change gate."""

    def __init__(self, grey_l: np.ndarray, grey_r: np.ndarray, disparity: np.ndarray,
                 confidence: np.ndarray | None = None) -> None:
        self.gate = _ChangeGate(grey_l, grey_r)
        self.disparity = disparity  # (H, W) float32, +inf invalid
        self.weight = np.where(np.isfinite(disparity), np.float32(1), np.float32(0)).astype(np.float32)
        self.confidence = confidence
        self.last: dict[str, Any] = {}

    def update(self, target: tuple[slice, slice], measured: np.ndarray, reset: np.ndarray,
               confidence: np.ndarray | None) -> None:
        """Take the new measurements ``measured`` ((h, w) float32 px) of the pixels ``target``:
        ``reset`` ones ((h, w) bool) as they are, the others through the running mean (the
        module docstring's rule)."""
        # In place on views of the state (float32 throughout: this runs on whole frames).
        old = self.disparity[target]
        weight = self.weight[target]
        finite = np.isfinite(measured)
        known = np.isfinite(old)
        with np.errstate(invalid="ignore"):
            diff = measured - old  # NaN or inf where either is invalid: never close
            distance = np.abs(diff)
        still = finite & known & ~reset
        agree = still & (distance <= AGREE_PX)
        disagree = still & ~agree
        np.add(weight, 1, out=weight, where=agree)
        np.minimum(weight, MAX_WEIGHT, out=weight, where=agree)
        np.subtract(weight, 1, out=weight, where=disagree)
        with np.errstate(invalid="ignore"):
            np.add(old, diff / np.maximum(weight, 1), out=old, where=agree)
            # A changed pixel whose new value stays within half a pixel of the old one (the same
            # surface, or one moving less than that in depth) starts over from the mean of both.
            again = reset & (distance <= RESTART_PX)
            np.add(old, 0.5 * diff, out=old, where=again)
        np.copyto(weight, 2, where=again)
        take = (reset & ~again) | (finite & ~known) | (disagree & (weight <= 0))
        np.copyto(old, measured, where=take)
        np.copyto(weight, finite.astype(np.float32), where=take)
        if self.confidence is not None and confidence is not None:
            np.copyto(self.confidence[target], confidence, where=take | agree)
