#!/usr/bin/env python3
"""Ablation: each preset with and without a stage, on the tuning scenes and on the validation scenes.

A stage earns its place in a preset by what it gains on the validation scenes (nothing was tuned
on them), not only on the scenes it was tuned on. For every preset and every named stage it
holds, this runs the preset as it is and without the stage (``interpolate`` is replaced by the
scanline ``fill`` the other presets use, so that rejected pixels are still filled) and prints,
with and without: the validation mean nonocc bad > 1 px, MiddEval3-Q weighted bad-2.0 and the v2
mean bad > 1 px (scoring rules of ``benchmarks/accuracy.py``). A stage is kept when the
validation mean gains (to two decimals).

    python benchmarks/ablation.py --presets fast,default --stages column_pattern --threads 1
    python benchmarks/ablation.py --presets quality --stages photo_consistency,interpolate
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import yaml

import accuracy  # benchmarks/accuracy.py: scenes, scoring rules; puts the checkout on sys.path
from stereocli.config import load_yaml, resolve_config_path
from stereocli.evaluation.api import weighted_average
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair

#: What replaces a stage in its "without" variant (``None``: nothing).
REPLACEMENTS = {"interpolate": {"name": "fill"}}
LIST_SECTIONS = ("preprocess", "aggregation", "refinement")


def without_stage(preset: str, stage: str, folder: Path) -> Path | None:
    """A YAML file holding ``preset`` without ``stage`` (or with its replacement); ``None`` when
    the preset does not run the stage."""
    layer = load_yaml(resolve_config_path(preset))
    found = False
    for section in LIST_SECTIONS:
        entries = []
        for entry in layer.get(section) or []:
            if entry.get("name") == stage:
                found = True
                if REPLACEMENTS.get(stage) is not None:
                    entries.append(dict(REPLACEMENTS[stage]))
            else:
                entries.append(entry)
        if section in layer:
            layer[section] = entries
    if not found:
        return None
    path = folder / f"{preset}-without-{stage}.yaml"
    path.write_text(yaml.safe_dump(layer, sort_keys=False))
    return path


def scores(scenes: list, config) -> dict[str, float]:
    """``{"validation": mean bad1.0, "mb2014": weighted bad2.0, "v2": mean bad1.0}`` of a config."""
    results: dict[str, list] = {}
    for scene in scenes:
        disparity = match_pair(scene.left, scene.right, config, ndisp=scene.ndisp).disparity
        results.setdefault(scene.dataset, []).append(accuracy.score(scene, disparity, 0.0))
    key = {"mb2014": "bad2.0", "v2": "bad1.0", "validation": "bad1.0"}
    return {dataset: weighted_average(res)["nonocc"][key[dataset]] for dataset, res in results.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=accuracy.DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--presets", default="realtime,fast,default,accurate,quality", help="comma-separated presets")
    ap.add_argument("--stages", default="column_pattern,photo_consistency,interpolate",
                    help="comma-separated stage names to leave out one at a time")
    ap.add_argument("--threads", type=int, default=0, help="kernel threads (0 = all cores)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = ap.parse_args(argv)
    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    if args.threads:
        accuracy.set_threads(args.threads)
    scenes = accuracy.load_scenes(args.data, list(accuracy.DATASETS), None)
    sets = [f"runtime.threads={args.threads}"] if args.threads else []
    rows = []
    with tempfile.TemporaryDirectory(prefix="ablation-") as tmp:
        for preset in filter(None, args.presets.split(",")):
            stages = filter(None, args.stages.split(","))
            variants = {stage: without_stage(preset, stage, Path(tmp)) for stage in stages}
            variants = {stage: path for stage, path in variants.items() if path is not None}
            if not variants:
                continue
            base = scores(scenes, build_config([preset], sets))
            for stage, path in variants.items():
                other = scores(scenes, build_config([str(path)], sets))
                gain = round(other["validation"], 2) - round(base["validation"], 2)
                rows.append({"preset": preset, "stage": stage, "with": base, "without": other,
                             "replacement": REPLACEMENTS.get(stage), "kept": gain > 0})
                print(f"# {preset} {stage}: validation {base['validation']:.2f} with, "
                      f"{other['validation']:.2f} without", file=sys.stderr)
    header = ["preset", "stage", "validation bad1 with / without", "MiddEval3-Q bad2.0 with / without",
              "v2 bad1 with / without", "decision"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        w, wo = r["with"], r["without"]
        stage = r["stage"] + (f" (without: {r['replacement']['name']})" if r["replacement"] else "")
        lines.append(f"| {r['preset']} | `{stage}` | {w['validation']:.2f} / {wo['validation']:.2f} | "
                     f"{w['mb2014']:.2f} / {wo['mb2014']:.2f} | {w['v2']:.2f} / {wo['v2']:.2f} | "
                     f"{'kept' if r['kept'] else 'leaves (no validation gain)'} |")
    print("\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
