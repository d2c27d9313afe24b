"""numba's decorators for the compiled window pass, and the rule its on-disk cache lacks.

The pass is compiled from several files (`window_factor`, `window_rows`, `window_kernel`).
numba keys each cached function on its own file's time stamp and size, so a cached `run_pass`
would keep the compiled code of a callee in another file after that file changed (a known
limitation: numba/numba #8396 and #9563 were not merged). `refresh_cache` closes the gap: a
digest of every source the pass is compiled from (`kernel_aot.SOURCES`, the digest the AOT
build is tied to) is kept beside numba's cache, and when it differs the cache indexes of every
function of the pass are emptied before anything is loaded from them: a change of any kernel
file compiles the whole pass again, as an edit of the single file used to.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar, cast

from numba import njit as _njit

F = TypeVar("F", bound=Callable[..., Any])
NV = 12  # a waypoint's jet: velocity to snap, 4 orders x 3 axes
STAMP = "window_kernel.sources"  # beside numba's index files: the digest they were compiled from
COMPILED: list[Any] = []  # every dispatcher of the pass, in definition order


def _jit(fn: F, **kw: Any) -> F:
    # numpy's error model: no zero-division branch in every inner loop (divisors are checked)
    try:
        disp = _njit(cache=True, error_model="numpy", **kw)(fn)
    except RuntimeError:  # no writable cache location (read-only install, no NUMBA_CACHE_DIR)
        disp = _njit(cache=False, error_model="numpy", **kw)(fn)
    COMPILED.append(disp)
    return cast(F, disp)


def njit(fn: F) -> F:
    """numba's decorator, typed, cached on disk so that each process does not compile again
    (compiling the pass takes ~20 s; loading it from the cache ~0.3 s)."""
    return _jit(fn)


def njit_inline(fn: F) -> F:
    """`njit`, inlined into its callers at the numba IR level (tiny helpers in the inner loops)."""
    return _jit(fn, inline="always")


def refresh_cache(dispatchers: Sequence[Any], digest: str) -> str:
    """Empty the on-disk cache indexes of `dispatchers` unless they were written from `digest`;
    then record `digest`. Returns `kept`, `emptied`, `no cache` (nothing cached on disk) or
    `unknown: <why>` (numba's internals or the file system refused; numba's own rule applies)."""
    try:
        caches = [d._cache for d in dispatchers]  # numba internals, hence the guard
        live = [c for c in caches if type(c).__name__ != "NullCache"]
        if not live:
            return "no cache"
        stamps = sorted({Path(c._cache_path) / STAMP for c in live})
        if all(s.is_file() and s.read_text() == digest for s in stamps):
            return "kept"
        for c in live:
            c.flush()  # an empty index: the next call compiles and saves anew
        for s in stamps:
            tmp = s.with_name(f"{s.name}.{os.getpid()}")
            tmp.write_text(digest)
            os.replace(tmp, s)  # another process reading the stamp sees the old or the new one
        return "emptied"
    except Exception as exc:  # a changed numba or an unwritable cache: never fail a plan for it
        return f"unknown: {type(exc).__name__}: {exc}"[:200]
