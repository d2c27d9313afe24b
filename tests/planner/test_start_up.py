"""What a process pays before its first plan: `import planner_core` loads none of the heavy
dependencies, a small plan needs neither scipy nor numba, and the first compile of the
compiled pass says so."""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import numpy as np
import pytest

from planner_core import iterative, window, window_kernel

HEAVY = ("numba", "llvmlite", "scipy", "matplotlib", "osqp")


def _modules_after(code: str) -> dict[str, object]:
    probe = code + (f"\nimport json, sys\nprint(json.dumps({{'loaded': [m for m in {HEAVY!r} if m in sys.modules], "
                    "'out': globals().get('out')}))")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    result: dict[str, object] = json.loads(r.stdout.strip().splitlines()[-1])
    return result


def test_import_and_a_small_plan_load_no_heavy_dependency() -> None:
    assert _modules_after("import planner_core\nfrom planner_core import Bounds, Problem, plan, verify") == {
        "loaded": [], "out": None}
    small = (
        "import numpy as np\n"
        "from planner_core import Bounds, Polytope, Problem, plan, use_compiled_kernel\n"
        "from planner_core.iterative import KERNEL_MIN_WAYPOINTS, compiled_pays_off\n"
        "eye = np.eye(3)\n"
        "box = Polytope(np.concatenate([eye, -eye]), np.full(6, 10.0))\n"
        "wps = np.array([[0.0, 0, 0], [2, 1, 0], [4, 0, 1], [6, 1, 1], [8, 0, 0]])\n"
        "p = Problem.from_waypoints(wps, np.full(4, 2.0), Bounds.symmetric(7, 6.5, 15, 60), (box,) * 4)\n"
        "choice = compiled_pays_off(p.m), compiled_pays_off(KERNEL_MIN_WAYPOINTS)\n"
        "use_compiled_kernel(choice[0], 'small problem')\n"  # as the CLI decides for its process
        "res = plan(p)\n"
        "out = [res.ok, res.stats['n_compiled_steps'], *choice]\n"
    )
    # a small plan: verified, without scipy or numba; compiled by the AOT build where `make setup`
    # built it (milliseconds to load), else on the dense daqp path
    aot = window.aot_ready()
    got = _modules_after(small)
    assert got["loaded"] == [] and got["out"][:1] == [True] and got["out"][2:] == [aot, True], got  # type: ignore[index]
    assert (got["out"][1] > 0) == aot, got  # type: ignore[index]


def test_compiled_pass_is_used_once_loaded() -> None:
    iterative.warm_up()  # the test session has it loaded already; either way, now it is
    assert iterative.compiled_pays_off(3) and iterative.compiled_pays_off(iterative.KERNEL_MIN_WAYPOINTS)


def test_a_cold_kernel_cache_announces_the_compile_once(monkeypatch: pytest.MonkeyPatch,
                                                         caplog: pytest.LogCaptureFixture,
                                                         request: pytest.FixtureRequest) -> None:
    """The compile itself is ~20 s: stood in for here by the warm-up it runs (which compiles
    for real on a cold cache); what is checked is that the user is told, before and after, once."""
    calls: list[int] = []
    before = window.kernel_build("jit")  # the JIT's compile: the AOT build has none to announce
    request.addfinalizer(lambda: window.kernel_build(before))
    monkeypatch.setattr(window_kernel, "cache_state", lambda: "cold")
    monkeypatch.setattr(iterative, "_compile_checked", [])
    monkeypatch.setattr(iterative, "warm_up", lambda: calls.append(1))
    from planner_core import Bounds, Polytope, Problem

    eye = np.eye(3)
    box = Polytope(np.concatenate([eye, -eye]), np.full(6, 10.0))
    wps = np.array([[0.0, 0, 0], [2, 1, 0], [4, 0, 1], [6, 1, 1]])
    problem = Problem.from_waypoints(wps, np.full(3, 2.0), Bounds.symmetric(7, 6.5, 15, 60), (box,) * 3)
    with caplog.at_level(logging.WARNING, logger="planner_core"):
        for _ in range(2):
            assert iterative.plan_iterative(problem).ok
    notes = [r.getMessage() for r in caplog.records if r.name == "planner_core"]
    assert calls == [1]
    assert len(notes) == 2 and notes[0].startswith("compiling the planner's kernel") and "compiled" in notes[1]


def test_kernel_cache_state_reads_numba_cache() -> None:
    iterative.warm_up()
    # after a warm-up in this process the cache holds this source's compiled pass (or numba
    # could not write one: then every process compiles, and says so)
    assert window_kernel.cache_state() in ("warm", "cold")


def test_every_public_name_resolves_from_its_module() -> None:
    """The door's table and its `__all__` name the same things, and each resolves (lazily) to
    the object its module defines; submodules named like functions do not shadow them."""
    import importlib

    import planner_core
    from planner_core import api

    assert set(api._WHERE) == set(api.__all__) == set(planner_core.__all__)
    for name, (module, attr) in api._WHERE.items():
        assert getattr(planner_core, name) is getattr(importlib.import_module(module), attr), name
    import planner_core.replan  # binds the submodule on the package: the function keeps the name

    assert callable(planner_core.replan) and callable(planner_core.verify)
