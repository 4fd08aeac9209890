"""Shared test set-up.

Every test process runs Dr.Jit and torch with ONE thread. With one thread renders and fits are
bit-identical run to run (Dr.Jit's multi-threaded reductions are not: renders differ by ~3e-7 and Adam
amplifies it — 148 of 2781 morph coordinates differed by up to 2.9e-4 between two runs here), so tests
that compare two runs (resume = uninterrupted, pool = serial) compare exactly. ``make test`` runs two
such processes side by side (pytest-xdist), which keeps both cores busy.
"""

import numpy as np
import pytest

import mi_plugins  # noqa: F401  (sets the variant, registers plugins)
import drjit as dr
import mitsuba as mi
import torch

dr.set_thread_count(1)
torch.set_num_threads(1)

#: the variant computes on a GPU (``cuda_ad_*``): its reductions use atomics (not bit-reproducible run to run)
#: and its cooperative vectors run in half precision (mi_plugins.neural_basis.CoopNet); tests that compare
#: two runs exactly, or float32 against float32 to 1e-4, use the tolerances measured there instead
CUDA = dr.backend_v(mi.Float) == dr.JitBackend.CUDA

# Chamfer / facing estimates with the morph trace's sample counts (20k queries, 200k reference samples) instead of
# the benches' 100k / 1M: the tests compare results far above that estimator's floor, and the full counts cost
# ~1.5 s per call (the estimator itself is tested with explicit counts)
from foundation import mesh_metrics  # noqa: E402

mesh_metrics.DEFAULT_SAMPLES = (20_000, 200_000)


def random_dirs(n: int, seed: int, upper: bool = True) -> mi.Vector3f:
    """n unit vectors, uniform on the (upper) sphere, from a seeded numpy generator."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    if upper:
        v[:, 2] = np.abs(v[:, 2])
    return mi.Vector3f(v.T.astype(np.float32))


def local_si(wi: mi.Vector3f, uv=(0.5, 0.5)) -> mi.SurfaceInteraction3f:
    """Surface interaction with an identity shading frame (local = world)."""
    n = dr.width(wi)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    si.wi = wi
    si.uv = mi.Point2f(*uv)
    return si


@pytest.fixture
def ctx():
    return mi.BSDFContext()


class compiled_kernels:
    """Counts the Dr.Jit kernels compiled (found in no cache, memory or disk) inside a ``with`` block."""

    def __enter__(self):
        self.was = dr.flag(dr.JitFlag.KernelHistory)
        dr.kernel_history_clear()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        return self

    def __exit__(self, *exc):
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, self.was)
        self.irs = [k["ir"].getvalue() if hasattr(k["ir"], "getvalue") else str(k["ir"])
                    for k in hist if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", False)]
        self.hashes = [k["hash"] for k in hist if k.get("type") == dr.KernelType.JIT]
        self.count = len(self.irs)
        return False


@pytest.fixture(scope="module")
def small_armadillo(tmp_path_factory):
    """A small morph benchmark of the armadillo (8 views at 48², 8 spp, an 800-vertex coarse input), one per test
    module that asks for it."""
    from pathlib import Path

    from inverse.morph import MorphBenchmarkSettings, load_morph_benchmark, make_morph_benchmark

    out = tmp_path_factory.mktemp("morph") / "armadillo"
    mesh = Path(__file__).resolve().parent.parent / "scenes" / "assets" / "meshes" / "armadillo.ply"
    s = MorphBenchmarkSettings(n_views=8, resolution=48, spp=8, coarse_vertices=800)
    return load_morph_benchmark(make_morph_benchmark(mesh, out, s, show_progress=False))
