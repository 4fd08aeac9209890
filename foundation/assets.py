"""The vendored assets (``scenes/assets``, licences in its README) and environment maps.

Environment maps are handed to Mitsuba as bitmaps read here (OpenEXR's Python binding), not as
file names: Mitsuba's own EXR reader waits forever on OpenEXR's thread pool when Dr.Jit runs
with one thread (measured: ``dr.set_thread_count(1)`` then ``envmap`` with a ``filename``
hangs in ``IlmThread::TaskGroup``), and one Dr.Jit thread is how runs become bit-reproducible.
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


def bundled_hdris() -> list[str]:
    return sorted(p.stem for p in HDRI_DIR.glob("*.exr"))


def hdri_path(name_or_path: str | os.PathLike) -> Path:
    """A bundled HDRI by name (``sunrise``) or an EXR file; the error names what was asked for."""
    s = str(name_or_path)
    p = Path(s)
    if p.suffix.lower() == ".exr" or os.sep in s:
        if not p.is_file():
            raise UsageError(f"{p}: no such HDRI file")
        return p
    q = HDRI_DIR / f"{s}.exr"
    if not q.is_file():
        raise UsageError(f"HDRI {s!r}: not a bundled environment map (have {', '.join(bundled_hdris())}) "
                         "and not an .exr file")
    return q


@functools.lru_cache(maxsize=16)
def _hdri_pixels(path: str, mtime: float) -> np.ndarray:
    from .imageio import ImageIOError, exr_layer, read_exr

    ch = read_exr(path)
    try:
        rgb = exr_layer(ch, "")
    except ImageIOError:
        raise ImageIOError(f"{path}: HDRI has no R, G, B channels (has {', '.join(sorted(ch))})") from None
    if rgb.shape[-1] < 3:
        raise ImageIOError(f"{path}: HDRI needs R, G, B channels (has {', '.join(sorted(ch))})")
    rgb = np.ascontiguousarray(rgb[..., :3], np.float32)
    if min(rgb.shape[:2]) < 2:
        raise ImageIOError(f"{path}: HDRI is {rgb.shape[1]}×{rgb.shape[0]} pixels; need at least 2×2")
    bad = ~np.isfinite(rgb)
    if bad.any():
        raise ImageIOError(f"{path}: HDRI has {int(bad.any(-1).sum())} pixels with NaN/Inf values")
    # Small negative values (resampling ringing, down to −0.004 in the bundled maps) are left as they are:
    # Mitsuba's own loader passes them through too, and clamping would change every render.
    rgb.setflags(write=False)
    return rgb


def hdri_pixels(name_or_path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of an HDRI (validated: RGB, finite; cached)."""
    p = hdri_path(name_or_path)
    return _hdri_pixels(str(p.resolve()), p.stat().st_mtime)


def envmap(name_or_path: str | os.PathLike, **props) -> dict:
    """Mitsuba ``envmap`` emitter dict for an HDRI (bundled name or EXR path), from a validated bitmap."""
    import mitsuba as mi

    return {"type": "envmap", "bitmap": mi.Bitmap(np.array(hdri_pixels(name_or_path))), **props}
