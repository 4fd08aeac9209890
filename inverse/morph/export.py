"""A morph run's mesh as a model other tools open: UV atlas (xatlas), a base-colour texture baked from the photos
through the run's fitted cameras with visibility (the photogrammetry texturing step) or from its vertex colours, the
vertex colours as ``COLOR_0``; and how each texture scores on the held-out photos (PSNR, ꟻLIP)."""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation import imageio
from foundation.errors import UsageError
from foundation.export import (ExportMaterial, ExportMesh, ExportSettings, mitsuba_mesh, reimport_check,
                               rotation_to_y_up, scatter, similarity, texel_surface, unwrap, write_model)
from foundation.mesh import read_ply
from foundation.scene import mitsuba_log_level

from .batch import load_result
from .results import MorphResult

TEXTURES = ("photos", "colours")


@dataclass
class MorphExport:
    """``export.json`` of a morph result."""

    kind: str  #: "morph"
    run: str
    input: str | None  #: the capture or benchmark whose photos were read (None: not found)
    format: str
    files: list[str]
    texture: str  #: the base-colour texture written ('photos' or 'colours')
    frame: str  #: the axes and units written
    vertices: int  #: of the result
    exported_vertices: int  #: after the UV seams are split
    texture_size: int
    photo_coverage: float | None  #: share of the atlas texels at least one fitted photo sees (photos texture)
    #: held-out photos: per texture ('vertex_colours' the result's own render, 'colours', 'photos'), mean PSNR, ꟻLIP
    heldout: dict = field(default_factory=dict)
    heldout_views: list[str] = field(default_factory=list)
    reimport: dict = field(default_factory=dict)  #: :func:`foundation.export.reimport_check`
    #: where the photos were taken from, seen from the model (glTF frame): azimuth about +Y from +Z towards +X and
    #: polar angle from +Y, degrees — a viewer's first camera (model-viewer's ``camera-orbit``); None: not a capture
    view_orbit_deg: list | None = None
    seconds: float = 0.0


def find_input(run: Path, given: str | Path | None) -> Path | None:
    """The capture or benchmark a run morphed: ``given``, else the folder holding the run (``morph run``'s default
    ``BENCHMARK/morph``) when it is one."""
    from inverse.capture import MARKER as CAPTURE_MARKER

    from .benchmark import MARKER

    for p in ([Path(given)] if given is not None else [run.parent]):
        if (p / CAPTURE_MARKER).is_file() or (p / MARKER).is_file():
            return p
        if given is not None:
            raise UsageError(f"--input {p}: neither a capture ({CAPTURE_MARKER}) nor a morph benchmark ({MARKER})")
    return None


def load_run(run: str | Path) -> tuple[MorphResult, np.ndarray, np.ndarray, np.ndarray]:
    """A finished run's result and its mesh (v, f, linear vertex colours)."""
    run = Path(run)
    for name in ("metrics.json", "morphed.ply"):
        if not (run / name).is_file():
            raise UsageError(f"{run}: not a finished morph run (no {name})")
    v, f, c = read_ply(run / "morphed.ply")
    if c is None:
        raise UsageError(f"{run / 'morphed.ply'}: the mesh has no vertex colours")
    return load_result(str(run / "metrics.json")), v, f, c


def fitted_cameras(bench, result: MorphResult) -> tuple[list, dict[int, np.ndarray]]:
    """The capture's cameras with the run's refinements applied and every photo's RGB gain (1 where not fitted)."""
    from .photo_model import moved_cameras

    cams = list(bench.meta.cameras)
    fit = result.photo_fit
    if fit is not None and fit.refined_cameras and fit.camera_rotation is not None:
        cams = moved_cameras(cams, fit.train_views, np.asarray(fit.camera_rotation), np.asarray(fit.camera_shift),
                             fit.focal_scale or 1.0)
    gains = {int(k): np.asarray(g, np.float64) for k, g in ((fit.gains or {}) if fit else {}).items()}
    return cams, {i: gains.get(i, np.ones(3)) for i in range(len(cams))}


def capture_frame(cameras: list, v: np.ndarray) -> tuple[np.ndarray, str]:
    """glTF frame of a capture: up is the cameras' mean up (COLMAP's −y axis), the mesh's bounding-box centre at the
    origin; structure from motion has no metric scale, so its units stay."""
    up = -np.mean([np.asarray(c.matrix)[:3, 1] for c in cameras], axis=0)
    r = rotation_to_y_up(up)
    vr = v @ r.T
    frame = similarity(r, 1.0)
    frame[:3, 3] = -(vr.min(0) + vr.max(0)) / 2  # the upright mesh's bounding box centred
    return (frame,
            "+Y up = the cameras' mean up, origin at the upright mesh's bounding-box centre, units of the capture "
            "(structure from motion: no metric scale)")


