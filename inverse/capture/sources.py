"""Readers of what photogrammetry and NeRF tools write: a COLMAP sparse model (text or binary, through pycolmap), a
nerfstudio / instant-ngp ``transforms.json`` and an LLFF ``poses_bounds.npy``. Each gives a :class:`Source`: the
photos with their cameras as the tool left them (any COLMAP camera model, distortion included) and poses in COLMAP
axes; :func:`inverse.capture.build.import_capture` turns it into a capture. Every error names the file."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foundation.errors import UsageError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".exr")
#: COLMAP's camera from OpenGL's (nerfstudio, instant-ngp, Blender): y and z flipped
COLMAP_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class SourceFrame:
    name: str  #: unique name of the photo in the capture (its file stem)
    image: Path
    camera: object  #: a ``pycolmap.Camera`` at ``camera.width × camera.height`` (its distortion included)
    cam_to_world: np.ndarray  #: 4×4, COLMAP axes
    mask: Path | None = None


@dataclass
class Source:
    kind: str  #: "colmap", "transforms", "llff", "sfm"
    path: Path
    frames: list[SourceFrame]
    points: np.ndarray | None = None  #: (N, 3) triangulated points, if the tool left some
    colours: np.ndarray | None = None  #: (N, 3) their colours in [0, 1] (sRGB, as photographed)
    notes: dict = field(default_factory=dict)
    #: (N, 3) each point's mean unit direction toward the cameras that observed it (its track), where the tool kept
    #: tracks: which side of the surface a point was seen from
    view_dirs: np.ndarray | None = None


def camera(model: str, width: int, height: int, params, where: str):
    """A pycolmap camera; an unknown model or a wrong parameter count is named."""
    import pycolmap

    try:
        cam = pycolmap.Camera(model=model, width=int(width), height=int(height), params=[float(x) for x in params])
    except Exception as exc:  # pycolmap's ValueError/TypeError for a model it does not know
        raise UsageError(f"{where}: camera model {model} with {len(params)} parameters: {exc}") from None
    if not cam.verify_params() or not np.isfinite(cam.params).all():
        raise UsageError(f"{where}: camera {model} {width}×{height} with parameters {list(params)}: not usable")
    return cam


def _check_pose(m: np.ndarray, where: str) -> np.ndarray:
    m = np.asarray(m, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise UsageError(f"{where}: pose has NaN/Inf values or is not 4×4")
    r = m[:3, :3]
    scale = np.cbrt(abs(np.linalg.det(r)))
    if not scale > 1e-9 or np.abs((r / scale) @ (r / scale).T - np.eye(3)).max() > 1e-3:
        raise UsageError(f"{where}: pose's rotation is not a rotation")
    if abs(scale - 1.0) > 1e-3:  # some tools store scaled rotations: keep the rotation, drop the scale
        m = m.copy()
        m[:3, :3] = r / scale
    return m


def _photo(folder: Path, name: str, where: str) -> Path:
    p = folder / name
    if p.is_file():
        return p
    if not p.suffix:  # NeRF datasets often omit the extension
        for s in PHOTO_SUFFIXES:
            if p.with_suffix(s).is_file():
                return p.with_suffix(s)
    raise UsageError(f"{p}: photo missing ({where} lists it)")


def _mask_for(masks: Path | None, name: str) -> Path | None:
    if masks is None:
        return None
    stem = Path(name).stem
    for cand in (masks / name, masks / f"{stem}.png", masks / f"{name}.png", masks / f"{stem}.jpg"):
        if cand.is_file():
            return cand
    raise UsageError(f"{masks}: no mask for photo {name} (looked for {stem}.png)")


def _unique_names(frames: list[SourceFrame], where: Path) -> list[SourceFrame]:
    seen: dict[str, str] = {}
    for fr in frames:
        if fr.name in seen:
            raise UsageError(f"{where}: two photos would share the name {fr.name!r} ({seen[fr.name]}, {fr.image})")
        seen[fr.name] = str(fr.image)
    return frames


# -- COLMAP ---------------------------------------------------------------------------------------------------------


def find_colmap_model(path: Path) -> Path:
    """The folder of a sparse model: PATH itself, PATH/sparse/0, PATH/sparse or PATH/0."""
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "0", path / "colmap" / "sparse" / "0"):
        if any((cand / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return cand
    raise UsageError(f"{path}: no COLMAP model (cameras.bin or cameras.txt) here or in sparse/0")


def read_colmap(path: str | Path, images: str | Path | None = None, masks: str | Path | None = None) -> Source:
    """A COLMAP sparse model (text or binary) and its photos (``images`` default: the model's ``images/`` beside
    ``sparse/``, or beside the model)."""
    import pycolmap

    path = Path(path)
    model = find_colmap_model(path)
    for name in ("cameras", "images"):
        if not any((model / f"{name}.{e}").is_file() for e in ("bin", "txt")):
            raise UsageError(f"{model}: COLMAP model without {name}.bin / {name}.txt")
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as exc:  # pycolmap raises a bare RuntimeError/ValueError with COLMAP's check message
        msg = " ".join(str(exc).split())[:200]
        raise UsageError(f"{model}: not a readable COLMAP model ({msg})") from None
    if images is None:
        cands = [path / "images", model.parent / "images", model.parent.parent / "images", model / "images"]
        images = next((c for c in cands if c.is_dir()), None)
        if images is None:
            raise UsageError(f"{path}: no images/ folder beside the model; give --images")
    images, masks = Path(images), (Path(masks) if masks else None)
    frames = []
    for _, im in sorted(rec.images.items()):
        if not im.has_pose:
            continue
        where = f"{model} image {im.name!r}"
        if im.camera_id not in rec.cameras:
            raise UsageError(f"{model}: image {im.name!r} names camera {im.camera_id}, which cameras lists not")
        c = rec.cameras[im.camera_id]
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        if not np.isfinite(w2c).all():
            raise UsageError(f"{where}: pose has NaN/Inf values")
        frames.append(SourceFrame(Path(im.name).stem, _photo(images, im.name, str(model)),
                                  camera(c.model.name, c.width, c.height, c.params, where),
                                  _check_pose(np.linalg.inv(w2c), where), _mask_for(masks, im.name)))
    if len(frames) < 2:
        raise UsageError(f"{model}: {len(frames)} registered image(s); a capture needs at least 2")
    pts, cols, dirs = model_points(rec)
    return Source("colmap", model, _unique_names(frames, model), pts if len(pts) else None,
                  cols if len(pts) else None, {"cameras": len(rec.cameras), "images": len(rec.images)},
                  view_dirs=dirs if len(pts) else None)


def model_points(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pycolmap reconstruction's points (N, 3), colours (N, 3, sRGB in [0, 1]) and view directions (N, 3): the
    mean of the unit vectors from each point to the centres of the photos in its track (zero for an empty track)."""
    centres = {i: np.asarray(im.projection_center(), np.float64) for i, im in rec.images.items() if im.has_pose}
    n = len(rec.points3D)
    pts, cols, dirs = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    for k, p in enumerate(rec.points3D.values()):
        pts[k], cols[k] = p.xyz, np.asarray(p.color, np.float64) / 255.0
        c = [centres[e.image_id] for e in p.track.elements if e.image_id in centres]
        if c:
            d = np.asarray(c) - pts[k]
            dirs[k] = (d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)).mean(0)
    return pts, cols, dirs


