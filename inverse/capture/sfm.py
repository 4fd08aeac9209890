"""Structure from motion on the CPU with pycolmap: SIFT features, matching, incremental mapping (photos only), and
triangulation with cameras already known (a capture imported without points or mesh). Measured behaviour and the
mapper options used: docs/capture.md."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation.errors import FailureError, UsageError

from .sources import PHOTO_SUFFIXES, Source, SourceFrame, model_points


@dataclass
class SfmSettings:
    """Settings of `photoreal capture sfm`."""

    max_size: int = 1024  #: longest side the features are found at (pixels; the photos themselves are kept)
    max_features: int = 8192  #: SIFT features per photo
    #: exhaustive matching up to this many photos (its cost grows with the square); sequential beyond
    exhaustive_up_to: int = 80
    #: mapper options that join low-texture captures into one model (a flash-lit skull split into 3 with COLMAP's
    #: defaults: 44 + 20 + 5 photos; one model of 64/66 with these)
    relaxed: bool = True
    #: photos of one size share one camera (one body and lens, as nerfstudio assumes); mixed sizes get one each
    single_camera: bool = True
    #: the lenses' radial distortion: auto keeps it where the reprojection errors need it (Bayesian information
    #: criterion; a distortion the points cannot tell from noise trades against the focal length), on always, off
    #: never (photos already undistorted)
    distortion: str = "auto"
    seed: int = 0

    def __post_init__(self):
        from foundation import validate

        validate.one_of("distortion", self.distortion, ("auto", "on", "off"))
        validate.integer("max_size", self.max_size, 64, 16384)
        validate.integer("max_features", self.max_features, 64)
        validate.integer("exhaustive_up_to", self.exhaustive_up_to, 2)
        validate.seed("seed", self.seed)


def focal_prior(path: Path, width: int) -> float | None:
    """Focal length in pixels at ``width`` from a photo's EXIF: its 35 mm equivalent, else the focal length over the
    sensor width (``FocalPlaneXResolution`` describes the full-resolution sensor even in a downsampled copy, so the
    sensor width comes from it and ``PixelXDimension``, the original width)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
            orig_w = sub.get(0xA002) or im.size[0]
    except (OSError, ValueError):
        return None
    f35, f = sub.get(0xA405), sub.get(0x920A)
    if f35:
        return float(f35) / 36.0 * width
    res, unit = sub.get(0xA20E), sub.get(0xA210, 2)
    if f and res:
        mm = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(unit))
        if mm:
            sensor_mm = float(orig_w) / float(res) * mm
            if 2.0 < sensor_mm < 80.0:
                return float(f) / sensor_mm * width
    return None


def flash_fired(path: Path) -> bool | None:
    """Whether a photo's EXIF ``Flash`` tag (0x9209, bit 0) says the flash fired; None where the file has no such tag
    (PNG, EXR, an edited copy that lost its EXIF)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            tag = im.getexif().get_ifd(0x8769).get(0x9209)
    except (OSError, ValueError):
        return None
    return None if tag is None else bool(int(tag) & 1)


def photo_exposure(path: Path) -> float | None:
    """A photo's exposure from its EXIF: ExposureTime (0x829A, s) × ISO (0x8827) / FNumber (0x829D)², the light a
    sensor gathers from the same radiance, up to the camera's constant; None where a tag is missing or not positive."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            sub = im.getexif().get_ifd(0x8769)
        t, n, iso = (sub.get(k) for k in (0x829A, 0x829D, 0x8827))
        if isinstance(iso, tuple):  # ISOSpeedRatings may hold several values: the first is the one used
            iso = iso[0] if iso else None
        t, n, iso = float(t), float(n), float(iso)
    except (OSError, ValueError, TypeError, ZeroDivisionError):
        return None
    if not (np.isfinite([t, n, iso]).all() and t > 0 and n > 0 and iso > 0):
        return None
    return t * iso / (n * n)


