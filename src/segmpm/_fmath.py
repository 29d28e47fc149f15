"""Floating-point primitives for the compiled kernels.

``fsqrt``: √x as LLVM's ``llvm.sqrt`` intrinsic. Numba lowers ``math.sqrt`` to a call of the C
library's ``sqrt``; LLVM may not execute such a call speculatively (on both sides of a branch) and
then neither turns the branch into a select nor vectorises the loop around it. The intrinsic is
the same IEEE-754 square root (correctly rounded, NaN for x < 0), without errno, and vectorises.
"""

from __future__ import annotations

from numba import types
from numba.extending import intrinsic


@intrinsic
def fsqrt(typingctx, x):
    """√x of a float (``llvm.sqrt``); same result as ``math.sqrt``."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.sqrt", [args[0].type])
        return builder.call(fn, args)

    return x(x), codegen
