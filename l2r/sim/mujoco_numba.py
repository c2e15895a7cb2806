"""MuJoCo's C functions, callable from numba kernels.

A kernel that calls them runs whole env steps, MuJoCo's physics steps included, without
returning to Python in between (`physics.py`). They are declared by symbol name and resolved in
the libmujoco that the `mujoco` bindings load, the same library and so the same version and the
same warning handler; kernels that call them cache as others do. They take the structs'
addresses, `MjModel._address` and `MjData._address`.

Called this way, outside the bindings' wrappers, a MuJoCo *error* (`mju_error`: a broken model,
an exhausted arena, neither of which the body's fixed model meets) ends the process with
MuJoCo's message instead of raising `mujoco.FatalError`. Warnings, such as the divergence
resets the env watches for, behave as from Python.
"""

from __future__ import annotations

from pathlib import Path

import llvmlite.binding as llvm
import mujoco
from numba import types


def _library() -> Path:
    """The libmujoco shipped inside the `mujoco` package (Linux: libmujoco.so.X, macOS: .dylib)."""
    here = Path(mujoco.__file__).parent
    found = sorted(here.glob("libmujoco.so*")) + sorted(here.glob("libmujoco*.dylib"))
    if not found:
        raise ImportError(f"no libmujoco shared library in {here}")
    return found[0]


llvm.load_library_permanently(str(_library()))

_MODEL_DATA = types.void(types.voidptr, types.voidptr)
mj_step1 = types.ExternalFunction("mj_step1", _MODEL_DATA)
mj_step2 = types.ExternalFunction("mj_step2", _MODEL_DATA)
mj_forward = types.ExternalFunction("mj_forward", _MODEL_DATA)
mj_transmission = types.ExternalFunction("mj_transmission", _MODEL_DATA)
# mj_solveM(m, d, x, y, n): x = M^-1 y for n vectors (rows), with the factor of the last mj_step1
mj_solveM = types.ExternalFunction("mj_solveM", types.void(types.voidptr, types.voidptr, types.voidptr, types.voidptr, types.intc))
