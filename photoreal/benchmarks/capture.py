"""`photoreal bench capture`: the vendored real captures (scenes/assets/captures: a skull, stone ruins) through
structure from motion on the CPU, and the held-out-photo scores of the coarse mesh it gives.

Per capture: photos registered / total, the number of models, points, mean reprojection error and the seconds of each
step (``capture sfm``), then PSNR, SSIM, ꟻLIP and the MobileNetV2 distance of the unlit render of the Poisson mesh,
coloured from the training photos, at every held-out photo (``capture score``): the first baseline a morph of a
real capture has to beat. Targets (issue "Real captures in"): ≥ 90 % of the skull's photos registered, mean
reprojection error ≤ 1 px.

The synthetic suite goes the same real path with a truth to judge by: meshes of the morph suite, speckled (random
vertex colours on a subdivided surface, as a textured object gives SIFT something to hold on to), path traced from
an orbit of cameras under uniform light; the cameras are thrown away, ``capture sfm`` runs on the photos, and the
recovered cameras are aligned to the true ones by a similarity (Umeyama, on the centres): centre errors as a
fraction of the orbit radius, rotation errors, and the Chamfer distance of the Poisson mesh to the truth. Target:
centres within 2 % of the orbit radius on ≥ 3 meshes.

The morph on both (issue "Morphing a real capture"), with the default flags: each real capture's SfM mesh morphed
against its training photos (the light, exposures and the cameras' last errors fitted), scored on the held-out
photos against the input mesh under the same fitted light and exposure, with camera refinement off (the default) and
on; each suite mesh morphed from its SfM mesh and cameras, and again from the same mesh mapped into the truth's frame
with the exact cameras, both judged by the Chamfer distance to the truth after the cameras' alignment. Targets:
held-out PSNR ≥ +2 dB and ꟻLIP ≥ 15 % lower than the input, 0 spikes, 0 inverted triangles; on the suite a Chamfer
≥ 30 % below the SfM mesh's and within 1.5× of the exact cameras' morph.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import ROOT

CAPTURES = ROOT / "scenes" / "assets" / "captures"


@dataclass
class CaptureBenchSettings:
    captures: tuple[str, ...] = ("skull", "ruins")  #: folders of scenes/assets/captures
    resolution: int = 512  #: longest side of the working photos
    max_size: int = 1024  #: longest side the SIFT features are found at (the vendored photos are smaller)
    spp: int = 16  #: samples per pixel of the held-out renders
    suite: tuple[str, ...] = ("bunny", "cow", "bone")  #: morph suite meshes through the real path (empty: none)
    suite_views: int = 36  #: photos on each suite mesh's orbit
    suite_resolution: int = 384  #: their side (pixels)
    suite_spp: int = 32
    max_centre_error: float = 0.02  #: target: recovered centres within this fraction of the orbit radius
    min_registered: float = 0.9  #: target: fraction of the photos registered
    max_reprojection_px: float = 1.0  #: target: mean reprojection error
    no_morph: bool = False  #: no morph of the captures and the suite's SfM meshes (SfM and scores only)
    #: no second morph of the real captures with camera refinement on (its effect)
    no_refine_on: bool = False
    #: no second morph of the suite's meshes from the exact cameras (the reference the real path is judged against)
    no_exact: bool = False
    #: the suite's morphs' iteration cap (0: the morph's default; the real captures always run the default)
    suite_iterations: int = 0
    min_psnr_gain: float = 2.0  #: target: held-out PSNR of the morphed mesh over the input's (dB)
    min_flip_reduction: float = 0.15  #: target: ꟻLIP lower by this fraction
    min_chamfer_reduction: float = 0.3  #: target: suite Chamfer below the SfM mesh's by this fraction
    max_chamfer_vs_exact: float = 1.5  #: target: suite Chamfer within this factor of the exact cameras' morph
    seed: int = 0

    def __post_init__(self):
        # `--suite ''`, `--captures ''`: none (argparse's "+" takes at least one word)
        self.captures, self.suite = tuple(c for c in self.captures if c), tuple(m for m in self.suite if m)
        validate.integer("suite_views", self.suite_views, 8, 400)
        validate.integer("suite_iterations", self.suite_iterations, 0)
        validate.integer("suite_resolution", self.suite_resolution, 64, 4096)
        validate.integer("suite_spp", self.suite_spp, 1, 4096)
        for c in self.captures:
            if not (CAPTURES / c / "images").is_dir():
                from foundation.errors import UsageError

                raise UsageError(f"captures: {c!r} is not a folder of {CAPTURES} with images/")
        validate.integer("resolution", self.resolution, 16, 8192)
        validate.integer("spp", self.spp, 1, 4096)
        validate.in_range("min_registered", self.min_registered, 0.0, 1.0)
        validate.positive("max_reprojection_px", self.max_reprojection_px)
        validate.seed("seed", self.seed)


def _morph(cap, out: Path, show_progress: bool, iterations: int | None = None, **overrides):
    """The default morph of a capture in ``out`` (resumable: a finished run is scored again only)."""
    from inverse.morph import CaptureBenchmark, MorphSettings, run_morph

    s = MorphSettings(**overrides, **({"iterations": iterations} if iterations else {}))
    return run_morph(CaptureBenchmark(cap, out / ".capture_input"), out, s, show_progress=show_progress)


def _morph_row(r, s: CaptureBenchSettings) -> dict:
    """A capture morph's figures: held-out input vs morphed, repairs, seconds, what it fitted, the targets."""
    metrics = ("psnr", "one_minus_ssim", "flip")
    row = {"input": {k: getattr(r.heldout_input, k) for k in metrics} | {"perceptual": r.perceptual_heldout_input},
           "morphed": {k: getattr(r.heldout_morphed, k) for k in metrics} | {"perceptual": r.perceptual_heldout_morphed},
           "spikes": r.spikes, "inverted_triangles": r.inverted_triangles, "seconds": r.seconds,
           "iterations": r.iterations, "vertices": r.vertices,
           "mode": r.photo_fit.mode if r.photo_fit else r.settings.mode,
           "mode_selection": None if r.mode_selection is None else
           {"lit": r.mode_selection.validation_l1_lit, "unlit": r.mode_selection.validation_l1_unlit},
           "flash": None if r.photo_fit is None else r.photo_fit.flash,
           "exposure_slope": None if r.photo_fit is None else r.photo_fit.exposure_slope,
           "masks": None if r.photo_fit is None else r.photo_fit.masks,
           "camera_movement": None if r.photo_fit is None or r.photo_fit.camera_movement is None else
           {k: v for k, v in r.photo_fit.camera_movement.items() if not isinstance(v, list)}}
    row["object_region"] = {"share": r.object_share, "psnr": [r.psnr_object_input, r.psnr_object_morphed],
                            "flip": [r.flip_object_input, r.flip_object_morphed],
                            "psnr_gain": r.psnr_object_morphed - r.psnr_object_input,
                            "flip_reduction": 1.0 - r.flip_object_morphed / r.flip_object_input}
    gain = row["morphed"]["psnr"] - row["input"]["psnr"]
    flip = 1.0 - row["morphed"]["flip"] / row["input"]["flip"]
    row["psnr_gain"], row["flip_reduction"] = gain, flip
    row["targets"] = {f"psnr_gain_at_least_{s.min_psnr_gain}": gain >= s.min_psnr_gain,
                      f"flip_reduction_at_least_{s.min_flip_reduction}": flip >= s.min_flip_reduction,
                      "no_spikes": r.spikes == 0, "no_inverted_triangles": r.inverted_triangles == 0}
    return row