def _prepare_photos(photos: list[Path], folder: Path, max_size: int) -> dict[str, tuple[Path, float, float | None]]:
    """Upright 8-bit copies at most ``max_size`` on their longest side: name → (original, scale, focal prior)."""
    from PIL import Image

    from foundation.imageio import read_image

    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for p in photos:
        img = read_image(p, channels=3, linear=False, what="photo")
        h, w = img.shape[:2]
        s = min(1.0, max_size / max(w, h))
        im = Image.fromarray(np.round(img * 255).astype(np.uint8))
        if s < 1.0:
            im = im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.LANCZOS)
        name = f"{p.stem}.png"
        im.save(folder / name)
        prior = focal_prior(p, im.size[0])
        out[name] = (p, im.size[0] / w, prior)
    return out


def quiet_colmap(verbose: bool = False) -> None:
    """COLMAP logs every step at INFO level to stderr; keep warnings and errors only (unless PHOTOREAL_DEBUG)."""
    import os

    import pycolmap

    if not verbose and os.environ.get("PHOTOREAL_DEBUG", "") in ("", "0"):
        pycolmap.logging.minloglevel = 1
        pycolmap.logging.stderrthreshold = 1


def run_sfm(photos: str | Path, work: str | Path, s: SfmSettings | None = None,
            progress=None) -> Source:
    """Cameras and points of a folder of photos; ``work`` keeps COLMAP's database and model. Returns the
    largest model as a source; its ``notes["sfm"]`` holds the figures (registered/total, models, points,
    reprojection error, seconds per step, the photos left out)."""
    import pycolmap
    from PIL import Image

    s = s or SfmSettings()
    quiet_colmap()
    folder = Path(photos)
    if not folder.is_dir():
        raise UsageError(f"{folder}: no such folder of photos")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.suffix.lower() != ".exr")
    if len(files) < 3:
        raise UsageError(f"{folder}: {len(files)} photos (JPEG/PNG/TIFF); structure from motion needs at least 3")
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda msg: None)
    # Resumable: each finished step is recorded in steps.json under a key of the settings and the photos; a rerun
    # after an interruption skips what is done (the mapping, seconds on the CPU, always runs again).
    from dataclasses import asdict

    from foundation.files import write_json
    from foundation.records import json_digest

    # the distortion is chosen after the mapping: changing it reuses the features and matches
    mapped = {k: v for k, v in asdict(s).items() if k != "distortion"}
    key = json_digest([mapped, [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in files]])
    steps_file = work / "steps.json"
    try:
        steps = json.loads(steps_file.read_text())
        steps = steps if steps.get("key") == key else None
    except (OSError, ValueError):
        steps = None
    steps = steps or {"key": key, "done": [], "seconds": {}}
    seconds: dict[str, float] = steps["seconds"]

    def done(step: str) -> None:
        steps["done"].append(step)
        write_json(steps_file, steps)

    db = work / "database.db"
    if "prepare" in steps["done"]:
        prepared = {n: (Path(o), sc, pr) for n, (o, sc, pr) in steps["prepared"].items()}
        say(f"{len(prepared)} photos prepared before: reusing them")
    else:
        t = time.perf_counter()
        say(f"preparing {len(files)} photos (longest side {s.max_size})")
        prepared = _prepare_photos(files, work / "images", s.max_size)
        seconds["prepare"] = time.perf_counter() - t
        steps["prepared"] = {n: [str(o), sc, pr] for n, (o, sc, pr) in prepared.items()}
        done("prepare")
    pycolmap.set_random_seed(s.seed)
    sizes = {Image.open(work / "images" / n).size for n in prepared}
    single = s.single_camera and len(sizes) == 1
    if "features" not in steps["done"]:
        db.unlink(missing_ok=True)
        t = time.perf_counter()
        say("SIFT features")
        ex = pycolmap.FeatureExtractionOptions()
        ex.max_image_size = s.max_size
        ex.sift.max_num_features = s.max_features
        ex.num_threads = -1
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        mode = pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE
        pycolmap.extract_features(db, work / "images", camera_mode=mode, reader_options=reader,
                                  extraction_options=ex, device=pycolmap.Device.cpu)
        _set_focal_priors(db, prepared)
        seconds["features"] = time.perf_counter() - t
        done("features")
    exhaustive = len(files) <= s.exhaustive_up_to
    if "matching" not in steps["done"]:
        t = time.perf_counter()
        say(f"matching ({'exhaustive' if exhaustive else 'sequential'})")
        if exhaustive:
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
        seconds["matching"] = time.perf_counter() - t
        done("matching")
    t = time.perf_counter()
    say("incremental mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    if s.relaxed:
        opts.min_num_matches = 10
        opts.mapper.init_min_num_inliers = 50
        opts.mapper.abs_pose_min_num_inliers = 15
        opts.mapper.abs_pose_min_inlier_ratio = 0.1
        opts.triangulation.ignore_two_view_tracks = False
    shutil.rmtree(work / "sparse", ignore_errors=True)
    (work / "sparse").mkdir()
    models = pycolmap.incremental_mapping(db, work / "images", work / "sparse", options=opts)
    seconds["mapping"] = time.perf_counter() - t
    if not models:
        raise FailureError(f"{folder}: no two photos could be registered (too little texture or overlap)")
    best_id = max(models, key=lambda k: models[k].num_reg_images())
    rec = models[best_id]
    if s.distortion != "on":
        say("lens distortion: kept only where the points need it" if s.distortion == "auto" else
            "lens distortion: off")
        rec, chosen = choose_distortion(rec, force_off=s.distortion == "off")
        rec.write(work / "sparse" / str(best_id))  # the model on disk is the one returned
    else:
        chosen = {"kept": True, "chosen_by": "on"}
    frames = []
    registered = set()
    for _, im in sorted(rec.images.items()):
        if not im.has_pose:
            continue
        orig, scale, _ = prepared[im.name]
        cam = rec.cameras[im.camera_id]
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()
        full = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params)
        full.rescale(round(cam.width / scale), round(cam.height / scale))
        frames.append(SourceFrame(orig.stem, orig, full, np.linalg.inv(w2c)))
        registered.add(im.name)
    pts, cols, dirs = model_points(rec)
    left = sorted(prepared[n][0].name for n in prepared if n not in registered)
    figures = {"photos": len(files), "registered": len(frames), "models": len(models),
               "model_sizes": sorted((m.num_reg_images() for m in models.values()), reverse=True),
               "points": int(len(pts)), "reprojection_px": float(rec.compute_mean_reprojection_error()),
               "mean_track_length": float(rec.compute_mean_track_length()),
               "matching": "exhaustive" if exhaustive else "sequential", "max_size": s.max_size,
               "cameras": "single" if single else "per photo", "distortion": chosen,
               "seconds": {k: round(v, 2) for k, v in seconds.items()}, "unregistered": left}
    return Source("sfm", folder, frames, pts, cols, {"sfm": figures}, view_dirs=dirs)