# -- transforms.json (nerfstudio, instant-ngp) ----------------------------------------------------------------------

_DIST = ("k1", "k2", "k3", "k4", "p1", "p2")


def _intrinsics(d: dict, base: dict, w: int, h: int, where: str) -> tuple[str, list[float]]:
    """(COLMAP model, parameters) of a transforms.json frame (its own keys over the file's)."""
    g = {**base, **{k: v for k, v in d.items() if k in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x",
                                                         "camera_angle_y", "camera_model", *_DIST)}}
    if not any(k in g for k in ("fl_x", "fl_y", "camera_angle_x")):
        raise UsageError(f"{where}: no intrinsics (fl_x/fl_y or camera_angle_x, for the file or the frame)")
    try:
        if "fl_x" in g or "fl_y" in g:
            fx = float(g.get("fl_x", g.get("fl_y")))
            fy = float(g.get("fl_y", fx))
        else:
            fx = 0.5 * w / math.tan(0.5 * float(g["camera_angle_x"]))
            fy = 0.5 * h / math.tan(0.5 * float(g["camera_angle_y"])) if "camera_angle_y" in g else fx
        cx, cy = float(g.get("cx", w / 2)), float(g.get("cy", h / 2))
        k = {n: float(g.get(n, 0.0)) for n in _DIST}
    except (TypeError, ValueError):
        raise UsageError(f"{where}: intrinsics are not numbers") from None
    model = str(g.get("camera_model", "OPENCV")).upper()
    if model == "OPENCV_FISHEYE":
        return model, [fx, fy, cx, cy, k["k1"], k["k2"], k["k3"], k["k4"]]
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE"):
        raise UsageError(f"{where}: camera_model {model!r}: OPENCV, OPENCV_FISHEYE or PINHOLE expected")
    if k["k3"] or k["k4"]:
        return "FULL_OPENCV", [fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], k["k4"], 0.0, 0.0]
    if any(k[n] for n in ("k1", "k2", "p1", "p2")):
        return "OPENCV", [fx, fy, cx, cy, k["k1"], k["k2"], k["p1"], k["p2"]]
    return "PINHOLE", [fx, fy, cx, cy]