def _one(name: str, s: CaptureBenchSettings, work: Path, show_progress: bool) -> dict:
    from foundation.mesh import read_ply
    from inverse.capture import SfmSettings, heldout_scores, import_capture, load_capture, run_sfm

    out = work / name / "capture"
    if not (out / "capture.json").is_file():  # a finished capture is reused: a rerun scores again only
        src = run_sfm(CAPTURES / name / "images", work / name / "sfm",
                      SfmSettings(max_size=s.max_size, seed=s.seed),
                      progress=(lambda m: print(f"{name}: {m}", flush=True)) if show_progress else None)
        import_capture(src, out, s.resolution, show_progress=show_progress)
    cap = load_capture(out)
    sfm = dict(cap.meta.sfm or {})
    row = {"sfm": sfm, "photos_in_capture": len(cap.meta.cameras), "held_out": cap.meta.test}
    if cap.mesh is None:
        row["scores"] = None
        row["scores_skipped"] = "no mesh: too few triangulated points"
    else:
        v, f, _ = read_ply(cap.mesh)
        r = heldout_scores(cap, v, f, spp=s.spp, seed=s.seed)
        r.pop("renders")
        row["mesh"] = {"vertices": int(len(v)), "faces": int(len(f))}
        row["scores"] = r
        if not s.no_morph:
            row["morph"] = _morph_row(_morph(cap, work / name / "morph", show_progress), s)
            row["export"] = _export_row(cap, work / name, s)
            if not s.no_refine_on:
                row["morph_refine_on"] = _morph_row(_morph(cap, work / name / "morph_refine_on", show_progress,
                                                           refine_cameras="auto"), s)
    reg = sfm.get("registered", 0) / max(1, sfm.get("photos", 1))
    row["registered_fraction"] = reg
    row["targets"] = {f"registered_at_least_{s.min_registered}": reg >= s.min_registered,
                      f"reprojection_at_most_{s.max_reprojection_px}_px":
                          sfm.get("reprojection_px", float("inf")) <= s.max_reprojection_px}
    return row


