"""Batch jobs for every subcommand: work items, executors, and each subcommand's planner and
item function.

:mod:`.items` holds the item and outcome types and the per-item runner; :mod:`.executors`
runs an item function over items in-process, in a process pool or on Dask (:mod:`.dask`);
:mod:`.lock` keeps one run per output folder;
:mod:`.match`, :mod:`.rectify`, :mod:`.triangulate` and :mod:`.evaluate` turn command-line
inputs into items and hold the functions workers run. Only paths travel to workers, never
arrays. The library packages never import this package.
"""