def read_transforms(path: str | Path, masks: str | Path | None = None) -> Source:
    """A ``transforms.json`` (a file, or the folder holding it); frame paths are relative to its folder."""
    from foundation.files import read_json

    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    data = read_json(path, "transforms.json")
    frames_in = data.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise UsageError(f"{path}: no frames")
    base = {k: v for k, v in data.items() if k != "frames"}
    masks = Path(masks) if masks else None
    frames = []
    for k, fr in enumerate(frames_in):
        where = f"{path} frame {k}"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise UsageError(f"{where}: needs file_path and transform_matrix")
        img = _photo(path.parent, str(fr["file_path"]), str(path))
        w, h = fr.get("w", base.get("w")), fr.get("h", base.get("h"))
        if w is None or h is None:
            from PIL import Image

            try:
                with Image.open(img) as im:
                    w, h = im.size
            except OSError:
                raise UsageError(f"{img}: not a readable photo") from None
        model, params = _intrinsics(fr, base, int(w), int(h), where)
        try:
            gl = np.asarray(fr["transform_matrix"], np.float64)
        except (TypeError, ValueError):
            raise UsageError(f"{where}: transform_matrix is not a 4×4 matrix of numbers") from None
        if gl.shape == (3, 4):
            gl = np.vstack([gl, [0, 0, 0, 1]])
        c2w = _check_pose(gl, where) @ COLMAP_FROM_OPENGL
        mask = None
        if "mask_path" in fr:
            mask = path.parent / str(fr["mask_path"])
            if not mask.is_file():
                raise UsageError(f"{mask}: mask missing ({where} lists it)")
        elif masks is not None:
            mask = _mask_for(masks, img.name)
        frames.append(SourceFrame(img.stem, img, camera(model, w, h, params, where), c2w, mask))
    pts = cols = None
    ply = data.get("ply_file_path")
    if ply and (path.parent / ply).is_file():  # nerfstudio's COLMAP points, if it kept them
        from foundation.mesh import read_ply

        v, _, c = read_ply(path.parent / ply)
        pts, cols = v.astype(np.float64), c  # in the frame of the poses (nerfstudio writes both so)
    return Source("transforms", path, _unique_names(frames, path), pts, cols)


# -- LLFF -----------------------------------------------------------------------------------------------------------


def read_llff(path: str | Path, masks: str | Path | None = None) -> Source:
    """An LLFF folder: ``poses_bounds.npy`` (N × 17: a 3×5 [R | t | hwf] per photo, rotation columns in LLFF's
    [down, right, backwards] order, then near/far bounds) and ``images/`` (or ``images_N/``) with N photos in name
    order. Photos smaller than the pose file's h, w scale the focal length with them, as LLFF loaders do."""
    path = Path(path)
    pb = path / "poses_bounds.npy" if path.is_dir() else path
    root = pb.parent
    if not pb.is_file():
        raise UsageError(f"{pb}: no such file (an LLFF capture has poses_bounds.npy)")
    try:
        arr = np.load(pb, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UsageError(f"{pb}: not a readable .npy file ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise UsageError(f"{pb}: expected N × 17 values (3×5 pose + 2 bounds per photo), got {arr.shape}")
    folders = [root / "images"] + sorted(root.glob("images_*"), key=lambda p: int(p.name[7:]) if p.name[7:].isdigit()
                                         else 1 << 30)
    folder = next((f for f in folders if f.is_dir()), None)
    if folder is None:
        raise UsageError(f"{root}: no images/ or images_N/ folder")
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if len(photos) != len(arr):
        raise UsageError(f"{pb}: {len(arr)} poses for {len(photos)} photos in {folder} (one pose per photo, in name "
                         "order)")
    masks = Path(masks) if masks else (root / "masks" if (root / "masks").is_dir() else None)
    from PIL import Image

    frames = []
    for k, (row, img) in enumerate(zip(arr, photos)):
        where = f"{pb} row {k} ({img.name})"
        if not np.isfinite(row).all():
            raise UsageError(f"{where}: NaN/Inf in the pose")
        m = row[:15].reshape(3, 5)
        h, w, f = m[:, 4]
        down, right, back = m[:, 0], m[:, 1], m[:, 2]
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, down, -back], 1)  # COLMAP: x right, y down, z forward
        c2w[:3, 3] = m[:, 3]
        c2w = _check_pose(c2w, where)
        try:
            with Image.open(img) as im:
                pw, ph = im.size
        except OSError:
            raise UsageError(f"{img}: not a readable photo") from None
        s = pw / w
        if abs(ph - h * s) > 1.0:
            raise UsageError(f"{where}: photo is {pw}×{ph}, the pose file says {w:g}×{h:g} (not a scaled copy)")
        frames.append(SourceFrame(img.stem, img, camera("SIMPLE_PINHOLE", pw, ph, [f * s, pw / 2, ph / 2], where),
                                  c2w, _mask_for(masks, img.name)))
    return Source("llff", pb, _unique_names(frames, pb), notes={"bounds": arr[:, 15:].tolist()})


def read_source(path: str | Path, images: str | Path | None = None, masks: str | Path | None = None) -> Source:
    """Whichever of the three ``path`` is (a transforms.json, an LLFF folder, a COLMAP model or its project)."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such file or folder")
    if path.suffix == ".json" or (path.is_dir() and (path / "transforms.json").is_file()):
        return read_transforms(path, masks)
    if path.name == "poses_bounds.npy" or (path.is_dir() and (path / "poses_bounds.npy").is_file()):
        return read_llff(path, masks)
    if path.is_dir():
        return read_colmap(path, images, masks)
    raise UsageError(f"{path}: not a COLMAP model, transforms.json or LLFF poses_bounds.npy")
