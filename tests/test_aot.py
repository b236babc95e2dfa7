"""Kernels compiled ahead of time (stereocli/runtime/aot.py) and numba started lazily: the
same maps bit for bit, the list of compiled signatures covers a default run, a stale or foreign
build is never used, and a default run with them does not import numba."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, installed_builds
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair
from stereocli.matching.warmup import synthetic_pair
from stereocli.runtime import aot

_FIND = aot.find  # the real lookup (the tests wrap it)
#: Two kernels built in the test (about 5 s): one that allocates, one that does not.
SOME_KERNELS = ["matching.kernels.maps._fill_background_rows", "matching.kernels.maps._lr_check_onto_rows"]


def _pairs() -> list[tuple[np.ndarray, np.ndarray, dict]]:
    """Inputs that take the default preset down each of its paths: coarse to fine (a volume of
    over 12 M cells), full range (a small one), grey, 16-bit, and with valid masks."""
    left, right = synthetic_pair(400, 300, 112)
    small_left, small_right = left[:120, :160].copy(), right[:120, :160].copy()
    grey_left, grey_right = left[..., 1].copy(), right[..., 1].copy()
    valid = np.ones(left.shape[:2], bool)
    valid[:, :6] = False
    return [(left, right, {"ndisp": 112}),
            (small_left, small_right, {"ndisp": 64}),
            (grey_left, grey_right, {"ndisp": 112}),
            (left.astype(np.uint16) * 257, right.astype(np.uint16) * 257, {"ndisp": 112}),
            (left, right, {"ndisp": 112, "left_valid": valid, "right_valid": valid}),
            (left, right, {"ndisp": 112, "keep_invalid": True})]  # match --keep-invalid: the median sees holes


def _maps(monkeypatch, folder: Path | None) -> tuple[list[np.ndarray], dict]:
    """The default preset's maps of :func:`_pairs`, with the kernels built in ``folder`` (None:
    none, numba's JIT), and ``{kernel: compiled calls}``."""
    if folder is None:
        monkeypatch.setenv("STEREOCLI_AOT", "0")
    else:
        monkeypatch.setenv("STEREOCLI_AOT", "1")
        monkeypatch.setenv("STEREOCLI_AOT_DIR", str(folder))
    monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild())
    used: dict = {}

    def counted(kernel, args):
        compiled = _FIND(kernel, args)
        if compiled is not None:
            used[kernel.py_func.__name__] = used.get(kernel.py_func.__name__, 0) + 1
        return compiled

    monkeypatch.setattr(aot, "find", counted)
    return _default_runs(), used


#: The presets whose kernels the build holds.
BUILT_PRESETS = ("default", "fast", "accurate", "realtime", "quality")


def _default_runs() -> list[np.ndarray]:
    """The maps of :func:`_pairs` by each of :data:`BUILT_PRESETS` (the default's on every pair,
    the others' on the first two and the grey one), and the disparity range estimated for the
    first pair (a coarse match of its own, run when the range is not given)."""
    from stereocli.features.disparity_range import estimate_range

    pairs = _pairs()
    maps = []
    for preset in BUILT_PRESETS:
        config = build_config([preset])
        maps += [match_pair(left, right, config, **kwargs).disparity
                 for left, right, kwargs in (pairs if preset == "default" else pairs[:3])]
    span = estimate_range(pairs[0][0], pairs[0][1])
    return maps + [np.array([span.min_disp, span.ndisp])]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    pytest.importorskip("numba.pycc")
    folder = tmp_path_factory.mktemp("aot")
    try:
        aot.build(folder, log=lambda line: None, only=SOME_KERNELS)
    except Exception as exc:  # noqa: BLE001 - e.g. no C compiler on this machine
        pytest.skip(f"numba.pycc cannot build here: {exc}")
    return folder


def test_type_names_are_numbas_own():
    numba = pytest.importorskip("numba")
    values = [np.zeros((3, 4), np.float32), np.zeros((3, 4, 2), np.uint16), np.zeros(5, np.int64),
              np.zeros((2, 2), np.bool_), np.zeros((4, 4), np.float64)[:, ::2], np.zeros((3, 4), order="F"),
              np.zeros(4, np.uint64)[::2], 3, 2.5, True, np.bool_(False), np.float32(1.5), np.int32(7)]
    for value in values:
        assert aot.type_name(value) == str(numba.typeof(value)), value
    frozen = np.zeros(3, np.float32)
    frozen.flags.writeable = False
    assert aot.type_name(frozen) is None  # numba's "readonly array": no compiled signature takes it
    assert aot.type_name("text") is None
    # and back: the build compiles the listed names as the types they name
    for signatures in aot.read_signatures().values():
        for name in {name for signature in signatures for name in signature}:
            assert str(aot.numba_type(name)) == name


