"""A :class:`~inverse.capture.sources.Source` (photos + the tool's cameras) → a capture folder: photos decoded to
linear RGB, downsampled by area to the working resolution, undistorted to square-pixel pinholes (principal point
kept), masks alike, a coarse mesh (the user's, or one made from triangulated points), the fixed held-out split."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from foundation.errors import UsageError

from .format import MARKER, CaptureCamera, CaptureMeta, check_camera, split


def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) box-filter weights: output sample j averages the input over [j, j + 1)·n_in/n_out."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    k = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, k + 1) - np.maximum(lo, k), 0.0, None)
    return overlap / overlap.sum(1, keepdims=True)


def area_resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample (H, W, C) to (height, width, C) by area averaging (no aliasing when shrinking)."""
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img.astype(np.float32)
    a = np.tensordot(_area_weights(h, height), img.astype(np.float64), axes=(1, 0))
    a = np.tensordot(a, _area_weights(w, width), axes=(1, 1))  # (height, C, width)
    return np.moveaxis(a, -1, 1).astype(np.float32)


def undistort(img: np.ndarray, source_camera, out: CaptureCamera) -> tuple[np.ndarray, np.ndarray]:
    """The photo seen by the pinhole ``out`` from the same centre (bilinear), and where the source covered it.

    For every output pixel centre the ray through it (pinhole ``out``) is projected by the source camera's own
    model, distortion included (pycolmap's ``img_from_cam``), and the photo is sampled there."""
    from scipy.ndimage import map_coordinates

    h, w = out.height, out.width
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    rays = np.stack([(xs - out.cx) / out.f, (ys - out.cy) / out.f, np.ones_like(xs)], -1).reshape(-1, 3)
    uv = np.asarray(source_camera.img_from_cam(rays, False), np.float64).reshape(h, w, 2)
    col, row = uv[..., 0] - 0.5, uv[..., 1] - 0.5  # pixel centres at integer array indices
    sh, sw = img.shape[:2]
    inside = np.isfinite(col) & (col >= -0.5) & (col <= sw - 0.5) & (row >= -0.5) & (row <= sh - 0.5)
    col, row = np.where(inside, col, 0.0), np.where(inside, row, 0.0)
    chans = [map_coordinates(img[..., c].astype(np.float64), [row, col], order=1, mode="nearest")
             for c in range(img.shape[2])]
    res = np.stack(chans, -1).astype(np.float32)
    res[~inside] = 0.0
    return res, inside


def working_camera(name: str, source_camera, c2w: np.ndarray, resolution: int | None):
    """(the pycolmap camera rescaled to the working size, the pinhole capture camera of that size)."""
    import pycolmap

    w, h = source_camera.width, source_camera.height
    s = min(1.0, resolution / max(w, h)) if resolution else 1.0
    W, H = max(1, round(w * s)), max(1, round(h * s))
    cam = pycolmap.Camera(model=source_camera.model, width=w, height=h, params=source_camera.params)
    cam.rescale(W, H)
    cx, cy = float(cam.principal_point_x), float(cam.principal_point_y)
    out = CaptureCamera(name, W, H, no_blank_focal(cam, float(cam.focal_length_x), cx, cy), cx, cy,
                        np.asarray(c2w, np.float64).tolist())
    return cam, out


def no_blank_focal(cam, f: float, cx: float, cy: float) -> float:
    """The least focal length ≥ ``f`` at which every pixel of a pinhole of ``cam``'s size maps inside ``cam``'s photo,
    as COLMAP's undistorter leaves no blank pixels: a lens that magnifies toward its edges (pincushion, a positive
    radial term) would leave the pinhole's rim without data, black pixels the fit and the scores would count."""
    w, h = cam.width, cam.height
    xs, ys = np.arange(w) + 0.5, np.arange(h) + 0.5
    ring = np.concatenate([np.stack([xs, np.full(w, 0.5)], 1), np.stack([xs, np.full(w, h - 0.5)], 1),
                           np.stack([np.full(h, 0.5), ys], 1), np.stack([np.full(h, w - 0.5), ys], 1)])

    def fits(fo: float) -> bool:
        rays = np.stack([(ring[:, 0] - cx) / fo, (ring[:, 1] - cy) / fo, np.ones(len(ring))], 1)
        uv = np.asarray(cam.img_from_cam(rays, False), np.float64)
        return bool(np.all(np.isfinite(uv)) and np.all((uv >= 0) & (uv <= [w, h])))

    if fits(f):
        return f
    lo, hi = f, 2.0 * f
    if not fits(hi):
        return hi
    for _ in range(40):  # bisection to 2⁻⁴⁰ of f
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi


def _fit_camera_to_photo(cam, photo_size: tuple[int, int], image: Path):
    """The camera for the photo as stored: the same size, or a uniformly scaled copy (images_2/, a thumbnail)."""
    import pycolmap

    pw, ph = photo_size
    if (pw, ph) == (cam.width, cam.height):
        return cam
    s = pw / cam.width
    if abs(ph - cam.height * s) > 1.0 + 1e-6 * cam.height:
        raise UsageError(f"{image}: photo is {pw}×{ph} (after its EXIF orientation), its camera {cam.width}×"
                         f"{cam.height}: not a scaled copy")
    c = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params)
    c.rescale(pw, ph)
    return c


