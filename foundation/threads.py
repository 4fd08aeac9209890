"""Thread counts of Dr.Jit and torch, and why they matter here.

* Dr.Jit with several threads is not bit-reproducible (reductions are summed in whatever order the
  threads finish: renders differ by ~3e-7 run to run and Adam amplifies it); with one thread renders
  and fits are bit-identical. Dr.Jit reads no environment variable for it: :func:`drjit_threads`.
* torch's default intra-op threads spin-wait on a busy core: a tiny pix2pix step took 4.2 s with 2
  threads while another job used the machine, 0.03 s with 1 (measured on this 2-core machine).
* Mitsuba's EXR reader hangs with one Dr.Jit thread (see :mod:`foundation.assets`):
  :func:`exr_safe` raises the count to two while a scene file that may reference EXRs loads.
"""

from __future__ import annotations

import contextlib
from typing import Iterator


@contextlib.contextmanager
def drjit_threads(n: int | None) -> Iterator[None]:
    """Run with ``n`` Dr.Jit worker threads (None or 0: leave as is), restoring the old count."""
    import drjit as dr

    old = dr.thread_count()
    if n:
        dr.set_thread_count(int(n))
    try:
        yield
    finally:
        if n and dr.thread_count() != old:
            dr.set_thread_count(old)


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run with ``n`` torch intra-op threads (None or 0: leave as is), restoring the old count."""
    import torch

    old = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


@contextlib.contextmanager
def exr_safe() -> Iterator[None]:
    """At least two Dr.Jit threads while Mitsuba may read an EXR file (it deadlocks with one)."""
    import drjit as dr

    with drjit_threads(2 if dr.thread_count() < 2 else None):
        yield