def _export_row(cap, folder: Path, s: CaptureBenchSettings) -> dict:
    """The morphed mesh exported (`photoreal export`): its textures baked from the photos and from the vertex colours
    against the vertex colours themselves, on the held-out photos at the capture's working width."""
    from foundation.export import ExportSettings
    from inverse.morph import export_morph

    width = max(c.width for c in cap.meta.cameras)
    rec = export_morph(folder / "morph", folder / "export", ExportSettings(eval_width=min(width, 512), spp=s.spp,
                                                                          seed=s.seed), input_path=cap.path)
    h = rec.heldout
    best = max(("photos", "colours"), key=lambda k: h[k]["psnr"])
    return {"heldout": h, "eval_width": min(width, 512), "photo_coverage": rec.photo_coverage,
            "default_texture": rec.texture, "better_texture_psnr": best,
            "better_texture_flip": min(("photos", "colours"), key=lambda k: h[k]["flip"]),
            "reimport_psnr": rec.reimport.get("render_psnr"), "validator_errors": _validator_errors(folder / "export"),
            "seconds": rec.seconds}


def _validator_errors(folder: Path) -> int | None:
    """The Khronos validator's error count of the exported model (None without node)."""
    import shutil

    from foundation.export import validate_gltf

    if shutil.which("node") is None:
        return None
    return int(validate_gltf(folder / "model.glb")["issues"]["numErrors"])


def _speckled(path: Path, seed: int, min_vertices: int = 60_000):
    """The mesh normalised (2-unit diagonal), subdivided to at least ``min_vertices``, with random vertex colours."""
    import pymeshlab

    from foundation.mesh import load_mesh_any, normalise_mesh

    v, f = load_mesh_any(path)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=normalise_mesh(v), face_matrix=f))
    for _ in range(6):  # every edge split once per pass (threshold 0: pymeshlab splits only long edges otherwise)
        if ms.current_mesh().vertex_number() >= min_vertices:
            break
        ms.meshing_surface_subdivision_midpoint(iterations=1, threshold=pymeshlab.PercentageValue(0))
    from scipy.spatial import cKDTree

    m = ms.current_mesh()
    v = m.vertex_matrix()
    rng = np.random.default_rng(seed)
    # Voronoi patches of random colour around 4000 random vertices: crisp corners a few pixels wide in every view
    seeds = v[rng.choice(len(v), min(4000, len(v)), replace=False)]
    grey = rng.uniform(0.05, 0.95, (len(seeds), 1)) * rng.uniform(0.7, 1.0, (len(seeds), 3))
    return v, m.face_matrix(), grey[cKDTree(seeds).query(v)[1]].astype(np.float32)


def _orbit(n: int, centre: np.ndarray, radius: float, res: int, fov: float = 40.0) -> list:
    """``n`` cameras around ``centre``, elevation alternating 15°/35° (a drone's two rings)."""
    from inverse.capture import CaptureCamera

    f = 0.5 * res / np.tan(np.radians(fov / 2))
    cams = []
    for i in range(n):
        az, el = 2 * np.pi * i / n, np.radians(15.0 if i % 2 else 35.0)
        eye = centre + radius * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        z = (centre - eye) / np.linalg.norm(centre - eye)
        x = np.cross(z, [0.0, -1.0, 0.0])
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = np.stack([x, np.cross(z, x), z], 1), eye
        cams.append(CaptureCamera(f"view{i:03d}", res, res, float(f), res / 2, res / 2, m.tolist()))
    return cams


