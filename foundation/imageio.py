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


# -- the one reader of images a user gives ---------------------------------------------------------------------------

_ORIENT = {  # EXIF orientation → the array operation that shows the image upright (PIL's exif_transpose)
    2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
    5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
    8: lambda a: np.rot90(a, 1),
}
HDR_SUFFIXES = (".exr", ".hdr", ".pfm")  #: read as stored (linear radiance); every other format is display-encoded


def _png_bit_depth(path: Path) -> int:
    with open(path, "rb") as fh:
        head = fh.read(25)
    return head[24] if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 25 else 8


def read_image(path: str | os.PathLike, channels: int | None = 3, linear: bool = True,
               what: str = "image") -> np.ndarray:
    """Any image a user gives (photo, exemplar, mask, texture, HDRI) as float32 (H, W, C), upright.

    JPEG, PNG, TIFF, BMP, WebP… in any mode — 1/8/16-bit grey, RGB, RGBA, LA, palette, CMYK — are scaled to
    [0, 1] by their bit depth (16-bit colour PNG/TIFF keeps its 16 bits), turned by their EXIF orientation and, with
    ``linear``, sRGB-decoded; EXR/HDR/PFM are linear radiance, read as stored. ``channels``: 3 gives RGB (grey
    repeated, alpha dropped), 1 grey (the alpha channel when there is one: a cut-out's mask), 4 RGBA (alpha 1 when
    absent), None as stored. A missing, unreadable or non-finite image is refused, naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageIOError(f"{p}: no such {what} file" if not p.exists() else f"{p}: is not a file ({what} expected)")
    if p.suffix.lower() in HDR_SUFFIXES:
        a, alpha = _read_hdr(p, what), None
    else:
        a, alpha = _read_display(p, what)
        if linear:
            a = srgb_to_linear(a)
    if a.ndim == 2:
        a = a[..., None]
    if not np.isfinite(a).all():
        raise ImageIOError(f"{p}: {what} has NaN/Inf values")
    if channels is None:
        return np.concatenate([a, alpha], -1) if alpha is not None else a
    if channels == 1:
        return alpha if alpha is not None else (a.mean(-1, keepdims=True) if a.shape[-1] > 1 else a)
    rgb = np.repeat(a, 3, -1) if a.shape[-1] == 1 else a[..., :3]
    if channels == 3:
        return np.ascontiguousarray(rgb, np.float32)
    if channels == 4:
        return np.concatenate([rgb, alpha if alpha is not None else np.ones_like(rgb[..., :1])], -1)
    raise ValueError(f"channels {channels}: expected 1, 3, 4 or None")


def _read_display(p: Path, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A display-encoded image in [0, 1] (H, W[, C]) and its alpha (H, W, 1) or None, upright."""
    from PIL import Image, UnidentifiedImageError

    try:
        im = Image.open(p)
        im.load()
        orientation = im.getexif().get(0x0112, 1)
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError) as exc:  # PIL's ways of saying "not an image"
        raise ImageIOError(f"{p}: not a readable {what} ({' '.join(str(exc).split())})") from None
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
        im = im.convert("RGB")
    elif mode == "PA":
        im = im.convert("RGBA")
    elif mode == "1":
        im = im.convert("L")
    mode = im.mode
    if mode.startswith("I;16") or mode == "I":
        a = np.asarray(im, np.float64) / 65535.0
    elif mode == "F":
        a = np.asarray(im, np.float64)
    elif mode in ("RGB", "RGBA") and p.suffix.lower() in (".png", ".tif", ".tiff") and _deep(p):
        a = _read_deep(p, what)  # PIL keeps 8 of the 16 bits of colour PNG/TIFF
    else:
        a = np.asarray(im, np.float64) / 255.0
    a = _ORIENT.get(orientation, lambda x: x)(a).astype(np.float32)
    if a.ndim == 3 and a.shape[-1] in (2, 4):  # LA, RGBA
        return a[..., :-1], a[..., -1:]
    return a, None


def _deep(p: Path) -> bool:
    if p.suffix.lower() == ".png":
        return _png_bit_depth(p) == 16
    import tifffile

    try:
        return tifffile.TiffFile(p).pages[0].bitspersample == 16
    except Exception:  # tifffile's many errors: let PIL's reading stand
        return False


def _read_deep(p: Path, what: str) -> np.ndarray:
    try:
        import cv2
    except ImportError:
        raise ImageIOError(f"{p}: a 16-bit colour {what} needs OpenCV to keep its 16 bits (pip install "
                           "opencv-python-headless; `make install` brings it with the face extra)") from None

    a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if a is None or a.dtype != np.uint16:
        raise ImageIOError(f"{p}: not a readable 16-bit {what}")
    a = a[..., [2, 1, 0, 3][: a.shape[-1]]] if a.ndim == 3 else a  # BGR(A) → RGB(A)
    return a.astype(np.float64) / 65535.0


def _read_hdr(p: Path, what: str) -> np.ndarray:
    import mitsuba as mi

    from .threads import exr_safe

    try:
        with exr_safe():
            bmp = mi.Bitmap(str(p))
    except Exception as exc:  # Mitsuba raises RuntimeError with its own wording
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ImageIOError(f"{p}: not a readable {what} ({first})") from None
    return np.array(bmp.convert(component_format=mi.Struct.Type.Float32, srgb_gamma=False), np.float32)


def read_photo(path_or_name: str) -> np.ndarray:
    """8-bit RGB photo (sRGB, as displayed) from a file (:func:`read_image`), or one of scikit-image's bundled
    photographs by name."""
    p = Path(path_or_name)
    if not p.exists():
        import skimage.data

        if path_or_name in ("astronaut", "chelsea", "coffee", "rocket") and hasattr(skimage.data, path_or_name):
            return np.asarray(getattr(skimage.data, path_or_name)())[..., :3]
        raise ImageIOError(f"{path_or_name}: no such image file")
    a = read_image(p, channels=3, linear=False)
    return np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
