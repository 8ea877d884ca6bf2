"""Flush-to-zero for the threads that run the networks (x86-64 only).

Attention logits far below their row's maximum give softmax terms in float32's denormal range,
which x86 cores process about 100x slower than normal numbers (see
:class:`~logdesc_rt.network.OnnxNetwork`). The SSE control register (MXCSR) holds two bits that
make the core treat them as zero: FTZ (results) and DAZ (inputs). They are per thread, and
onnxruntime sets them only on its own pool threads and, once per process, on the thread that
creates the first session; a thread that runs a one-thread session runs every operator itself,
so this module sets them on it.

The register is read and written by numba-compiled code (an LLVM intrinsic through numba's
documented ``intrinsic`` extension; numba is already a dependency). Elsewhere than x86-64, or
where the compilation fails, nothing is changed and :func:`flush_denormals_on_this_thread`
returns False: callers then keep to threads onnxruntime set up itself.
"""

from __future__ import annotations

import platform

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

from ._jit import jit

FTZ_BIT = 1 << 15  # MXCSR: flush results below the normal range to zero
DAZ_BIT = 1 << 6  # MXCSR: read denormal inputs as zero
X86_64 = platform.machine().lower() in ("x86_64", "amd64")


@intrinsic
def _mxcsr_or(typing_context, bits):  # noqa: ARG001 (numba's intrinsic signature)
    """ORs ``bits`` (int32) into this thread's MXCSR; returns the new value (int32)."""

    def codegen(context, builder, signature, arguments):  # noqa: ARG001
        pointer = ir.IntType(8).as_pointer()
        function_type = ir.FunctionType(ir.VoidType(), [pointer])
        store = builder.module.declare_intrinsic("llvm.x86.sse.stmxcsr", fnty=function_type)
        load = builder.module.declare_intrinsic("llvm.x86.sse.ldmxcsr", fnty=function_type)
        slot = builder.alloca(ir.IntType(32))
        builder.call(store, [builder.bitcast(slot, pointer)])
        builder.store(builder.or_(builder.load(slot), arguments[0]), slot)
        builder.call(load, [builder.bitcast(slot, pointer)])
        return builder.load(slot)

    return types.int32(types.int32), codegen


@jit
def _set_mxcsr_bits(bits):
    return _mxcsr_or(bits)


def flush_denormals_on_this_thread() -> bool:
    """Set FTZ and DAZ on the calling thread; True if they are set (x86-64), False where this
    platform has no such register or it cannot be reached (nothing changed then)."""
    if not X86_64:
        return False
    try:
        value = int(_set_mxcsr_bits(np.int32(FTZ_BIT | DAZ_BIT)))
    except Exception:  # noqa: BLE001 (any failure to compile or run: keep IEEE behaviour)
        return False
    return (value & (FTZ_BIT | DAZ_BIT)) == (FTZ_BIT | DAZ_BIT)
