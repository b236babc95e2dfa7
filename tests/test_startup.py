"""What one call costs before it matches: stage modules load by name, numba's start-up settings,
the compile notice and the warm-up. (Timings live in benchmarks/startup.py, not here.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stereocli import registry
from stereocli.matching import stages, warmup


def _python(code: str, **env) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, **env))


def test_import_stereocli_loads_the_package_alone_and_the_functions_on_first_use():
    # `import stereocli` stays light (benchmarks/startup.py times it): the public functions, and
    # numpy, OpenCV and numba with them, load when first used; the command line's Click never.
    loaded = "import sys\nprint(sorted(m for m in sys.modules if m.split('.')[0] in {})) "
    heavy = "('stereocli', 'numpy', 'cv2', 'numba', 'yaml', 'click', 'typing')"
    # (stereocli.lazy: the few lines that import the public names on first use)
    assert _python("import stereocli\n" + loaded.format(heavy)).stdout.split() == ["['stereocli',", "'stereocli.lazy']"]
    used = _python("import stereocli\nstereocli.match\nstereocli.evaluate\n" + loaded.format("('numba', 'click')"))
    assert used.stdout.split() == ["[]"], used.stderr
    listed = _python("import stereocli\nprint(all(callable(getattr(stereocli, n)) for n in stereocli.__all__ "
                     "if n != '__version__'))")
    assert listed.stdout.split() == ["True"], listed.stderr


def test_the_catalogue_names_every_stage_and_the_module_that_registers_it():
    registered = {(s.kind, s.name): s.func.__module__ for s in registry.stages()}
    declared = {(kind, name): module for module, kinds in stages.CATALOGUE.items()
                for kind, names in kinds.items() for name in names}
    assert declared == registered


def test_a_run_imports_only_the_stage_modules_its_config_names():
    code = ("import sys, json\nfrom stereocli.matching.config import build_config\nbuild_config()\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('stereocli.matching'))))")
    loaded = set(json.loads(_python(code).stdout))
    assert {"stereocli.matching.preprocess", "stereocli.matching.cost", "stereocli.matching.optimize.sgm",
            "stereocli.matching.refine"} <= loaded
    unused = {"stereocli.matching.aggregate", "stereocli.matching.cost_mi", "stereocli.matching.optimize.bp",
              "stereocli.matching.optimize.gc", "stereocli.matching.refine_voting", "stereocli.matching.refine_local",
              "stereocli.matching.refine_segment"}
    assert not loaded & unused


def test_another_stage_loads_its_module_when_named_and_listing_loads_all(run_cli):
    code = ("import sys\nfrom stereocli.matching.config import build_config\n"
            "build_config(sets=['optimizer.name=bp'])\nprint('stereocli.matching.optimize.bp' in sys.modules)")
    assert _python(code).stdout.strip() == "True"
    listed = run_cli("stages", "--format", "json")
    assert len(listed.json()) == sum(len(n) for kinds in stages.CATALOGUE.values() for n in kinds.values())


def test_numba_starts_without_its_blas_probe_and_idle_threads_soon_sleep():
    code = ("import os, sys\nfrom stereocli.process import prepare_kernels\nprepare_kernels()\n"
            "from numba import njit\nf = njit(lambda x: x + 1)\nf(1)\n"
            "import numba.np.arraymath as am\n"
            "print(os.environ['OMP_WAIT_POLICY'], os.environ['GOMP_SPINCOUNT'], am._HAVE_BLAS,"
            " 'scipy.linalg' in sys.modules)")
    assert _python(code).stdout.split() == ["passive", "10000", "False", "False"]
    # A value the user set wins.
    assert _python(code, OMP_WAIT_POLICY="active").stdout.split()[0] == "active"


def test_the_command_line_keeps_blas_to_one_thread_set_before_numpy_loads():
    code = ("import os, sys\nfrom stereocli.cli.main import main\nloaded_early = 'numpy' in sys.modules\n"
            "try:\n    main(['config', 'show'])\nexcept SystemExit:\n    pass\n"
            "from stereocli.process import limit_blas_threads\n"
            "print(loaded_early, 'numpy' in sys.modules, os.environ.get('OPENBLAS_NUM_THREADS'), limit_blas_threads())")
    env = {k: v for k, v in __import__("os").environ.items() if k != "OPENBLAS_NUM_THREADS"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    # numpy is not loaded before main() sets the variable, the command loads it, and then it is
    # too late to set it (limit_blas_threads says so).
    assert done.stdout.split()[-4:] == ["False", "True", "1", "False"]
    # A value the user set wins.
    assert _python(code, OPENBLAS_NUM_THREADS="2").stdout.split()[-2] == "2"


def test_numba_starts_without_its_cffi_support_and_cffi_still_imports_later():
    pytest.importorskip("cffi")  # installed by other packages; numba imports it when present
    code = ("import sys\nfrom stereocli.process import prepare_kernels\nprepare_kernels()\n"
            "from numba import njit\nf = njit(lambda x: x + 1)\nf(1)\n"
            "from numba.core.typing import cffi_utils\n"
            "print(cffi_utils.SUPPORTED, 'cffi' in sys.modules)\n"
            "import cffi\nprint(cffi.FFI is not None)")
    assert _python(code).stdout.split() == ["False", "False", "True"]


def test_the_compile_notice_comes_once_per_command():
    code = ("from stereocli.process import prepare_kernels, notify_compilation\nprepare_kernels()\n"
            "notify_compilation(lambda: print('NOTICE'))\n"
            "from numba import njit\nf = njit(lambda x: x + 1)\nf(1)\nf(1.5)\n"
            "notify_compilation(None)\ng = njit(lambda x: x - 1)\ng(1)\nprint('done')")
    assert _python(code).stdout.split() == ["NOTICE", "done"]


def test_a_notice_that_asks_again_is_called_at_later_compiles_until_it_is_done():
    # The command line's warm-up waits for a compile during a pair's matching (its config known).
    code = ("from stereocli.process import prepare_kernels, notify_compilation\nprepare_kernels()\n"
            "calls = []\n"
            "def notice():\n    calls.append(1)\n    print('NOTICE', len(calls))\n    return len(calls) < 2\n"
            "notify_compilation(notice)\n"
            "from numba import njit\nf = njit(lambda x: x + 1)\nf(1)\nf(1.5)\nf(2j)\nprint('done')")
    assert _python(code).stdout.split() == ["NOTICE", "1", "NOTICE", "2", "done"]


def test_the_compile_notice_says_so_on_stderr_unless_quiet(capsys, monkeypatch):
    from types import SimpleNamespace

    from stereocli.cli.main import COMPILE_NOTICE, _compile_notice
    from stereocli.runtime import aot

    monkeypatch.setattr(aot, "missing_build_advice", lambda: "")  # an install with its kernels built
    _compile_notice(SimpleNamespace(obj={"verbosity": 0}))
    err = capsys.readouterr().err
    assert err == COMPILE_NOTICE + "\n"
    _compile_notice(SimpleNamespace(obj={"verbosity": -1}))
    assert capsys.readouterr().err == ""
    # An install that lost its kernels says why and how to build them instead, once.
    monkeypatch.setattr(aot, "missing_build_advice", lambda: "the kernels were not compiled ahead of time (why)")
    _compile_notice(SimpleNamespace(obj={"verbosity": 0}))
    assert capsys.readouterr().err == "stereocli: the kernels were not compiled ahead of time (why)\n"


def test_warm_up_plan_spreads_the_longest_tasks_first():
    # The fine level and the coarse level's kernels compile in different processes.
    assert warmup.plan(["default"], 2) == [[("default", "volume_large"), ("default", "maps_1")],
                                           [("default", "maps_2"), ("default", "volume_small")]]
    assert warmup.plan(["default"], 1) == [[("default", t) for t in ("volume_large", "maps_2", "volume_small",
                                                                     "maps_1")]]
    slots = warmup.plan(["a", "b"], 3)
    assert sorted(t for s in slots for t in s) == sorted((c, t) for c in "ab" for t in warmup.TASKS)


def test_the_map_tasks_share_the_map_refinements_between_them(monkeypatch):
    # Every map refinement of the default runs in exactly one of the two map tasks.
    from stereocli.matching import pipeline
    from stereocli.matching.config import build_config

    ran = {}
    real_finish = pipeline.finish

    def finish(prepared, results, config):
        ran[current] = [c.stage.name for c in config.refinement if not c.stage.traits.needs_cost]
        return real_finish(prepared, results, config)

    monkeypatch.setattr(pipeline, "finish", finish)
    config = build_config([], [])
    for current in ("maps_1", "maps_2"):
        warmup.run_task(current, config)
    every = [c.stage.name for c in config.refinement if not c.stage.traits.needs_cost]
    assert ran["maps_1"] == every[0::2] and ran["maps_2"] == every[1::2]
    assert sorted(ran["maps_1"] + ran["maps_2"]) == sorted(every) and len(every) >= 4


def test_given_coarse_disparities_replace_the_coarse_level(monkeypatch):
    # Handing the fine level the coarse level's own result gives the same map, and the coarse
    # level does not run (the warm-up compiles the two levels in different processes).
    from stereocli.matching.config import build_config
    from stereocli.matching.optimize import sgm as osgm
    from stereocli.matching.pipeline import prepare, run_strip, strip_input

    config = build_config([], ["optimizer.coarse_min_volume=0"])
    left, right = warmup.synthetic_pair(160, 96, 32)
    prepared = prepare(left, right, config, ndisp=32)
    computed = run_strip(strip_input(prepared, 0, 96), config, 0, 96)
    coarse = osgm.coarse_disparity(strip_input(prepared, 0, 96), config.optimizer.params, config.cost)
    calls, given_calls = [], []
    real = osgm.coarse_disparity
    monkeypatch.setattr(osgm, "coarse_disparity", lambda *a: calls.append(1) or real(*a))
    given_config = warmup.with_coarse_level(config, lambda *a: given_calls.append(1) or coarse)
    given = run_strip(strip_input(prepared, 0, 96), given_config, 0, 96)
    assert calls == [] and given_calls == [1]
    assert np.array_equal(given.disparity, computed.disparity)
    assert np.isfinite(computed.disparity).mean() > 0.5
    # An optimizer without the trait keeps its config as it is.
    dp = build_config([], ["optimizer.name=dp"])
    assert warmup.with_coarse_level(dp, lambda *a: coarse) is dp


def test_synthetic_pair_shows_a_box_in_front_of_a_plane():
    left, right = warmup.synthetic_pair(96, 64, 16)
    assert left.shape == right.shape == (64, 96, 3) and left.dtype == np.uint8
    assert np.array_equal(left[0, 8:], right[0, 4:-4])  # background at ndisp // 4
    assert np.array_equal(left[32, 40:60], right[32, 32:52])  # the box at ndisp // 2


def test_warmup_command_runs_every_task(run_cli):
    r = run_cli("warmup", "--jobs", "1")
    assert r.code == 0
    for task in warmup.TASKS:
        assert f"default: {task} ready" in r.err
    assert "compiled kernels for default" in r.err
    assert run_cli("warmup", "--jobs", "1", "-q").err == ""


@pytest.mark.parametrize("sets", [[], ["optimizer.coarse_min_volume=1.0"], ["optimizer.coarse=false"]])
def test_the_warm_up_pair_takes_the_code_path_of_the_real_pair(monkeypatch, sets):
    # The tiny pair matched before a run's first pair must run the kernels that pair runs, or
    # the first pair's time.txt includes loading the others.
    from stereocli.matching.config import build_config, small_twin
    from stereocli.matching.optimize import sgm as osgm
    from stereocli.matching.pipeline import match_pair
    from stereocli.matching.warmup import tiny_match

    windowed = []
    real_windowed = osgm._run_windowed
    monkeypatch.setattr(osgm, "_run_windowed", lambda *a, **k: (windowed.append(True), real_windowed(*a, **k)))
    config = build_config([], sets)
    left, right = warmup.synthetic_pair(200, 160, 64)
    match_pair(left, right, config, ndisp=64)
    real = bool(windowed)
    windowed.clear()
    tiny_match(small_twin(config, 160, 200, 64), channels=3, dtype=np.dtype(np.uint8), min_disp=0, ndisp=64,
               masks=False)
    assert bool(windowed) == real
    assert real == (sets == ["optimizer.coarse_min_volume=1.0"])  # 160·200·64 = 2.0 M cells


def test_warm_up_processes_import_this_package_whatever_the_working_directory(tmp_path):
    # Started from a folder that holds another ``stereocli`` (a checkout beside an installed
    # copy), the warm-up processes must still run this one: ``python -m`` looks in the working
    # directory first. The decoy's warm-up module fails, so a worker that imports it fails the
    # warm-up.
    decoy = tmp_path / "decoy"
    (decoy / "stereocli" / "matching").mkdir(parents=True)
    (decoy / "stereocli" / "__init__.py").write_text("")
    (decoy / "stereocli" / "matching" / "__init__.py").write_text("")
    (decoy / "stereocli" / "matching" / "warmup.py").write_text("raise SystemExit(3)\n")
    script = tmp_path / "run_warm_up.py"
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(Path(warmup.__file__).resolve().parents[2])!r})\n"
        "from stereocli.matching import warmup\n"
        "from stereocli.matching.config import build_config\n"
        "done = []\n"
        "warmup.warm_up({'rt': build_config(['realtime'])}, jobs=2, report=lambda *a: done.append(a[1]))\n"
        "print(sorted(done))\n")
    run = subprocess.run([sys.executable, str(script)], cwd=decoy, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == str(sorted(warmup.TASKS))