def test_the_listed_signatures_are_those_of_the_built_presets(monkeypatch):
    seen: set = set()

    def recorded(kernel, args):
        seen.add((aot.kernel_name(kernel.py_func), tuple(aot.type_name(a) for a in args)))
        return _FIND(kernel, args)

    monkeypatch.setattr(aot, "find", recorded)
    _default_runs()
    listed = {(kernel, signature) for kernel, signatures in aot.read_signatures().items()
              for signature in signatures}
    assert seen == listed


@pytest.mark.slow
def test_kernels_built_ahead_of_time_give_the_same_maps_as_the_jit(monkeypatch, built):
    jit_maps, jit_used = _maps(monkeypatch, None)
    aot_maps, aot_used = _maps(monkeypatch, built)
    assert jit_used == {}
    assert set(aot_used) == {kernel.rsplit(".", 1)[1] for kernel in SOME_KERNELS}
    for jit_map, aot_map in zip(jit_maps, aot_maps):
        np.testing.assert_array_equal(aot_map, jit_map)


@pytest.mark.slow
def test_a_build_for_other_sources_another_cpu_damaged_or_none_is_not_used(monkeypatch, built, tmp_path):
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(built))
    monkeypatch.delenv("STEREOCLI_AOT", raising=False)
    assert aot._usable_build()[0]  # the fixture's build is used as it is
    manifest = json.loads((built / aot.MANIFEST).read_text())
    for key, value in (("sources", "0" * 16), ("cpu", "another"), ("numpy", "0")):
        changed = tmp_path / key
        changed.mkdir()
        for item in built.iterdir():
            (changed / item.name).symlink_to(item)
        (changed / aot.MANIFEST).unlink()
        (changed / aot.MANIFEST).write_text(json.dumps({**manifest, key: value}))
        monkeypatch.setenv("STEREOCLI_AOT_DIR", str(changed))
        assert aot._usable_build()[0] == {}, key
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(tmp_path / "empty"))
    assert aot._usable_build()[0] == {}
    # A damaged build: a module missing (the build is not used), or one that does not load (that
    # kernel runs from the JIT, the others from the build, and the record says so).
    modules = sorted(built.glob("*.so")) or sorted(built.glob("*.pyd"))
    for damage in ("missing", "garbage"):
        damaged = tmp_path / damage
        damaged.mkdir()
        for item in built.iterdir():
            if item != modules[0]:
                (damaged / item.name).symlink_to(item)
        if damage == "garbage":
            (damaged / modules[0].name).write_bytes(b"not a shared library")
        monkeypatch.setenv("STEREOCLI_AOT_DIR", str(damaged))
        if damage == "missing":
            assert aot._usable_build()[0] == {}, damage
            continue
        table = aot._usable_build()[0]
        monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild(table=table))
        broken = [kernel for kernel in table.values() if kernel.path.name == modules[0].name]
        assert len(broken) == 1 and broken[0].load() == {}
        assert all(kernel.load() for kernel in table.values() if kernel not in broken)
        assert f"1 did not load: {broken[0].name} (" in aot.describe()
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(built))
    monkeypatch.setenv("STEREOCLI_AOT", "0")
    assert aot._usable_build()[0] == {}


@pytest.mark.slow
def test_the_record_says_whether_the_build_is_used_and_why_not(monkeypatch, built, tmp_path):
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(built))
    for flag, expected in (("1", "2 compiled at install; others from numba's JIT"),
                           ("0", "none compiled at install (STEREOCLI_AOT=0): numba's JIT")):
        monkeypatch.setenv("STEREOCLI_AOT", flag)
        monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild())
        assert aot.describe() == expected
    monkeypatch.setenv("STEREOCLI_AOT", "1")
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(tmp_path))
    monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild())
    assert aot.describe() == f"none compiled at install (no build in {tmp_path}): numba's JIT"


def _complete_build() -> Path | None:
    """A build of every listed kernel for these sources: the installed package's (``pip install
    .``; the tests import the checkout's sources) or the checkout's (``pip install -e .``);
    None if neither."""
    for folder in [*installed_builds(), aot.BUILD_DIR]:
        manifest = aot.read_manifest(folder)
        if manifest and manifest == aot.expected_manifest(manifest["kernels"]) \
                and set(manifest["kernels"]) == set(aot.read_signatures()):
            return folder
    return None


