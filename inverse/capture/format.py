"""The capture format: photos + pinhole cameras (+ a coarse mesh, masks, points, a held-out split, a ground truth).

A capture folder holds

- ``capture.json`` (written last: a folder holding it is complete): the cameras, the split, what was imported;
- ``images/NAME.exr``: every photo at the working resolution, linear RGB, undistorted to its pinhole camera;
- ``masks/NAME.png`` (optional): the object's pixels, white;
- ``mesh.ply`` (optional): the coarse mesh, with vertex colours where the source had them;
- ``points.ply`` (optional): triangulated points with their colours (structure from motion).

Cameras are pinholes with square pixels, in COLMAP's axes (x right, y down, z forward) and pixel convention (the
image's top-left corner at (0, 0), pixel centres at +0.5): ``cam_to_world`` maps camera to world, ``f`` is the focal
length in pixels and ``(cx, cy)`` the principal point. :func:`sensor` gives the Mitsuba ``perspective`` sensor of a
camera: Mitsuba's camera looks down +z with x left and y up, and puts the principal point at
``principal_point_offset = 0.5 − (cx / W, cy / H)`` (measured: tests/capture/test_capture.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foundation.errors import UsageError

FORMAT = "photoreal-capture/1"
MARKER = "capture.json"
HELD_OUT_EVERY = 8  #: every 8th photo (in name order) is held out of every fit, as NeRF benchmarks do

#: Mitsuba's camera axes from COLMAP's: x and y flipped (both look down +z)
MITSUBA_FROM_COLMAP = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass
class CaptureCamera:
    """One photo's pinhole camera (undistorted, at the working resolution)."""

    name: str  #: the photo's name without extension: images/NAME.exr (masks/NAME.png)
    width: int
    height: int
    f: float  #: focal length in pixels (square pixels)
    cx: float  #: principal point, pixels from the left edge
    cy: float  #: principal point, pixels from the top edge
    cam_to_world: list[list[float]]  #: 4×4, COLMAP axes (x right, y down, z forward)
    #: the photo's EXIF says a flash fired (a light at the camera); None: not known (no EXIF, or not a photo file)
    flash: bool | None = None
    #: the photo's EXIF exposure, time × ISO / f-number² (relative: photos of one camera compare); None: not known
    exposure: float | None = None

    @property
    def matrix(self) -> np.ndarray:
        return np.asarray(self.cam_to_world, np.float64)

    @property
    def centre(self) -> np.ndarray:
        return self.matrix[:3, 3]

    def scaled(self, width: int) -> "CaptureCamera":
        """The same camera with its image resampled to ``width`` pixels across (the height keeps the aspect)."""
        k = width / self.width
        return CaptureCamera(self.name, int(width), max(1, int(round(self.height * k))), self.f * k, self.cx * k,
                             self.cy * k, self.cam_to_world, self.flash, self.exposure)

    def K(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) of world points and their depth along the optical axis (N,)."""
        w2c = np.linalg.inv(self.matrix)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.f * pc[:, 0] / z + self.cx, self.f * pc[:, 1] / z + self.cy], -1)
        return uv, z


@dataclass
class CaptureMeta:
    """``capture.json``."""

    cameras: list[CaptureCamera]
    train: list[str]  #: names of the photos a fit may use
    test: list[str]  #: held-out names (never fitted; scores are taken on them)
    source: dict = field(default_factory=dict)  #: what was imported: {"format", "path", …}
    mesh: str | None = None  #: "mesh.ply" when the capture has a coarse mesh
    masks: bool = False
    points: int = 0  #: triangulated points in points.ply
    truth: str | None = None  #: a ground-truth mesh in the folder (synthetic captures)
    sfm: dict | None = None  #: structure-from-motion figures, when the cameras came from `capture sfm`
    format: str = FORMAT


def split(names: list[str], every: int = HELD_OUT_EVERY) -> tuple[list[str], list[str]]:
    """The fixed split: every ``every``-th photo in name order held out (at least one, never all)."""
    names = sorted(names)
    if len(names) < 2:
        raise UsageError(f"a capture needs at least 2 photos (one held out), got {len(names)}")
    test = [n for k, n in enumerate(names) if k % every == every - 1] or [names[len(names) // 2]]
    return [n for n in names if n not in test], test


def sensor(cam: CaptureCamera, spp_sampler: bool = True, sample_border: bool = False) -> dict:
    """The Mitsuba ``perspective`` sensor of a capture camera (its film is the photo's size)."""
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    to_world = cam.matrix @ MITSUBA_FROM_COLMAP
    fov = float(np.degrees(2.0 * np.arctan(0.5 * cam.width / cam.f)))
    d = {"type": "perspective", "fov": fov, "fov_axis": "x",
         "principal_point_offset_x": 0.5 - cam.cx / cam.width, "principal_point_offset_y": 0.5 - cam.cy / cam.height,
         "to_world": mi.ScalarTransform4f(to_world.tolist()),
         "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height), "rfilter": {"type": "box"},
                  "sample_border": sample_border}}
    if spp_sampler:
        d["sampler"] = {"type": "independent"}
    return d


