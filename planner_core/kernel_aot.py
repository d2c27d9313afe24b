"""The compiled pass built ahead of time: `window_kernel` as a plain CPython extension module.

`python -m planner_core.build_kernel` compiles `window_kernel.run_pass` and `fill_rows` (the
two functions `window` calls) with numba.pycc into `planner_core/_window_aot*.so`, from the
same source as numba's JIT: no copy of the maths. Loading it needs numpy only: no numba, no
LLVM (~105 MB resident and ~0.4 s to load from numba's cache, for the JIT).

This module does not import numba. It holds the exported signatures (the types numba's JIT
compiles for the arrays `window` passes), the digest that ties a build to its source, and the
loader `load`, which refuses a build of another source (or of other signatures, or for
another numpy) with the reason: `window` then uses numba's JIT, as before the AOT build.

A pycc module unboxes an array by its item size alone (dtype, dimensions and layout are not
checked): `AotKernel` checks every argument against the signature before the call, copies an
input that is not laid out as declared (the values, hence the arithmetic, are the same) and
refuses an output (written in place) that is not.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

MODULE = "_window_aot"  # planner_core._window_aot
# Every file the pass is compiled from (the exported functions' modules and what they call):
# a build, and numba's cache of the JIT (`kernel_jit.refresh_cache`), belong to all of them.
SOURCES = tuple(Path(__file__).with_name(f) for f in
                ("kernel_jit.py", "window_factor.py", "window_rows.py", "window_kernel.py"))
BUILD_COMMAND = "python -m planner_core.build_kernel"

_I1 = "int64[::1]"
_F1 = "float64[::1]"
_F2 = "float64[:, ::1]"
_F3 = "float64[:, :, ::1]"

# Exported functions: return type, arguments (name, numba type) in `window_kernel`'s order.
# The types are those numba's JIT compiles for what `window` passes (`k8` is a product of
# fancy-indexed arrays: not C-contiguous, typed 'A' as the JIT types it).
EXPORTS: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "run_pass": ("int64", (
        ("j0", "int64"), ("window", "int64"), ("m", "int64"),
        ("off", _I1), ("n1", _I1), ("n2", _I1), ("hull", _F3), ("cs", _F2), ("pr", _I1), ("pd", _I1),
        ("bn1", "int64"), ("nb", "int64"), ("face_off", _I1), ("pa", _F2), ("w", _F2), ("b6", _F2),
        ("f6", _F2), ("k8", "float64[:, :, :]"), ("kdd", _F3), ("qpos", _F2), ("qsum", _F2), ("kba4", _F3),
        ("kab4", _F3), ("jets", _F3), ("guess", _F3), ("active", "boolean[::1]"), ("step_times", _F1),
        ("check_tol", "float64"), ("ts", _I1),
    )),
    "fill_rows": ("void", (
        ("segs", _I1), ("off", _I1), ("hull", _F3), ("w", _F2), ("cs", _F2), ("pr", _I1), ("pd", _I1),
        ("bdir", _F2), ("bn1", "int64"), ("blim", _F2), ("face_off", _I1), ("pa", _F2), ("pb", _F1),
        ("inf", "float64"), ("margin", "float64"), ("ab", _F2), ("c0", _F1), ("lim", _F2), ("limw", _F2),
        ("add_tol", "float64"),
    )),
}
# arguments written in place: they must be passed as declared (a copy would lose the writes)
OUTPUTS: dict[str, frozenset[str]] = {
    "run_pass": frozenset({"jets", "guess", "active", "step_times", "ts"}),
    "fill_rows": frozenset({"ab", "c0", "lim", "limw"}),
}
_DTYPES = {"int64": np.dtype(np.int64), "float64": np.dtype(np.float64), "boolean": np.dtype(np.bool_)}


def signature(name: str) -> str:
    """numba's signature string of export `name`."""
    ret, args = EXPORTS[name]
    return f"{ret}({', '.join(t for _, t in args)})"


def source_digest(sources: tuple[Path, ...] | None = None) -> int:
    """63 bits of SHA-256 over the kernel's sources (each file's name and bytes), the exported
    signatures and numpy's version (a pycc module is built against numpy's C API): what a build
    must have been made from."""
    h = hashlib.sha256()
    for path in sources or SOURCES:
        data = path.read_bytes()
        h.update(f"{path.name} {len(data)}\n".encode())
        h.update(data)
    for name in sorted(EXPORTS):
        h.update(f"\n{name}: {signature(name)}".encode())
    h.update(f"\nnumpy {np.__version__}".encode())
    return int.from_bytes(h.digest()[:8], "little") >> 1