def photo_orbit(cameras: list, frame: np.ndarray) -> list[float]:
    """The mean direction from the model to the cameras in the glTF frame, as (azimuth, polar) degrees."""
    c = np.array([frame[:3, :3] @ np.asarray(cam.centre) + frame[:3, 3] for cam in cameras]).mean(0)
    d = c / max(float(np.linalg.norm(c)), 1e-12)
    return [float(np.degrees(np.arctan2(d[0], d[2]))), float(np.degrees(np.arccos(np.clip(d[1], -1, 1))))]


def export_morph(run: str | Path, out: str | Path, s: ExportSettings | None = None, input_path: str | Path | None = None,
                 stem: str = "model") -> MorphExport:
    """Write the run's mesh as ``out/stem.{glb,gltf,obj}`` with ``out/export.json`` (:class:`MorphExport`); the folder
    appears complete or not at all."""
    from foundation.files import atomic_dir, write_json
    from foundation.records import to_json

    from .capture_input import is_capture, load_morph_input

    s = s or ExportSettings()
    t0 = time.perf_counter()
    run = Path(run)
    result, v, f, c = load_run(run)
    src = find_input(run, input_path)
    if s.texture == "photos" and src is None:
        raise UsageError(f"{run}: the photos texture needs the capture or benchmark the run morphed (give --input, or "
                         "--texture colours)")
    if src is None:
        import sys

        print(f"export: {run}: no capture or benchmark beside the run: the vertex colours' texture, no held-out "
              "scores (--input CAPTURE bakes from its photos)", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="photoreal-export-") as work, atomic_dir(out, "export.json") as tmp:
        bench = load_morph_input(src, Path(work) / "input") if src is not None else None
        capture = bench is not None and is_capture(bench)
        if s.texture == "photos" and not capture:
            raise UsageError(f"{src}: the photos texture is baked through a capture's cameras; this is a synthetic "
                             "benchmark (use --texture colours)")
        # auto: a capture's photos where the run ended unlit (radiance, as photogrammetry textures); a lit run's
        # vertex colours are the albedo under its fitted light, which the photos' texture would bake in twice
        lit = (result.photo_fit.mode if result.photo_fit is not None else result.settings.mode) == "lit"
        texture = s.texture if s.texture != "auto" else ("photos" if capture and not lit else "colours")
        atlas = unwrap(v, f, s.texture_size, s.padding)
        vv, ff, uv = v[atlas.vertex_of], atlas.faces, atlas.uvs
        surf = texel_surface(vv, ff, uv, atlas.width, atlas.height, {"colour": c[atlas.vertex_of]})
        textures = {"colours": scatter(surf.mask, surf.attributes["colour"])}
        coverage = None
        cams, gains = fitted_cameras(bench, result) if bench is not None else (None, None)
        if capture:
            textures["photos"], coverage = bake_photos(bench, result, cams, gains, v, f, surf)
            frame, what = capture_frame(bench.meta.cameras, v)
            orbit = photo_orbit(bench.meta.cameras, frame)
        else:
            orbit = None
            frame, what = np.eye(4), "+Y up and the units of the benchmark's scene (Mitsuba's frame)"
        mesh = ExportMesh(vv, ff, uv, c[atlas.vertex_of], to_gltf=frame)
        material = ExportMaterial(name="morphed", base_colour=textures[texture], roughness_factor=1.0,
                                  metallic_factor=0.0, double_sided=True)
        files = write_model(tmp, stem, s.format, mesh, material)
        check = reimport_check(files[0], mesh, material, spp=s.spp)
        heldout, views = ({}, [])
        if bench is not None and bench.meta.test:
            heldout, views = score_textures(bench, result, run, (vv, ff, uv), c[atlas.vertex_of], textures, gains, s)
        rec = MorphExport(kind="morph", run=str(run), input=str(src) if src else None, format=s.format,
                          files=sorted(p.name for p in files), texture=texture, frame=what, vertices=int(len(v)),
                          exported_vertices=int(len(vv)), texture_size=atlas.width, photo_coverage=coverage,
                          heldout=heldout, heldout_views=views, reimport=check, view_orbit_deg=orbit, seconds=time.perf_counter() - t0)
        write_json(tmp / "export.json", to_json(rec))
    return rec