def squared_reprojection_errors(rec) -> np.ndarray:
    """Every observation's squared reprojection error in pixels² (one per 2D point with a 3D point)."""
    out = []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        xyz = np.array([rec.points3D[o[1]].xyz for o in obs])
        m = im.cam_from_world().matrix()
        uv = np.asarray(rec.cameras[im.camera_id].img_from_cam(xyz @ m[:, :3].T + m[:, 3]))
        out.append(np.sum((uv - xy) ** 2, axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def choose_distortion(rec, force_off: bool = False):
    """The reconstruction with or without its cameras' distortion parameters, by the Bayesian information criterion.

    A copy with every distortion parameter at zero is refitted (global bundle adjustment, focal lengths, poses and
    points free); with n residuals (two per observation), RSS₁ / RSS₀ the squared reprojection errors with and
    without distortion and p distortion parameters, the distortion stays only if n·ln(RSS₀/RSS₁) > p·ln n. A
    radial term the points cannot tell from noise trades against the focal length (on an orbit of pinhole renders it
    took the focal length further from the truth). Returns the reconstruction chosen and its figures.
    ``force_off``: the refit without distortion, whatever the criterion says."""
    import pycolmap

    extra = sum(len(c.extra_params_idxs()) for c in rec.cameras.values())
    if extra == 0:
        return rec, {"kept": False, "chosen_by": "the camera model has none"}

    def adjust(r, free: bool):
        o = pycolmap.BundleAdjustmentOptions()
        o.refine_extra_params = free
        o.print_summary = False
        pycolmap.bundle_adjustment(r, o)
        return squared_reprojection_errors(r)

    e1 = adjust(rec, True)
    plain = pycolmap.Reconstruction(rec)
    for c in plain.cameras.values():
        p = np.array(c.params)
        p[c.extra_params_idxs()] = 0.0
        c.params = p
    e0 = adjust(plain, False)
    n = 2 * len(e1)
    gain = float(n * np.log(max(e0.sum(), 1e-12) / max(e1.sum(), 1e-12)))
    penalty = float(extra * np.log(max(n, 2)))
    keep = gain > penalty and not force_off
    figures = {"kept": bool(keep), "chosen_by": "off" if force_off else "BIC", "fit_gain": round(gain, 2),
               "penalty": round(penalty, 2), "reprojection_rms_px_with": float(np.sqrt(e1.mean())),
               "reprojection_rms_px_without": float(np.sqrt(e0.mean()))}
    return (rec if keep else plain), figures


def _set_focal_priors(db: Path, prepared: dict) -> None:
    """Focal lengths from EXIF, in pixels of the copies (COLMAP's own prior reads the focal-plane resolution of the
    full-size sensor and comes out several times too long for a downsampled photo)."""
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        images = {im.name: im for im in database.read_all_images()}
        for name, (_, _, prior) in prepared.items():
            if prior is None or name not in images:
                continue
            cam = database.read_camera(images[name].camera_id)
            params = np.array(cam.params)
            params[0] = prior
            cam.params = params
            cam.has_prior_focal_length = True
            database.update_camera(cam)
    finally:
        database.close()


def triangulate_known(capture_dir: Path, cams: list,
                      show_progress: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3), colours (N, 3, sRGB) and view directions (N, 3, :func:`model_points`) triangulated from a
    capture's own photos and pinhole cameras (known poses: features, exhaustive matching, triangulation; nothing is
    re-estimated)."""
    import tempfile

    import pycolmap
    from PIL import Image

    from foundation import imageio

    quiet_colmap()
    with tempfile.TemporaryDirectory(prefix="photoreal-triangulate-") as tmp:
        tmp = Path(tmp)
        (tmp / "images").mkdir()
        for c in cams:
            img = imageio.exr_layer(imageio.read_exr(capture_dir / "images" / f"{c.name}.exr"), "")[..., :3]
            Image.fromarray(imageio.to_uint8_srgb(img)).save(tmp / "images" / f"{c.name}.png")
        db = tmp / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        pycolmap.extract_features(db, tmp / "images", camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        by_name = {f"{c.name}.png": c for c in cams}
        database = pycolmap.Database.open(str(db))
        try:
            images = database.read_all_images()
            rec = pycolmap.Reconstruction()
            for im in images:
                c = by_name[im.name]
                cam = database.read_camera(im.camera_id)
                cam.params = np.array([c.f, c.f, c.cx, c.cy])
                rec.add_camera_with_trivial_rig(cam)
                w2c = np.linalg.inv(c.matrix)
                rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=im.camera_id,
                                                                image_id=im.image_id),
                                                 pycolmap.Rigid3d(w2c[:3]))
        finally:
            database.close()
        (tmp / "tri").mkdir()
        opts = pycolmap.IncrementalPipelineOptions()
        opts.triangulation.ignore_two_view_tracks = False  # a point two photos agree on is a point (few photos)
        rec = pycolmap.triangulate_points(rec, db, tmp / "images", tmp / "tri", options=opts)
    return model_points(rec)