def cpu_digest() -> int:
    """63 bits of SHA-256 over this machine's CPU flags (/proc/cpuinfo): the build targets the
    CPU it is built on (as numba's JIT does), so a copy on another CPU is refused, not run into
    an illegal instruction. 0 where /proc/cpuinfo does not say."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return 0
    flags = next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), None)
    if flags is None:
        return 0
    return int.from_bytes(hashlib.sha256(" ".join(sorted(flags)).encode()).digest()[:8], "little") >> 1


def built_path() -> Path | None:
    """The built extension module, when there is one (found, not imported)."""
    spec = importlib.util.find_spec(f"planner_core.{MODULE}")
    return Path(spec.origin) if spec is not None and spec.origin else None


@dataclass(frozen=True)
class _Arg:
    name: str
    dtype: np.dtype[Any] | None  # None: a scalar
    scalar: str  # numba's scalar type name, for a scalar
    ndim: int
    contiguous: bool
    output: bool


def _parse(name: str) -> tuple[_Arg, ...]:
    out = []
    for arg, typ in EXPORTS[name][1]:
        if "[" not in typ:
            out.append(_Arg(arg, None, typ, 0, False, False))
            continue
        base, dims = typ[:-1].split("[")
        parts = [p.strip() for p in dims.split(",")]
        out.append(_Arg(arg, _DTYPES[base], base, len(parts), parts[-1] == "::1", arg in OUTPUTS[name]))
    return tuple(out)


def _scalar(a: _Arg, v: Any) -> Any:
    if a.scalar == "int64":
        return int(v)
    if a.scalar == "float64":
        return float(v)
    raise TypeError(f"unsupported scalar type {a.scalar}")


class AotKernel:
    """The built module's `run_pass` and `fill_rows`, each argument checked against `EXPORTS`."""

    kind = "aot"

    def __init__(self, module: Any) -> None:
        self.module = module
        self.path = Path(module.__file__)
        self._specs = {name: _parse(name) for name in EXPORTS}
        self._fns: dict[str, Callable[..., Any]] = {name: getattr(module, name) for name in EXPORTS}

    def _args(self, name: str, args: tuple[Any, ...]) -> list[Any]:
        specs = self._specs[name]
        if len(args) != len(specs):
            raise TypeError(f"{name}: {len(args)} arguments, the AOT build takes {len(specs)}")
        out: list[Any] = []
        for a, v in zip(specs, args, strict=True):
            if a.dtype is None:
                out.append(_scalar(a, v))
                continue
            if not isinstance(v, np.ndarray) or v.dtype != a.dtype or v.ndim != a.ndim:
                got = f"{v.dtype} {v.ndim}-d array" if isinstance(v, np.ndarray) else type(v).__name__
                raise TypeError(f"{name}({a.name}): {a.dtype} {a.ndim}-d array expected, got {got}")
            if a.contiguous and not v.flags.c_contiguous:
                if a.output:
                    raise TypeError(f"{name}({a.name}): written in place, must be C-contiguous")
                v = np.ascontiguousarray(v)
            if a.output and not v.flags.writeable:
                raise TypeError(f"{name}({a.name}): written in place, is read-only")
            out.append(v)
        return out

    def run_pass(self, *args: Any) -> int:
        return int(self._fns["run_pass"](*self._args("run_pass", args)))

    def fill_rows(self, *args: Any) -> None:
        self._fns["fill_rows"](*self._args("fill_rows", args))


def load(sources: tuple[Path, ...] | None = None) -> AotKernel | str:
    """The AOT build of `sources` (default `SOURCES`: the kernel's files), or why not (not built,
    not loadable, built from other sources or for another CPU)."""
    sources = sources or SOURCES
    path = built_path()
    if path is None:
        return f"not built ({BUILD_COMMAND})"
    try:
        module = importlib.import_module(f"planner_core.{MODULE}")
        built = int(module.source_hash())
        cpu = int(module.cpu_hash())
    except (ImportError, OSError, AttributeError) as exc:
        return f"{path.name} does not load: {type(exc).__name__}: {exc}"
    want = source_digest(sources)
    if built != want:
        return (f"stale: {path.name} was built from other kernel sources ({', '.join(p.name for p in sources)}), "
                f"signatures or numpy: digest {built:016x}, the sources' {want:016x}; rebuild with {BUILD_COMMAND}")
    if cpu != cpu_digest():
        return f"{path.name} was built for another CPU (its flags differ from this one's); rebuild with {BUILD_COMMAND}"
    return AotKernel(module)