def _suite_case(name: str, s: CaptureBenchSettings, work: Path, show_progress: bool) -> dict:
    import mi_plugins  # noqa: F401
    import mitsuba as mi

    from foundation import imageio
    from foundation.files import read_json, write_json
    from foundation.mesh import write_ply
    from foundation.mesh_metrics import chamfer
    from inverse.capture import SfmSettings, camera_errors, coarse_mesh_from_points, run_sfm, sensor
    from inverse.morph import suite_mesh

    folder = work / "suite" / name
    done = folder / "result.json"
    if done.is_file():  # a finished case is reused (a morph part is added to one made without it)
        row = read_json(done, "suite result")
        if s.no_morph or "morph" in row or "chamfer" not in row.get("mesh", {}):
            return row
    v, f, col = _speckled(suite_mesh(name, folder), s.seed)
    centre = 0.5 * (v.min(0) + v.max(0))
    bound = float(np.linalg.norm(v - centre, axis=1).max())
    radius = 1.3 * bound / np.tan(np.radians(20.0))  # the object fills most of the frame
    cams = _orbit(s.suite_views, centre, radius, s.suite_resolution)
    ply = write_ply(folder / "truth.ply", v, f, col)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                          "sky": {"type": "constant", "radiance": 0.6},
                          "mesh": {"type": "ply", "filename": str(ply), "bsdf": {"type": "twosided", "bsdf": {
                              "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}}}})
    photos = folder / "photos"
    photos.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    for k, c in enumerate(cams):
        if not (photos / f"{c.name}.png").is_file():
            img = np.array(mi.render(scene, sensor=mi.load_dict(sensor(c)), spp=s.suite_spp, seed=s.seed + k))
            exif = Image.Exif()  # what a camera records: the 35 mm equivalent focal length (a prior, refined by SfM)
            exif[0x8769] = {0xA405: int(round(c.f / c.width * 36.0))}
            Image.fromarray(imageio.to_uint8_srgb(img[..., :3])).save(photos / f"{c.name}.png", exif=exif)
    src = run_sfm(photos, folder / "sfm", SfmSettings(max_size=s.suite_resolution, seed=s.seed),
                  progress=(lambda m: print(f"suite {name}: {m}", flush=True)) if show_progress else None)
    sfm = src.notes["sfm"]
    truth = {c.name: c.matrix for c in cams}
    err = camera_errors({fr.name: fr.cam_to_world for fr in src.frames}, truth, radius)
    row = {"sfm": sfm, "cameras": err, "orbit_radius": radius, "views": s.suite_views,
           "resolution": s.suite_resolution}
    try:
        mv, mf, _ = coarse_mesh_from_points(src.points, None, np.array([fr.cam_to_world[:3, 3] for fr in src.frames]),
                                            view_dirs=src.view_dirs)
        r, t = np.asarray(err["rotation"]), np.asarray(err["translation"])
        aligned = err["scale"] * mv @ r.T + t
        ch = chamfer(aligned, mf, v, f)
        size = float(np.linalg.norm(v.max(0) - v.min(0)))
        row["mesh"] = {"vertices": int(len(mv)), "chamfer": ch["chamfer"], "chamfer_of_size": ch["chamfer"] / size,
                       "normal_consistency": ch["normal_consistency"]}
    except Exception as exc:  # no usable surface from these points: the cameras' figures still stand
        row["mesh"] = {"error": " ".join(str(exc).split())[:200]}
    row["within_target"] = err["centre_error_max"] <= s.max_centre_error
    if not s.no_morph and "chamfer" in row["mesh"]:
        row["morph"] = _suite_morph(folder, src, cams, err, v, f, row["mesh"]["chamfer"], s, show_progress)
    write_json(done, row)
    return row


def _suite_morph(folder: Path, src, cams: list, err: dict, v, f, chamfer_sfm: float, s: CaptureBenchSettings,
                 show_progress: bool) -> dict:
    """The suite mesh's real path on to the morph: the SfM capture (its cameras, the Poisson mesh of its points)
    morphed with the default flags, and — unless ``no_exact`` — the same mesh mapped by the cameras' similarity into
    the truth's frame, morphed from the exact cameras and the unprocessed photos; both morphs' Chamfer to the truth
    (the SfM one after the similarity)."""
    from dataclasses import replace

    from foundation import imageio
    from foundation.mesh import read_ply_colours, write_ply
    from foundation.mesh_metrics import chamfer
    from inverse.capture import Capture, import_capture, load_capture

    cap_dir = folder / "capture"
    if not (cap_dir / "capture.json").is_file():
        import_capture(src, cap_dir, s.suite_resolution, show_progress=show_progress)
    cap = load_capture(cap_dir)
    scale, rot, shift = err["scale"], np.asarray(err["rotation"]), np.asarray(err["translation"])

    def to_truth(x):
        return scale * np.asarray(x, np.float64) @ rot.T + shift

    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    out = {"chamfer_sfm_mesh": chamfer_sfm}
    r = _morph(cap, folder / "morph", show_progress, s.suite_iterations)
    mv, mf, _ = read_ply_colours(folder / "morph" / "morphed.ply")
    ch = chamfer(to_truth(mv), mf, v, f)
    out["sfm_cameras"] = {"chamfer": ch["chamfer"], "chamfer_of_size": ch["chamfer"] / size,
                          "normal_consistency": ch["normal_consistency"], **_morph_row(r, s)}
    if not s.no_exact:
        exact = folder / "capture_exact"
        exact.mkdir(exist_ok=True)
        cv, cf, cc = read_ply_colours(cap.mesh)
        write_ply(exact / "mesh.ply", to_truth(cv), cf, cc)
        names = {c.name for c in cap.meta.cameras}
        true = [c for c in cams if c.name in names]
        photos = {c.name: imageio.read_image(folder / "photos" / f"{c.name}.png", channels=3, linear=True,
                                             what="photo") for c in true}
        meta = replace(cap.meta, cameras=true, mesh="mesh.ply", masks=False, truth=None,
                       source={"format": "suite-exact", "exact_cameras": True})
        r = _morph(Capture(exact, meta, photos), folder / "morph_exact", show_progress, s.suite_iterations)
        ev, ef, _ = read_ply_colours(folder / "morph_exact" / "morphed.ply")
        ch = chamfer(ev, ef, v, f)
        out["exact_cameras"] = {"chamfer": ch["chamfer"], "chamfer_of_size": ch["chamfer"] / size,
                                "normal_consistency": ch["normal_consistency"], **_morph_row(r, s)}
    got = out["sfm_cameras"]["chamfer"]
    out["chamfer_reduction"] = 1.0 - got / chamfer_sfm
    out["targets"] = {f"chamfer_reduction_at_least_{s.min_chamfer_reduction}":
                      out["chamfer_reduction"] >= s.min_chamfer_reduction}
    if "exact_cameras" in out:
        out["chamfer_vs_exact"] = got / out["exact_cameras"]["chamfer"]
        out["targets"][f"chamfer_within_{s.max_chamfer_vs_exact}x_exact"] = \
            out["chamfer_vs_exact"] <= s.max_chamfer_vs_exact
    return out


def run(s: CaptureBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    work = Path(work)
    suite = {name: _suite_case(name, s, work, show_progress) for name in s.suite}
    return {"captures": {name: _one(name, s, work, show_progress) for name in s.captures},
            "suite": suite,
            "suite_within_target": sum(r["within_target"] for r in suite.values()),
            "settings": {"resolution": s.resolution, "max_size": s.max_size, "spp": s.spp,
                         "suite_views": s.suite_views, "suite_resolution": s.suite_resolution}}


def summary(result: dict) -> dict:
    out = {}
    for name, r in result["captures"].items():
        sfm = r["sfm"]
        out[name] = {"registered": f"{sfm.get('registered')}/{sfm.get('photos')}", "models": sfm.get("models"),
                     "points": sfm.get("points"), "reprojection_px": sfm.get("reprojection_px"),
                     "seconds": sfm.get("seconds"),
                     "heldout_mean": (r["scores"] or {}).get("mean"), "targets": r["targets"]}
        if r.get("export"):
            out[name]["export_heldout"] = {k: f"{v['psnr']:.2f} dB / ꟻLIP {v['flip']:.3f}"
                                           for k, v in r["export"]["heldout"].items()}
    for name, r in result.get("suite", {}).items():
        out[f"suite {name}"] = {"registered": f"{r['sfm']['registered']}/{r['sfm']['photos']}",
                                "centre_error_max": r["cameras"]["centre_error_max"],
                                "rotation_error_max_deg": r["cameras"]["rotation_error_max_deg"],
                                "chamfer_of_size": r["mesh"].get("chamfer_of_size"), "within_target": r["within_target"]}
        if "morph" in r:
            m = r["morph"]
            out[f"suite {name}"]["morph"] = {"chamfer_sfm_mesh": m["chamfer_sfm_mesh"],
                                             "chamfer_morphed": m["sfm_cameras"]["chamfer"],
                                             "chamfer_exact_cameras": m.get("exact_cameras", {}).get("chamfer"),
                                             "targets": m["targets"]}
    for name, r in result["captures"].items():
        for key in ("morph", "morph_refine_on"):
            if key in r:
                m = r[key]
                out[name][key] = {"psnr": [m["input"]["psnr"], m["morphed"]["psnr"]],
                                  "flip": [m["input"]["flip"], m["morphed"]["flip"]], "spikes": m["spikes"],
                                  "inverted_triangles": m["inverted_triangles"], "mode": m["mode"],
                                  "flash": m.get("flash"),
                                  **({"exposure_slope": m["exposure_slope"]} if m.get("exposure_slope") else {}),
                                  "targets": m["targets"]}
    return out


SETTINGS = CaptureBenchSettings