def check_camera(cam: CaptureCamera, where: str) -> None:
    """A camera's numbers are usable: finite, a rotation, positive focal length and size."""
    m = np.asarray(cam.cam_to_world, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise UsageError(f"{where}: camera {cam.name!r} has a pose that is not a finite 4×4 matrix")
    r = m[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
        raise UsageError(f"{where}: camera {cam.name!r}: its rotation is not a rotation (det {np.linalg.det(r):.3g})")
    if not (np.isfinite([cam.f, cam.cx, cam.cy]).all() and cam.f > 0 and cam.width > 0 and cam.height > 0):
        raise UsageError(f"{where}: camera {cam.name!r} has no usable intrinsics (f {cam.f}, {cam.width}×{cam.height})")


@dataclass
class Capture:
    """A loaded capture: its folder and description; photos and masks are read when asked for."""

    path: Path
    meta: CaptureMeta
    photos: dict[str, np.ndarray] = field(default_factory=dict)  #: filled by :meth:`photo` (or given, in memory)

    @property
    def cameras(self) -> dict[str, CaptureCamera]:
        return {c.name: c for c in self.meta.cameras}

    def photo(self, name: str) -> np.ndarray:
        """(H, W, 3) float32 linear RGB."""
        if name not in self.photos:
            from foundation import imageio

            p = self.path / "images" / f"{name}.exr"
            img = imageio.exr_layer(imageio.read_exr(p), "")[..., :3].astype(np.float32)
            cam = self.cameras[name]
            if img.shape[:2] != (cam.height, cam.width):
                raise UsageError(f"{p}: photo is {img.shape[1]}×{img.shape[0]}, its camera {cam.width}×{cam.height}")
            self.photos[name] = img
        return self.photos[name]

    def mask(self, name: str) -> np.ndarray | None:
        """(H, W) bool, or None without masks."""
        if not self.meta.masks:
            return None
        from foundation.imageio import read_image

        return read_image(self.path / "masks" / f"{name}.png", channels=1, linear=False, what="mask")[..., 0] > 0.5

    @property
    def mesh(self) -> Path | None:
        return self.path / self.meta.mesh if self.meta.mesh else None

    @property
    def truth(self) -> Path | None:
        return self.path / self.meta.truth if self.meta.truth else None


def load_capture(path: str | Path) -> Capture:
    """Read a capture folder; a missing or inconsistent part is named."""
    from foundation.records import load_folder_record

    path = Path(path)
    meta = load_folder_record(path, MARKER, CaptureMeta, FORMAT, "capture", "photoreal capture import")
    names = [c.name for c in meta.cameras]
    if len(set(names)) != len(names):
        raise UsageError(f"{path / MARKER}: two cameras share a name")
    for c in meta.cameras:
        check_camera(c, str(path / MARKER))
        if not (path / "images" / f"{c.name}.exr").is_file():
            raise UsageError(f"{path / 'images' / (c.name + '.exr')}: photo missing from the capture")
        if meta.masks and not (path / "masks" / f"{c.name}.png").is_file():
            raise UsageError(f"{path / 'masks' / (c.name + '.png')}: mask missing from the capture")
    unknown = [n for n in meta.train + meta.test if n not in names]
    if unknown or not meta.train or not meta.test or set(meta.train) & set(meta.test):
        raise UsageError(f"{path / MARKER}: train/test must be disjoint, non-empty lists of its photos")
    for f in (meta.mesh, meta.truth):
        if f and not (path / f).is_file():
            raise UsageError(f"{path / f}: missing from the capture")
    return Capture(path, meta)