@pytest.mark.slow
def test_the_installed_build_gives_the_same_maps_with_every_kernel(monkeypatch):
    folder = _complete_build()
    if folder is None:
        pytest.skip("no ahead-of-time build of these sources is installed")
    jit_maps, _ = _maps(monkeypatch, None)
    aot_maps, aot_used = _maps(monkeypatch, folder)
    assert set(aot_used) == {kernel.rsplit(".", 1)[1] for kernel in aot.read_signatures()}
    for jit_map, aot_map in zip(jit_maps, aot_maps):
        np.testing.assert_array_equal(aot_map, jit_map)


@pytest.mark.slow
def test_runs_of_the_built_presets_never_import_numba(tmp_path):
    folder = _complete_build()
    if folder is None:
        pytest.skip("no ahead-of-time build of these sources is installed")
    import cv2

    left, right = synthetic_pair(160, 120, 64)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    code = ("import sys\nfrom stereocli.cli.main import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit as exit:\n    assert exit.code == 0, exit.code\n"
            "print('numba' in sys.modules, 'stereocli.matching.kernels.slanted' in sys.modules)")
    argv = [str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--ndisp", "64", "-q", "--overwrite"]
    # The library calls of the other tests, in a fresh process: numba never starts either.
    library = ("import sys\nsys.path.insert(0, sys.argv[1])\nimport test_aot\ntest_aot._default_runs()\n"
               "print('numba' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", library, str(Path(__file__).parent)], capture_output=True,
                          text=True, env=dict(os.environ, STEREOCLI_AOT="1", STEREOCLI_AOT_DIR=str(folder)))
    assert done.returncode == 0 and done.stdout.split()[-1] == "False", done.stderr
    outputs = {}
    for aot_flag in ("1", "0"):
        out = tmp_path / f"out{aot_flag}"
        done = subprocess.run([sys.executable, "-c", code, "match", *argv, "-o", str(out)], capture_output=True,
                              text=True, env=dict(os.environ, STEREOCLI_AOT=aot_flag, STEREOCLI_AOT_DIR=str(folder)))
        assert done.returncode == 0, done.stderr
        outputs[aot_flag] = (done.stdout.split()[-2:], (out / "l" / "disp0.pfm").read_bytes())
    # numba imported only without the build; with it, only the kernels the default runs are loaded
    # (not quality's slanted_patchmatch kernels)
    assert outputs["1"][0] == ["False", "False"] and outputs["0"][0][0] == "True", outputs
    assert outputs["1"][1] == outputs["0"][1]


def test_numba_starts_on_first_use_and_kernels_imported_later_get_its_prange():
    code = ("import sys\nimport stereocli.matching.kernels.sgm as sgm\n"
            "print('numba' in sys.modules)\n"
            "from stereocli.runtime.compiling import start_numba\nstart_numba()\n"
            "import numba\nimport stereocli.matching.kernels.costs as costs\n"
            "print(costs.prange is numba.prange, type(sgm._penalty2).__name__)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.split() == ["False", "True", "CPUDispatcher"], done.stderr


def test_an_install_that_did_not_build_says_why_and_how_to_fix_it(monkeypatch, tmp_path):
    (tmp_path / aot.FAILED_NOTE).write_text("CompileError: no C compiler\n")  # what setup.py leaves
    monkeypatch.setenv("STEREOCLI_AOT", "1")
    monkeypatch.setenv("STEREOCLI_AOT_DIR", str(tmp_path))
    monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild())
    assert aot.describe() == "none compiled at install (not built at install: CompileError: no C compiler): numba's JIT"
    advice = aot.missing_build_advice()
    assert "CompileError: no C compiler" in advice and "to build them: " in advice
    monkeypatch.setenv("STEREOCLI_AOT", "0")  # turned off on purpose: nothing to advise
    monkeypatch.setattr(aot, "_BUILD", aot._UsedBuild())
    assert aot.missing_build_advice() == ""


@pytest.mark.slow
def test_a_wheel_without_compiled_kernels_is_pure_python(tmp_path):
    # STEREOCLI_AOT=0 stands for a failed build; the wheel must then not claim a platform.
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "-q", "-w", str(tmp_path)],
                          capture_output=True, text=True, env=dict(os.environ, STEREOCLI_AOT="0"))
    assert done.returncode == 0, done.stderr[-2000:]
    [wheel] = tmp_path.glob("stereocli-*.whl")
    assert wheel.name.endswith("-py3-none-any.whl"), wheel.name
    import zipfile

    names = zipfile.ZipFile(wheel).namelist()
    assert "stereocli/runtime/_aot/BUILD_FAILED.txt" in names
    assert not [n for n in names if n.endswith((".so", ".pyd"))]