def import_capture(source, out: str | Path, resolution: int | None = 512, mesh: str | Path | None = None,
                   show_progress: bool = True, triangulate: bool = True, derived: tuple[str, ...] = (),
                   coarse: str = "auto") -> Path:
    """Write the capture folder ``out`` (atomically) from a source; returns it.

    ``resolution``: the longest side of the working photos (never enlarged; None keeps the photos' size).
    ``mesh``: the tool's coarse mesh (OBJ with its MTL texture, PLY with or without vertex colours, GLB); without
    one, a coarse mesh is made from the source's points, or from points triangulated with the given cameras.
    ``derived``: entries of ``out`` that the new capture replaces (a structure-from-motion work folder inside it).
    ``coarse`` (without ``mesh``): "poisson" (the points' surface), "hull" (the masks' visual hull, coloured from the
    training photos), "auto": Poisson when the source has points, else the hull when it has masks, else Poisson of
    points triangulated with the cameras."""
    from foundation import imageio
    from foundation.files import atomic_dir, write_json
    from foundation.mesh import write_ply
    from foundation.progress import progress_bar
    from foundation.records import to_json

    from .coarse import coarse_mesh_from_points, load_coarse_mesh
    from .sfm import flash_fired, photo_exposure

    t0 = time.perf_counter()
    if resolution is not None and not (isinstance(resolution, int) and 16 <= resolution <= 8192):
        raise UsageError(f"resolution must be an integer in [16, 8192], got {resolution}")
    if coarse not in ("auto", "poisson", "hull"):
        raise UsageError(f"coarse {coarse!r}: auto, poisson or hull")
    if coarse == "hull" and not all(fr.mask is not None for fr in source.frames):
        raise UsageError("coarse hull: needs a mask for every photo (--masks)")
    user_mesh = load_coarse_mesh(mesh) if mesh is not None else None  # a bad mesh is named before any work
    frames = sorted(source.frames, key=lambda fr: fr.name)
    with atomic_dir(out, MARKER, derived=derived) as tmp:
        (tmp / "images").mkdir()
        if any(fr.mask is not None for fr in frames):
            if not all(fr.mask is not None for fr in frames):
                missing = [fr.name for fr in frames if fr.mask is None]
                raise UsageError(f"masks for some photos only (none for {', '.join(missing[:4])})")
            (tmp / "masks").mkdir()
        cams = []
        with progress_bar(total=len(frames), desc="import photos", unit="photo", disable=not show_progress) as bar:
            for fr in frames:
                photo = imageio.read_image(fr.image, channels=3, linear=True, what="photo")
                src = _fit_camera_to_photo(fr.camera, (photo.shape[1], photo.shape[0]), fr.image)
                cam, pin = working_camera(fr.name, src, fr.cam_to_world, resolution)
                pin.flash, pin.exposure = flash_fired(fr.image), photo_exposure(fr.image)
                check_camera(pin, str(source.path))
                small = area_resize(photo, cam.width, cam.height)
                img, _ = undistort(small, cam, pin)
                imageio.write_exr(tmp / "images" / f"{fr.name}.exr", {"": img}, half=True)
                if fr.mask is not None:
                    m = imageio.read_image(fr.mask, channels=1, linear=False, what="mask")
                    if m.shape[:2] != photo.shape[:2]:
                        raise UsageError(f"{fr.mask}: mask is {m.shape[1]}×{m.shape[0]}, its photo "
                                         f"{photo.shape[1]}×{photo.shape[0]}")
                    mm, _ = undistort(area_resize(m, cam.width, cam.height), cam, pin)
                    imageio.write_png(tmp / "masks" / f"{fr.name}.png", np.repeat(mm > 0.5, 3, -1).astype(np.float32),
                                      linear=False)
                cams.append(pin)
                bar.update(1)
        train, test = split([c.name for c in cams])
        points = 0
        pts, cols, dirs = source.points, source.colours, source.view_dirs
        masked = (tmp / "masks").is_dir()
        hull = user_mesh is None and (coarse == "hull" or (coarse == "auto" and pts is None and masked))
        if pts is None and user_mesh is None and triangulate and not hull:
            from .sfm import triangulate_known

            pts, cols, dirs = triangulate_known(tmp, cams, show_progress)
        if pts is not None and len(pts):
            points = len(pts)
            write_ply(tmp / "points.ply", pts, np.zeros((0, 3), np.int64),
                      None if cols is None else imageio.srgb_to_linear(cols))
        mesh_name = None
        if hull:
            from .coarse import visual_hull
            from .format import Capture
            from .scores import colour_from_photos

            interim = Capture(tmp, CaptureMeta(cams, train, test, masks=True))
            v, f = visual_hull(cams, {c.name: interim.mask(c.name) for c in cams})
            user_mesh = (v, f, colour_from_photos(interim, v, f))
        if user_mesh is not None:
            v, f, c = user_mesh
            write_ply(tmp / "mesh.ply", v, f, c)
            mesh_name = "mesh.ply"
        elif pts is not None and len(pts) >= 100:
            v, f, c = coarse_mesh_from_points(pts, None if cols is None else imageio.srgb_to_linear(cols),
                                              np.array([c.centre for c in cams]), view_dirs=dirs)
            write_ply(tmp / "mesh.ply", v, f, c)
            mesh_name = "mesh.ply"
        meta = CaptureMeta(cams, train, test, {"format": source.kind, "path": str(source.path), **source.notes,
                                               "seconds": time.perf_counter() - t0},
                           mesh=mesh_name, masks=masked, points=points,
                           sfm=source.notes.get("sfm"))
        write_json(tmp / MARKER, to_json(meta))
    return Path(out)
