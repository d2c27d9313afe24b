"""numba keys each cached function on its own file's time stamp and size: a caller cached in
one file keeps a callee's old compiled code after the callee's file changes. The compiled pass
lives in several files (`window_factor`, `window_rows`, `window_kernel`), which is safe only with
`kernel_jit.refresh_cache`. Shown on two tiny modules compiled in fresh processes (a second each)
rather than on the pass itself (~20 s to compile)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from planner_core import kernel_jit, window_kernel

CALLEE = "from numba import njit\n\n\n@njit(cache=True)\ndef g(x):\n    return x + {add}\n"
CALLER = "from numba import njit\n\nfrom callee import g\n\n\n@njit(cache=True)\ndef f(x):\n    return 2 * g(x)\n"
RUN = """
import hashlib, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import callee, caller
from planner_core.kernel_jit import refresh_cache
if sys.argv[2] == "refresh":
    digest = hashlib.sha256(b"".join(Path(sys.argv[1], n).read_bytes() for n in ("callee.py", "caller.py"))).hexdigest()
    print(refresh_cache([callee.g, caller.f], digest))
else:
    print("-")
print(caller.f(1))
"""


def _run(folder: Path, mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", RUN, str(folder), mode], capture_output=True, text=True,
                         check=True, timeout=120).stdout.split()
    return out[0], int(out[1])


def _modules(folder: Path, add: int) -> None:
    (folder / "callee.py").write_text(CALLEE.format(add=add))
    (folder / "caller.py").write_text(CALLER)


def test_a_callee_edit_compiles_the_caller_again_only_with_refresh(tmp_path: Path) -> None:
    _modules(tmp_path, 1)
    assert _run(tmp_path, "plain") == ("-", 4)
    _modules(tmp_path, 1000)  # another size: numba's own index of `g` is stale, `f`'s is not
    # why refresh_cache exists (if this fails, numba now invalidates callers itself):
    assert _run(tmp_path, "plain") == ("-", 4), "numba's cache no longer keeps a caller's stale code"
    assert _run(tmp_path, "refresh") == ("emptied", 2002)  # no stamp yet: emptied, compiled anew
    assert _run(tmp_path, "refresh") == ("kept", 2002)  # same sources: loaded from the cache
    _modules(tmp_path, 1)
    assert _run(tmp_path, "refresh") == ("emptied", 4)


def test_the_pass_is_refreshed_from_every_kernel_file() -> None:
    """Every dispatcher of the pass is registered (so all are emptied together), and the digest
    the stamp records is the AOT build's, over all four files."""
    names = {d.py_func.__module__ for d in kernel_jit.COMPILED}
    assert names == {"planner_core.window_factor", "planner_core.window_rows", "planner_core.window_kernel"}
    assert window_kernel.run_pass in kernel_jit.COMPILED and window_kernel.fill_rows in kernel_jit.COMPILED
    from planner_core import kernel_aot
    assert {p.name for p in kernel_aot.SOURCES} >= {"kernel_jit.py", "window_factor.py", "window_rows.py",
                                                   "window_kernel.py"}
    assert window_kernel.CACHE in ("kept", "emptied", "no cache")
