"""A cache prefetch hint for numba kernels (issue 25): the wavefront passes of the stepwise
integration and its σ read each pixel's inputs on a different image row, so every pixel waits
for its own cache misses; prefetching a few pixels ahead overlaps them. Values are unaffected."""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["prefetch"]


@intrinsic
def prefetch(typingctx, arr, idx):
    """Hint the cache line of the C-contiguous array ``arr``'s flat element ``idx`` into the
    caches (LLVM's prefetch: read, high locality); no effect on values."""
    sig = types.void(arr, types.intp)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [ptr.type, i32, i32, i32]),
                                            "llvm.prefetch.p0i8")
        builder.call(fn, [ptr, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen
