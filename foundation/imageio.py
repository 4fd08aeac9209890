"""Image I/O: multi-channel EXR (OpenEXR), PNG previews, linear <-> sRGB (colour-science).

Every writer goes through :func:`foundation.files.atomic_path`: data is written to a temporary
file beside the target and renamed into place, so a crash or an exception never leaves a
half-written output.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from .errors import UsageError
from .files import atomic_path


class ImageIOError(UsageError):
    """An image file is missing, unreadable or not what was expected (the message names it)."""


# -- colour transfer ----------------------------------------------------------------


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values (clipped to [0, 1] first)."""
    import colour

    return np.asarray(colour.cctf_encoding(np.clip(x, 0.0, 1.0), function="sRGB"), dtype=np.float32)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`linear_to_srgb`."""
    import colour

    return np.asarray(colour.cctf_decoding(np.clip(x, 0.0, 1.0), function="sRGB"), dtype=np.float32)


# -- EXR ------------------------------------------------------------------------------


def write_exr(path: str | os.PathLike, layers: Mapping[str, np.ndarray], half: bool = False) -> Path:
    """Write named layers into one multi-channel EXR.

    ``layers`` maps a layer name to an (H, W) or (H, W, C) array. Channel names
    follow the EXR convention ``layer.R`` / ``layer.X``: 3-channel layers get
    R, G, B (``normal`` and ``position`` get X, Y, Z), 2-channel ones U, V, and
    1-channel ones Y (or T for ``depth``). The layer named ``""`` (or
    ``"rgb"``) becomes the default R, G, B channels that viewers show.
    """
    import OpenEXR

    channels: dict[str, np.ndarray] = {}
    shape = None
    for name, arr in layers.items():
        a = np.asarray(arr)
        if a.ndim == 2:
            a = a[..., None]
        if a.ndim != 3:
            raise ImageIOError(f"{path}: layer '{name}' must be (H, W) or (H, W, C), got {a.shape}")
        if shape is None:
            shape = a.shape[:2]
        elif a.shape[:2] != shape:
            raise ImageIOError(f"{path}: layer '{name}' is {a.shape[:2]}, others are {shape}")
        c = a.shape[2]
        if name in ("normal", "position"):
            suffixes = "XYZ"
        elif c == 2:
            suffixes = "UV"
        elif c == 1:
            suffixes = "T" if name == "depth" else "Y"
        elif c in (3, 4):
            suffixes = "RGBA"
        else:
            suffixes = [str(i) for i in range(c)]
        prefix = "" if name in ("", "rgb") else f"{name}."
        for i in range(c):
            channels[prefix + suffixes[i]] = np.ascontiguousarray(
                a[..., i], dtype=np.float16 if half else np.float32
            )
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
    return Path(path)


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read an EXR into {channel name: (H, W) float32 array}; interleaved RGB(A) is split."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ImageIOError(f"{path}: no such EXR file")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        return {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain RuntimeErrors without the path
        raise ImageIOError(f"{path}: not a readable EXR file ({exc})") from exc


def exr_layer(channels: Mapping[str, np.ndarray], layer: str) -> np.ndarray:
    """Stack a layer's channels (e.g. 'albedo' -> albedo.R/G/B) into (H, W, C)."""
    prefix = "" if layer in ("", "rgb") else f"{layer}."
    names = [k for k in channels if k.startswith(prefix) and "." not in k[len(prefix):]]
    order = "RGBAXYZUVTY"
    names.sort(key=lambda k: order.find(k[len(prefix):]) if k[len(prefix):] in order else 99)
    if not names:
        raise ImageIOError(f"no layer '{layer}' (channels: {sorted(channels)})")
    return np.stack([channels[k] for k in names], axis=-1)


# -- PNG ------------------------------------------------------------------------------


def to_uint8_srgb(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    rgb = np.asarray(linear, dtype=np.float32)[..., :3] * exposure
    return np.round(linear_to_srgb(rgb) * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray, linear: bool = True, exposure: float = 1.0) -> Path:
    """Write an (H, W, 3) image as 8-bit PNG; linear input is sRGB-encoded first."""
    from PIL import Image

    a = np.asarray(image)
    if a.dtype != np.uint8:
        a = to_uint8_srgb(a, exposure) if linear else np.round(np.clip(a, 0, 1) * 255).astype(np.uint8)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    with atomic_path(path) as tmp:
        Image.fromarray(a[..., :3]).save(tmp, format="PNG")
    return Path(path)


def read_photo(path_or_name: str) -> np.ndarray:
    """8-bit RGB photo from a file, or one of scikit-image's bundled photographs by name."""
    from PIL import Image

    p = Path(path_or_name)
    if not p.is_file():
        import skimage.data

        if path_or_name in ("astronaut", "chelsea", "coffee", "rocket") and hasattr(skimage.data, path_or_name):
            return np.asarray(getattr(skimage.data, path_or_name)())[..., :3]
        raise ImageIOError(f"{path_or_name}: no such image file")
    try:
        return np.asarray(Image.open(p).convert("RGB"))
    except Exception as exc:  # PIL raises several unrelated types for bad files
        raise ImageIOError(f"{p}: not a readable image ({exc})") from exc


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
