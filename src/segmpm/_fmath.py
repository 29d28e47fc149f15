"""Floating-point primitives for the compiled kernels that LLVM can vectorise.

Numba lowers ``math.sqrt`` and ``math.log`` to calls of the C library. LLVM may not execute such
a call speculatively (on both sides of a branch), and it cannot vectorise a loop that contains
one (there is no vector ``log`` without Intel's SVML). The material pass of the time loop runs on
four points per AVX2 instruction only with these replacements:

* ``fsqrt``: LLVM's ``llvm.sqrt`` intrinsic, the same IEEE-754 square root as ``math.sqrt``
  (correctly rounded, NaN for x < 0), without errno.
* ``flog``: the natural logarithm in arithmetic and integer operations only. x = 2ᵏ m with
  m ∈ [√½, √2) read from the bits, f = m − 1 (exact), s = f/(2 + f), and
  ln(1 + f) = 2 atanh s = f − (f²/2 − s (f²/2 + R)), R = Σ_{j=1}^{10} 2 s²ʲ/(2j + 1) (the Taylor
  series of atanh; |s| ≤ 3 − 2√2 < 0.172, so the first omitted term is below 1e-18 of the
  result); then k ln 2 added in two parts. Within one unit in the last place of ``math.log``
  (tests/test_fmath.py); the same special values (NaN for x < 0 or NaN, −∞ at 0, +∞ at +∞) and
  subnormal x.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


@intrinsic
def fsqrt(typingctx, x):
    """√x of a float (``llvm.sqrt``); the same result as ``math.sqrt``."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.sqrt", [args[0].type])
        return builder.call(fn, args)

    return x(x), codegen


@intrinsic
def _bits(typingctx, x):
    """The IEEE-754 bits of a float64 as an int64."""
    if x != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _from_bits(typingctx, i):
    """The float64 with the IEEE-754 bits of an int64."""
    if i != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


#: bits of the float64 nearest √½: the mantissa of x is reduced to [√½, √2)
_SQRT_HALF_BITS = 0x3FE6A09E667F3BCD
#: ln 2 = _LN2_HI + _LN2_LO (the float64 nearest ln 2 and the rest, from 60 decimal digits)
_LN2_HI = 0.6931471805599453
_LN2_LO = 2.3190468138462996e-17
#: the smallest normal float64, and 2⁵⁴ to scale a subnormal x into the normal range
_TINY = 2.2250738585072014e-308
_TWO54 = 18014398509481984.0
#: bits of 1.0 (the exponent bias), of 2⁵², and 2⁵² + 1023
_ONE_BITS = 0x3FF0000000000000
_TWO52_BITS = 0x4330000000000000
_TWO52_PLUS_BIAS = 4503599627371519.0


@njit(cache=True, error_model="numpy", inline="always")
def flog(x):
    """ln x of a float64 without a library call (vectorisable); see the module docstring."""
    tiny = x < _TINY
    ix = _bits(x * _TWO54 if tiny else x)
    # biased exponent of x/√½, in [0, 2047) for positive normal x; the mask makes the shift a
    # logical one (AVX2 has no 64-bit arithmetic shift)
    e = ((ix - _SQRT_HALF_BITS + _ONE_BITS) >> 52) & 0x7FF
    m = _from_bits(ix - ((e - 1023) << 52))
    # k = e − 1023 as a float, exactly, without an int64 conversion (none in AVX2): the float
    # with the bits of 2⁵² + e, minus 2⁵² + 1023
    kf = _from_bits(e | _TWO52_BITS) - _TWO52_PLUS_BIAS
    kf = kf - 54.0 if tiny else kf
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    R = z * (2.0 / 3.0 + z * (2.0 / 5.0 + z * (2.0 / 7.0 + z * (2.0 / 9.0 + z * (2.0 / 11.0
        + z * (2.0 / 13.0 + z * (2.0 / 15.0 + z * (2.0 / 17.0 + z * (2.0 / 19.0
        + z * (2.0 / 21.0))))))))))  # fmt: skip
    hfsq = 0.5 * f * f
    r = kf * _LN2_HI + ((f - (hfsq - s * (hfsq + R))) + kf * _LN2_LO)
    # x ≤ 0 or NaN: −∞ at 0, NaN else; +∞ stays +∞
    r = r if x > 0.0 else (-np.inf if x == 0.0 else np.nan)
    return r if x < np.inf else x