def bake_photos(bench, result: MorphResult, cams: list, gains: dict, v, f, surf) -> tuple[np.ndarray, float]:
    """The base colour at every covered texel from the fitted photos (their gains divided out); texels no photo sees
    keep the vertex colours' value. Returns the texture and the share of texels seen."""
    from inverse.capture import project_photos

    fit = result.photo_fit
    ids = list(fit.train_views) if fit is not None else list(bench.meta.train)
    acc, wsum = project_photos(v, f, surf.position, surf.normal, [cams[i] for i in ids],
                               [bench.photo(i) for i in ids], [gains[i] for i in ids])
    vals = surf.attributes["colour"].astype(np.float64).copy()
    seen = wsum > 0
    vals[seen] = acc[seen] / wsum[seen, None]
    return scatter(surf.mask, np.clip(vals, 0, None).astype(np.float32)), float(seen.mean())


def _quantised(tex: np.ndarray) -> np.ndarray:
    """The texture as the file stores it: 8-bit sRGB, read back linear."""
    return imageio.srgb_to_linear(imageio.to_uint8_srgb(tex).astype(np.float32) / 255.0)


def score_textures(bench, result: MorphResult, run: Path, mesh: tuple, colours: np.ndarray, textures: dict,
                   gains: dict, s: ExportSettings) -> tuple[dict, list[str]]:
    """Renders at the held-out cameras (as imported: the photos no step fitted) of the result with its vertex colours
    and with each texture, under the run's fitted environment and with each photo's gain, against the photos; mean
    PSNR and ꟻLIP over the held-out photos. Unlit results: the colour is emitted; lit: diffuse under the environment
    (the 'photos' texture holds radiance, light baked in: always emitted); a lit run's fitted flash lights the photos
    it lit."""
    from foundation.assets import envmap
    from foundation.metrics import image_metrics

    from .benchmark import sensor_dict
    from .photo_model import fitted_envmap
    from .scene import FLASH, camera_centre, flash_distance, flash_emitter, flash_sampling_weight, photo_at, set_flash

    fit = result.photo_fit
    env_values = None
    if fit is not None and fit.environment:
        env_values = imageio.exr_layer(imageio.read_exr(run / fit.environment), "")[..., :3]
        env = fitted_envmap(env_values)
    else:
        env = envmap(bench.meta.hdri)
    mode = fit.mode if fit is not None else result.settings.mode  # the mode the run ended in (its selection's)
    vv, ff, uv = mesh
    with tempfile.TemporaryDirectory(prefix="photoreal-export-score-") as work:
        ply = Path(work) / "mesh.ply"
        mitsuba_mesh(vv, ff, uv, attributes={"color": colours}).write_ply(str(ply))
        looks = {"vertex_colours": ({"type": "mesh_attribute", "name": "vertex_color"}, mode)}
        for name, tex in textures.items():
            bmp = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(_quantised(tex), np.float32)),
                   "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}
            looks[name] = (bmp, "unlit" if name == "photos" else mode)
        out: dict = {}
        lit_by_flash = fit is not None and fit.flash is not None and env_values is not None
        weight = flash_sampling_weight(fit.flash, env_values, flash_distance(
            np.array([camera_centre(bench.meta.cameras[k]) for k in fit.train_views]), vv)) if lit_by_flash else None
        for name, (colour, look) in looks.items():
            shape = {"type": "ply", "filename": str(ply), "face_normals": True}
            if look == "unlit":
                shape.update(bsdf={"type": "diffuse", "reflectance": 0.0}, emitter={"type": "area", "radiance": colour})
            else:
                shape["bsdf"] = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": colour}}
            scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 2}, "env": env, "mesh": shape}
            flash = look == "lit" and lit_by_flash
            if flash:
                scene[FLASH] = flash_emitter()
            with mitsuba_log_level(mi.LogLevel.Error):
                scene = mi.load_dict(scene)
            params = mi.traverse(scene)
            scores = []
            for i in bench.meta.test:
                if flash:  # the fitted flash at the camera, for the photos it lit
                    set_flash(params, camera_centre(bench.meta.cameras[i]),
                              fit.flash if i in (fit.flash_photos or ()) else np.zeros(3), weight)
                    params.update()
                sensor = mi.load_dict(sensor_dict(bench.meta.cameras[i], s.eval_width, bench.meta.fov))
                img = np.array(mi.render(scene, sensor=sensor, spp=s.spp, seed=s.seed + int(i)))[..., :3] * gains[i]
                scores.append(image_metrics(img, photo_at(bench, i, s.eval_width)))
            out[name] = {"psnr": float(np.mean([x.psnr for x in scores])),
                         "flip": float(np.mean([x.flip for x in scores]))}
            del scene
    return out, [bench.meta.names[i] if hasattr(bench.meta, "names") else str(i) for i in bench.meta.test]
