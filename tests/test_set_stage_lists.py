"""``--set`` adds, removes and replaces listed stages, and the errors that point at it show it."""

from __future__ import annotations

import pytest

from stereocli.config import parse_set
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config

DEFAULT = ["subpixel", "confidence", "lr_check", "fill", "median", "plane_smooth"]
FAST = ["subpixel", "lr_check", "fill", "median", "plane_smooth"]


def names(config) -> list[str]:
    return [c.stage.name for c in config.refinement]


def test_parse_set_splits_the_operator():
    assert parse_set("refinement.lr_check.max_diff=2") == (["refinement", "lr_check", "max_diff"], "=", 2)
    assert parse_set("refinement+=confidence") == (["refinement"], "+=", "confidence")
    assert parse_set("refinement.lr_check+={name: median, size: 5}") == (
        ["refinement", "lr_check"], "+=", {"name": "median", "size": 5})
    assert parse_set("refinement-=median") == (["refinement"], "-=", "median")


def test_append_insert_remove_replace():
    assert names(build_config()) == DEFAULT
    assert names(build_config(sets=["refinement+=bilateral"])) == DEFAULT + ["bilateral"]
    assert names(build_config(["fast"], ["refinement.lr_check+=confidence"])) == DEFAULT
    assert names(build_config(["fast"], ["refinement.1+=confidence"])) == DEFAULT
    assert names(build_config(sets=["refinement-=median"])) == ["subpixel", "confidence", "lr_check", "fill",
                                                                "plane_smooth"]
    assert names(build_config(sets=["refinement-=0"])) == DEFAULT[1:]
    replaced = build_config(sets=["refinement.median={name: bilateral, radius: 2}"])
    assert names(replaced) == ["subpixel", "confidence", "lr_check", "fill", "bilateral", "plane_smooth"]
    assert replaced.refinement[4].params.radius == 2
    assert names(build_config(sets=["refinement=[subpixel, {name: lr_check, max_diff: 2}]"])) == ["subpixel",
                                                                                                  "lr_check"]
    assert names(build_config(sets=["refinement=[]"])) == []
    assert build_config(sets=["cost={name: sad, window: [3, 3]}"]).cost.params.window == (3, 3)


def test_added_stage_takes_params_and_later_sets_edit_it():
    config = build_config(["fast"], ["refinement+={name: median, size: 7}", "refinement.5.size=9"])
    assert names(config) == FAST + ["median"]
    assert [c.params.size for c in config.refinement if c.stage.name == "median"] == [3, 9]


@pytest.mark.parametrize("assignment, message", [
    ("cost+=sad", "--set cost+=sad: += adds or removes a stage of a listed section (preprocess, aggregation, "
                  "refinement); set cost with cost.key=value"),
    ("refinement-=medain", "--set refinement-=medain: no stage 'medain' in refinement (did you mean 'median'?)"),
    ("refinement.9+=median", "--set refinement.9+=median: refinement has 5 stages (indices 0 to 4)"),
    ("refinement-=", "--set refinement-=: remove with refinement-=<stage name or index>, e.g. refinement-=0"),
    ("refinement+=7", "--set refinement+=7: expected a stage: its name (e.g. median) or {name: median, size: 5}"),
    ("refinement.median.size.x=3", "--set refinement.median.size.x=3: address a listed stage as "
                                   "refinement.<stage name or index>.<key>; forms: "),
    ("refinement+=confidence", "--set refinement+=confidence: refinement: 'confidence' reads the cost volume and "
                               "must come before 'plane_smooth' (stages that only edit the disparity map run after "
                               "the volume is dropped); e.g. --set refinement.lr_check+=confidence inserts it before "
                               "the first of them"),
])
def test_errors_show_the_syntax(assignment, message):
    with pytest.raises(ConfigError) as info:
        build_config(["fast"], [assignment])
    assert str(info.value).startswith(message)


def test_a_name_listed_twice_is_removed_by_index():
    with pytest.raises(ConfigError, match=r"refinement has 2 'geodesic_vote' stages \(at 8, 9\); address one by its "
                                          r"index, e.g. refinement-=8"):
        build_config(["quality"], ["refinement-=geodesic_vote"])
    config = build_config(["quality"], ["refinement-=9"])
    assert [c.params.lines for c in config.refinement if c.stage.name == "geodesic_vote"] == ["rows"]


def test_confidence_error_names_a_set_that_works(run_cli, tmp_path):
    from conftest import two_scenes

    scenes = two_scenes(tmp_path / "scenes", 64, 48)
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "a", "-c", "fast", "--confidence")
    assert r.code == 2
    hint = "add a refinement stage that does, e.g. --set refinement.lr_check+=confidence"
    assert r.err.strip().endswith(hint), r.err
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "b", "-c", "fast", "--confidence",
                "--set", "refinement.lr_check+=confidence")
    assert r.code == 0, r.err
    assert (tmp_path / "b" / "planes" / "conf0.pfm").is_file()
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "c", "--confidence", "--set", "refinement=[subpixel]")
    assert r.code == 2 and r.err.strip().endswith("e.g. --set refinement+=confidence"), r.err
