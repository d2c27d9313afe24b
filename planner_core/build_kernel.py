"""Build the compiled pass ahead of time: `python -m planner_core.build_kernel`.

Compiles `window_kernel.run_pass` and `window_kernel.fill_rows` (what `window` calls) with
numba.pycc, at the signatures of `kernel_aot.EXPORTS`, into `planner_core/_window_aot*.so`: a
plain CPython extension module that needs only numpy at run time (see `kernel_aot`). The maths
are not copied: each export is a one-line shim calling the njit function itself, so the pass is
compiled by numba's own pipeline (the same flags as the JIT: numpy's error model, inlining) and
linked into the module; the build also leaves those compiled functions in numba's on-disk cache
(the JIT fallback's). The module also exports the digest of the source it was built from
(`source_hash`) and of the CPU it was built for (`cpu_hash`): `kernel_aot.load` refuses a
build whose digests are not this source's and this machine's.

Exit status 0 when the module is built and loads (in a fresh process, without numba), else 1
with the reason; plans then use numba's JIT, as without this build. ~30-60 s here.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from planner_core import kernel_aot

PACKAGE = Path(__file__).resolve().parent


class BuildError(RuntimeError):
    pass


def _shim(name: str, fn: Any) -> Callable[..., Any]:
    """`def name(a, b, ...): return fn(a, b, ...)`, checked against `fn`'s parameters."""
    params = [arg for arg, _ in kernel_aot.EXPORTS[name][1]]
    have = list(inspect.signature(fn.py_func).parameters)
    if have != params:
        raise BuildError(f"kernel_aot.EXPORTS[{name!r}] lists {params}, window_kernel.{name} takes {have}")
    src = f"def {name}({', '.join(params)}):\n    return _fn({', '.join(params)})\n"
    ns: dict[str, Any] = {"_fn": fn}
    exec(src, ns)  # generated from the parameter names above
    shim: Callable[..., Any] = ns[name]
    return shim


def _constant(name: str, value: int) -> Callable[[], int]:
    ns: dict[str, Any] = {"_value": value}
    exec(f"def {name}():\n    return _value\n", ns)
    fn: Callable[[], int] = ns[name]
    return fn


def build(output_dir: Path = PACKAGE, verbose: bool = False) -> Path:
    """Compile the module into `output_dir` (replacing a previous build atomically); its path."""
    digest = kernel_aot.source_digest()
    pycc: Any = importlib.import_module("numba.pycc")  # untyped

    from planner_core import window_kernel

    with tempfile.TemporaryDirectory(prefix=".aot-build-", dir=output_dir) as tmp:
        cc = pycc.CC(kernel_aot.MODULE)
        cc.output_dir = tmp
        cc.target_cpu = "host"  # as numba's JIT; kernel_aot refuses the module on another CPU
        cc.verbose = verbose
        for name in kernel_aot.EXPORTS:
            cc.export(name, kernel_aot.signature(name))(_shim(name, getattr(window_kernel, name)))
        cc.export("source_hash", "int64()")(_constant("source_hash", digest))
        cc.export("cpu_hash", "int64()")(_constant("cpu_hash", kernel_aot.cpu_digest()))
        cc.compile()
        built = list(Path(tmp).glob(f"{kernel_aot.MODULE}*"))
        if len(built) != 1:
            raise BuildError(f"pycc left {[p.name for p in built]} in its output directory")
        target = output_dir / built[0].name
        os.replace(built[0], target)  # a process loading the old build keeps its mapping
    if kernel_aot.source_digest() != digest:
        target.unlink()
        raise BuildError("window_kernel.py changed during the build")
    return target


_CHECK = (
    "import sys\n"
    "from planner_core import kernel_aot\n"
    "k = kernel_aot.load()\n"
    "print(k if isinstance(k, str) else 'ok', 'numba' in sys.modules)\n"
)


def check() -> str | None:
    """None when a fresh process loads the build without numba, else why not."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(PACKAGE.parent), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-c", _CHECK], capture_output=True, text=True, env=env, timeout=120)
    out = r.stdout.strip()
    if r.returncode != 0:
        return f"loading it failed: {r.stderr.strip()[-800:]}"
    if out != "ok False":
        return f"loading it: {out}"
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--verbose", action="store_true", help="pycc's own output")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    try:
        if shutil.which(os.environ.get("CC", "cc")) is None and shutil.which("gcc") is None:
            raise BuildError("no C compiler (pycc compiles the module's wrapper with one)")
        path = build(verbose=args.verbose)
        why = check()
        if why is not None:
            path.unlink(missing_ok=True)
            raise BuildError(why)
    except Exception as exc:  # any failure: say why; plans use numba's JIT as before
        print(f"AOT build of the compiled pass failed ({type(exc).__name__}: {exc}); "
              "plans use numba's JIT (planner_core.window_kernel) instead", file=sys.stderr)
        return 1
    size = path.stat().st_size / 2**20
    print(f"built {path.relative_to(PACKAGE.parent)} ({size:.1f} MB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
