"""One pair's row strips spread over Dask workers (``stereocli match --split-strips``).

The item task runs :func:`~stereocli.match.pipeline.prepare` and
:func:`~stereocli.match.pipeline.finish` itself and sends each strip's volume stages
(:func:`~stereocli.match.pipeline.run_strip`, a pure function of the cropped strip state and
the config) to the cluster as a sub-task. Strips are stitched in plan order, so the result is
bit-identical to :func:`~stereocli.match.pipeline.match_pair` in one process with the same
config, whichever workers ran the strips.
"""

from __future__ import annotations

from .pipeline import PreparedPair, StripMap, StripResult, run_strip, run_strips, strip_input
from .state import MatchState


def cluster_strip_map(config_dict: dict) -> StripMap:
    """A ``strip_map`` for :func:`~stereocli.match.pipeline.match_pair` that spreads strips over
    the cluster the calling task runs on (in-process when there is one strip or no cluster).

    ``config_dict`` is the effective config as a plain dict: workers validate it once per process.
    """

    def strip_map(prepared: PreparedPair, config) -> list[StripResult]:
        from ..distributed import in_worker, worker_map

        if len(prepared.strips) < 2 or not in_worker():
            return run_strips(prepared, config)
        # Cropped strip states (image rows only, no volumes) are scattered to the cluster.
        args = [(strip_input(prepared, y0, y1), config_dict, y0, y1, prepared.keep_invalid)
                for y0, y1 in prepared.strips]
        return worker_map(strip_task, args)

    return strip_map


def strip_task(sub: MatchState, config_dict: dict, y0: int, y1: int, keep_invalid: bool) -> StripResult:
    """Sub-task body: the volume stages of one strip, on whichever worker runs it."""
    from .run import _config

    return run_strip(sub, _config(config_dict), y0, y1, keep_invalid=keep_invalid)
