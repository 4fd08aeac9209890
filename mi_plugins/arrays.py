"""Host arrays that Dr.Jit's LLVM backend can reuse compiled kernels for.

Dr.Jit maps a CPU numpy array into the LLVM backend *without copying* and records
whether its data pointer is aligned to the vector width (32 bytes for float32 on
AVX2, at most 64). A kernel reading an unaligned input is compiled with unaligned
loads, i.e. it is a *different kernel*: numpy only guarantees 16-byte alignment, so a
training loop that uploads a fresh batch every iteration compiles the same kernel
again for every combination of aligned and unaligned inputs (2^k variants for k
inputs), and none of them is found in the kernel cache of the next run. Measured on
the BTF benchmark test with an empty cache: 885 kernels compiled, 206 distinct once
alignment is ignored (220 s of compilation, 117 s without the variants).

:func:`aligned` returns a C-contiguous copy on a 64-byte boundary (or the array
itself when it already is one); pass host arrays through it before they become
Dr.Jit arrays in anything that runs more than once.
"""

from __future__ import annotations

import numpy as np

ALIGN = 64  # bytes: Dr.Jit checks min(64, vector width × element size)


def is_aligned(a: np.ndarray) -> bool:
    """Whether Dr.Jit would map ``a`` as aligned (C-contiguous, data on a 64-byte boundary)."""
    return bool(a.flags.c_contiguous) and a.ctypes.data % ALIGN == 0


def aligned(a, dtype=np.float32) -> np.ndarray:
    """``a`` as a C-contiguous ``dtype`` array whose data starts on a 64-byte boundary.

    Returns ``a`` itself when it already is one (no copy); values are converted like
    ``np.asarray(a, dtype)`` (``dtype=None`` keeps ``a``'s).
    """
    a = np.asarray(a, dtype)
    if is_aligned(a):
        return a
    buf = np.empty(a.nbytes + ALIGN, np.uint8)
    off = -buf.ctypes.data % ALIGN
    out = buf[off:off + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out
