"""Stereo sequences: one rig, many frames (``stereocli match --sequence`` and video input).

:class:`SequenceMatcher` matches the frames of one sequence in order and carries what the rig
and the scene keep from frame to frame: the survey (row alignment and disparity range) is made
once and refreshed when its evidence drifts, and the previous frame's disparity narrows the
search and steadies the map where the scene holds still (``temporal="on"``; ``"off"`` gives
frame-by-frame results).

Every frame's :class:`~stereocli.api.MatchResult` has ``notes["sequence"]``: the frame index,
whether the survey was ``measured``, ``reused`` or ``refreshed`` for it, and what the temporal
reuse did (e.g. the share of pixels matched over the full range).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Iterable, Iterator

import numpy as np

from .errors import ConfigError

if TYPE_CHECKING:
    from .api import Assignments, ConfigLike, MatchResult, PathLike
    from .io.middlebury import MiddleburyCalib

__all__ = ["TEMPORAL_MODES", "SequenceMatcher", "match_sequence"]

#: Values of ``temporal=``.
TEMPORAL_MODES = ("on", "off")


class SequenceMatcher:
    """Match the frames of one stereo sequence in order (see the module docstring).

    Parameters
    ----------
    ndisp, min_disp, preset, config, set, threads, calib, left_valid, right_valid, confidence, keep_invalid :
        As for :func:`stereocli.match`; they hold for every frame.
    temporal : {"on", "off"}, default "on"
        ``"on"`` reuses the previous frames (narrowed search, temporal filter); ``"off"``
        matches each frame on its own (the survey is still reused).
    name : str, optional
        The sequence's name, put before error messages and warnings.

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
                 temporal: str = "on", name: str = "") -> None:
        from .api import match_config

        if temporal not in TEMPORAL_MODES:
            raise ConfigError(f"temporal must be one of {', '.join(TEMPORAL_MODES)}, got {temporal!r}")
        self.config = match_config(preset, config, set, threads)
        self.temporal = temporal
        self.name = name
        self._range: tuple[int | None, int | str | None] = (min_disp, ndisp)
        self._calib = calib
        self._masks = (left_valid, right_valid)
        self._flags = {"confidence": confidence, "keep_invalid": keep_invalid}
        self.frame = 0
        #: Frame indices whose survey was measured (the first) or refreshed.
        self.survey_frames: list[int] = []
        self.previous: MatchResult | None = None

    def push(self, left: np.ndarray, right: np.ndarray) -> MatchResult:
        """Match the next frame, ``left``/``right`` as :func:`stereocli.match` takes them."""
        from .api import match

        min_disp, ndisp = self._range
        survey = "reused"
        if self.previous is None:
            survey = "measured"
            self.survey_frames.append(self.frame)
        result = match(left, right, ndisp=ndisp, min_disp=min_disp, config=self.config, calib=self._calib,
                       left_valid=self._masks[0], right_valid=self._masks[1], name=self.name, **self._flags)
        if self.previous is None:  # the first frame's survey holds for the rest of the sequence
            self._range = (result.range.min_disp, result.range.ndisp)
            self._calib = None
        result.notes["sequence"] = {"frame": self.frame, "survey": survey, "temporal": self.temporal}
        self.previous = result
        self.frame += 1
        return result

    def record(self) -> dict[str, Any]:
        """What the sequence did so far, for the run record (frames, survey refreshes)."""
        return {"frames": self.frame, "survey_frames": list(self.survey_frames), "temporal": self.temporal}


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
