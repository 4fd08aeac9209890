"""The vendored assets (``scenes/assets``, licences in its README) and environment maps.

Environment maps are handed to Mitsuba as bitmaps read here, not as file names: Mitsuba's EXR reader
waits forever on OpenEXR's thread pool when Dr.Jit runs with one thread (measured: after
``dr.set_thread_count(1)``, an ``envmap`` with a ``filename`` hangs in ``IlmThread::TaskGroup``), and one
Dr.Jit thread is how runs become bit-reproducible. The bitmap is read by Mitsuba itself, with two
threads for the moment (:func:`foundation.threads.exr_safe`), so the radiance is bit-identical.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from .errors import UsageError

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
ASSETS = SCENES / "assets"
HDRI_DIR = ASSETS / "hdri"
MESHES = ASSETS / "meshes"
FACE = ASSETS / "face"
ARMADILLO = MESHES / "armadillo.ply"
NEURAL = ASSETS / "neural"


def bundled_basis() -> Path:
    """The vendored universal neural-BTF basis (seed 002 MLPs, ``scenes/assets/neural/basis.npz``)."""
    p = NEURAL / "basis.npz"
    if not p.is_file():
        raise UsageError(f"{p}: the bundled neural basis is missing (a broken checkout?)")
    return p


def bundled_matdiff() -> Path:
    """The vendored material diffusion model (seed 002 §3.2; a weights-only run folder,
    ``scenes/assets/neural/matdiff``: float16 EMA weights, its metrics, device and chosen sampler)."""
    p = NEURAL / "matdiff"
    if not (p / "checkpoint.npz").is_file():
        raise UsageError(f"{p}: the bundled material diffusion model is missing (a broken checkout?); "
                         "give --run RUN of `photoreal btf train-diffusion`")
    return p


def pymeshlab_sample(name: str) -> Path:
    """A real mesh shipped inside pymeshlab's wheel (``tests/sample_meshes``: bunny.obj, cow.obj, …)."""
    import pymeshlab

    p = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes" / name
    if not p.is_file():
        raise UsageError(f"{p}: pymeshlab's sample mesh {name!r} is missing (reinstall pymeshlab)")
    return p


def bundled_hdris() -> list[str]:
    return sorted(p.stem for p in HDRI_DIR.glob("*.exr"))


def _names_a_file(name_or_path: str | os.PathLike) -> bool:
    s = str(name_or_path)
    return Path(s).suffix.lower() == ".exr" or os.sep in s


def hdri_path(name_or_path: str | os.PathLike) -> Path:
    """A bundled HDRI by name (``sunrise``) or an EXR file; the error names what was asked for."""
    s = str(name_or_path)
    p = Path(s)
    if _names_a_file(s):
        if not p.is_file():
            raise UsageError(f"{p}: no such HDRI file")
        return p
    q = HDRI_DIR / f"{s}.exr"
    if not q.is_file():
        raise UsageError(f"HDRI {s!r}: not a bundled environment map (have {', '.join(bundled_hdris())}) "
                         "and not an .exr file")
    return q


def hdri_label(name_or_path: str | os.PathLike) -> str:
    """A short name for an HDRI: the bundled name, or a file's stem (image layer names, figure captions)."""
    return Path(name_or_path).stem if _names_a_file(name_or_path) else str(name_or_path)


HDRI_RINGING = 0.05  #: negative values down to this fraction of the mean radiance are resampling ringing, kept


@functools.lru_cache(maxsize=16)
def _hdri_bitmap(path: str, mtime: float):
    """Mitsuba's own reader (what ``envmap`` with a file name would use: bit-identical radiance; Python's
    OpenEXR binding differs in the last bit at a few pixels), run with two Dr.Jit threads."""
    import mitsuba as mi

    from .imageio import ImageIOError
    from .threads import exr_safe

    try:
        with exr_safe():
            bmp = mi.Bitmap(path)
    except Exception as exc:  # Mitsuba raises RuntimeError with its own wording
        raise ImageIOError(f"{path}: not a readable HDR image ({str(exc).splitlines()[0] if str(exc) else exc})") from None
    if bmp.channel_count() < 3:
        raise ImageIOError(f"{path}: HDRI needs R, G, B channels (it has {bmp.channel_count()})")
    bmp = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    rgb = np.array(bmp)
    if min(rgb.shape[:2]) < 2:
        raise ImageIOError(f"{path}: HDRI is {rgb.shape[1]}×{rgb.shape[0]} pixels; need at least 2×2")
    bad = ~np.isfinite(rgb)
    if bad.any():
        raise ImageIOError(f"{path}: HDRI has {int(bad.any(-1).sum())} pixels with NaN/Inf values")
    # Small negative values (resampling ringing, down to −0.004 in the bundled maps) are left as they are:
    # Mitsuba's own loader passes them through too, and clamping would change every render. Radiance that is
    # negative beyond that, or nowhere positive, would light a scene with nothing (or less than nothing).
    peak = float(rgb.max())
    if peak <= 0.0:
        raise ImageIOError(f"{path}: HDRI is black everywhere (largest value {peak:g}): it would light nothing")
    low = float(rgb.min())
    if low < -HDRI_RINGING * max(float(rgb.mean()), 1e-12):
        raise ImageIOError(f"{path}: HDRI has negative radiance (down to {low:g}, mean {float(rgb.mean()):g}): "
                           "not an environment map")
    return bmp


def hdri_pixels(name_or_path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of an HDRI (validated: RGB, finite; cached)."""
    return np.array(hdri_bitmap(name_or_path))


def hdri_bitmap(name_or_path: str | os.PathLike):
    """The HDRI as a validated RGB float32 ``mi.Bitmap`` (cached by path and modification time)."""
    p = hdri_path(name_or_path)
    return _hdri_bitmap(str(p.resolve()), p.stat().st_mtime)


def envmap(name_or_path: str | os.PathLike, **props) -> dict:
    """Mitsuba ``envmap`` emitter dict for an HDRI (bundled name or EXR path), from a validated bitmap."""

    return {"type": "envmap", "bitmap": hdri_bitmap(name_or_path), **props}
