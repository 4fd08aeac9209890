"""A capture written back in the formats other tools read: a COLMAP model (text or binary, PINHOLE cameras), a
nerfstudio ``transforms.json`` (OpenGL axes), an LLFF ``poses_bounds.npy``; photos as 8-bit sRGB PNG. Importing
an export gives the same cameras (tests/capture: within 1e-6)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from foundation.errors import UsageError

from .format import Capture
from .sources import COLMAP_FROM_OPENGL

FORMATS = ("colmap", "colmap-text", "transforms", "llff")


def _photos(cap: Capture, folder: Path) -> None:
    from foundation import imageio

    folder.mkdir(parents=True, exist_ok=True)
    for c in cap.meta.cameras:
        imageio.write_png(folder / f"{c.name}.png", cap.photo(c.name))
        m = cap.mask(c.name)
        if m is not None:
            (folder.parent / "masks").mkdir(exist_ok=True)
            imageio.write_png(folder.parent / "masks" / f"{c.name}.png", np.repeat(m[..., None], 3, -1)
                              .astype(np.float32), linear=False)


def export_capture(cap: Capture, out: str | Path, fmt: str) -> Path:
    """Write ``cap`` to the new folder ``out`` in ``fmt`` (one of :data:`FORMATS`)."""
    from foundation.files import atomic_dir, write_text

    if fmt not in FORMATS:
        raise UsageError(f"format {fmt!r}: one of {', '.join(FORMATS)}")
    with atomic_dir(out, None) as tmp:
        _photos(cap, tmp / "images")
        cams = cap.meta.cameras
        if fmt.startswith("colmap"):
            import pycolmap

            rec = pycolmap.Reconstruction()
            for k, c in enumerate(cams, start=1):
                rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=c.width, height=c.height,
                                                                params=[c.f, c.f, c.cx, c.cy], camera_id=k))
                w2c = np.linalg.inv(c.matrix)
                rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{c.name}.png", camera_id=k, image_id=k),
                                                 pycolmap.Rigid3d(w2c[:3]))
            (tmp / "sparse" / "0").mkdir(parents=True)
            (rec.write_text if fmt == "colmap-text" else rec.write_binary)(str(tmp / "sparse" / "0"))
        elif fmt == "transforms":
            frames = [{"file_path": f"images/{c.name}.png", "fl_x": c.f, "fl_y": c.f, "cx": c.cx, "cy": c.cy,
                       "w": c.width, "h": c.height,
                       "transform_matrix": (c.matrix @ np.linalg.inv(COLMAP_FROM_OPENGL)).tolist(),
                       **({"mask_path": f"masks/{c.name}.png"} if cap.meta.masks else {})} for c in cams]
            write_text(tmp / "transforms.json", json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=2))
        else:
            if len({(c.width, c.height, c.f) for c in cams}) != 1 or any(
                    abs(c.cx - c.width / 2) > 1e-9 or abs(c.cy - c.height / 2) > 1e-9 for c in cams):
                raise UsageError("LLFF holds one focal length and a centred principal point for all photos: this "
                                 "capture's cameras differ")
            rows = []
            for c in cams:
                m = c.matrix
                right, down, fwd = m[:3, 0], m[:3, 1], m[:3, 2]
                pose = np.stack([down, right, -fwd, m[:3, 3], [c.height, c.width, c.f]], 1)
                rows.append(np.concatenate([pose.ravel(), [0.1, 100.0]]))
            np.save(tmp / "poses_bounds.npy", np.array(rows))
    return Path(out)
