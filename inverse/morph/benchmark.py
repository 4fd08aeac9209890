"""Geometry-morphing benchmark with ground truth (REAL-DIBS §2.3 artifacts, measured).

A case is built from any mesh file (OBJ/PLY/OFF) or from a procedural
village, and holds:

* the **ground-truth** geometry (PLY) and its textured materials;
* **photos**: ~32 views on a drone-like orbit, path traced under a real HDR
  environment, split into train and held-out (test) views, with cameras;
* a **degraded reconstruction** reproducing the thesis' photogrammetry
  artifacts: decimation (fast-simplification), bumpy flat regions, eroded
  or floating small parts (chimneys), wobbly sharp edges, and vertex colours
  from a blurred, misregistered texture lookup;
* ``morph_benchmark.json`` with settings, cameras and the artifact log.

The village's textures come from the real photographs scikit-image ships
(brick, gravel, grass), tinted per material.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import imageio, validate
from foundation.assets import HDRI_DIR, envmap, hdri_path
from foundation.errors import UsageError
from foundation.files import Memo, array_key, atomic_dir, file_digest, write_json
from foundation.mesh import load_mesh_any, normalise_mesh, sample_surface, vertex_normals, write_ply
from foundation.progress import progress_bar
from foundation.records import load_folder_record, to_json
from .village import material_texture, part_mesh, procedural_colours, village_parts
from .cameras import Camera, drone_orbit, framing_distance, sensor_dict

MARKER = "morph_benchmark.json"  #: written last: a folder holding it is a complete benchmark
#: start remeshes of the coarse input that runs store in the benchmark (``run.stored_remesh``): caches, remade with it
STORED_STARTS = "start_remesh_*.ply"
FORMAT = "photoreal-morph-benchmark/1"
#: renders of one view with other seeds before a photo with non-finite pixels is refused (the first seed is the
#: view's own: benchmarks without such pixels are unchanged)
PHOTO_TRIES = 4


#: shadings of the photographed truth (:attr:`MorphBenchmarkSettings.truth_normals`)
TRUTH_NORMALS = ("vertex", "face")


@dataclass
class MorphBenchmarkSettings:
    n_views: int = 32
    test_every: int = 4  #: every k-th view is held out
    resolution: int = 128
    spp: int = 64
    hdri: str = "sunrise"  #: a bundled HDRI's name or an .exr file (copied into the benchmark)
    photo_max_depth: int = 4  #: path length of the "photos" (2 = direct light only)
    #: camera elevation range; None = the drone's (25°, 45°) for the village, (−15°, 65°) for an object: its sides,
    #: a little of its underside and its top
    elevation_deg: tuple[float, float] | None = None
    #: objects: the camera distance frames the object's bounding sphere with this margin (fraction of the image
    #: half-width), so every view holds the whole silhouette; the village is a scene and keeps its drone framing
    framing_margin: float = 0.1
    coarse_vertices: int = 3000  #: decimation target of the degraded mesh
    bump_amplitude: float = 0.012  #: × scene size, on flat regions
    wobble_amplitude: float = 0.008  #: × scene size, on sharp edges
    misregistration: float = 0.01  #: × scene size, colour lookup offset
    colour_blur: float = 0.02  #: × scene size, colour lookup blur radius
    n_houses: int = 6
    seed: int = 0
    #: shading normals of the photographed truth: "vertex" interpolates vertex normals (smooth shading, what earlier
    #: benchmarks used), "face" shades each triangle flat — the geometry the Chamfer measures. For truths with few
    #: vertices the two disagree: josie's truth (1,600 vertices) rendered flat is 0.0088 from its smooth photos in L1,
    #: against the photos' own noise of 0.0066
    truth_normals: str = "vertex"

    def __post_init__(self):
        validate.one_of("truth_normals", self.truth_normals, TRUTH_NORMALS)
        # At least 4 views: every test_every-th is held out, and both splits must be non-empty.
        validate.integer("n_views", self.n_views, 4, 1024)
        validate.integer("test_every", self.test_every, 2, self.n_views)
        validate.integer("resolution", self.resolution, 16, 4096)
        validate.integer("spp", self.spp, 1, 1 << 16)
        validate.integer("photo_max_depth", self.photo_max_depth, 2, 64)
        validate.integer("coarse_vertices", self.coarse_vertices, 100)
        validate.integer("n_houses", self.n_houses, 1, 6)
        validate.seed("seed", self.seed)
        for name in ("bump_amplitude", "wobble_amplitude", "misregistration", "colour_blur"):
            validate.non_negative(name, getattr(self, name))
        validate.in_range("framing_margin", self.framing_margin, 0.0, 0.9)
        el = self.elevation_deg
        if el is not None:
            self.elevation_deg = el = tuple(float(x) for x in el)
        if el is not None and (len(el) != 2 or not -89 <= el[0] <= el[1] <= 89):
            raise UsageError(f"elevation_deg must be (low, high) within [-89, 89]°, got {el}")
        # The HDRI itself is checked when a benchmark is made (an .exr is copied in; a record need not find it).
        if not isinstance(self.hdri, str) or not self.hdri:
            raise UsageError(f"hdri: a bundled HDRI name or an .exr file, got {self.hdri!r}")

    def elevations(self, kind: str) -> tuple[float, float]:
        if self.elevation_deg is not None:
            return tuple(self.elevation_deg)
        return (25.0, 45.0) if kind == "village" else (-15.0, 65.0)




@dataclass
class Degradation:
    """What :func:`degrade` did to the ground truth (the artifact log of the benchmark)."""

    chimneys_cut: list[int]
    chimneys_floating: list[int]
    bump_rms: float
    coarse_vertices: int
    dense_vertices: int


@dataclass
class MorphBenchmarkMeta:
    """``morph_benchmark.json``: how the benchmark was made, its cameras and split."""

    source: str  #: the mesh file's name (no folder: the JSON is shared) or "village"
    kind: str  #: "village" or the mesh file's stem
    settings: MorphBenchmarkSettings
    cameras: list[Camera]
    fov: float  #: degrees, horizontal
    train: list[int]  #: camera indices of the photos to fit
    test: list[int]  #: held-out camera indices (never fitted)
    scene_size: float  #: bounding-box diagonal of the ground truth
    centre: list[float]
    hdri: str  #: bundled HDRI name, or ``hdri.exr`` in the benchmark folder (absolute once loaded)
    degradation: Degradation
    gt_parts: list[str]
    seconds: float
    format: str = FORMAT
    source_sha256: str | None = None  #: content hash of the mesh file (None for the village)

    @property
    def resolution(self) -> int:
        return self.settings.resolution


# -- meshes ---------------------------------------------------------------------------------------




# -- cameras -------------------------------------------------------------------------------------------




# -- degradation (thesis §2.3) -----------------------------------------------------------------------------


def _smooth_field(p: np.ndarray, scale: float, rng: np.random.Generator, n: int = 8) -> np.ndarray:
    k = rng.normal(size=(n, 3)) / scale
    ph = rng.uniform(0, 2 * np.pi, n)
    return sum(np.sin(p @ k[i] + ph[i]) for i in range(n)) / np.sqrt(n)


#: the uniform remesh of the last few truths (seconds for the armadillo; deterministic: every benchmark of one mesh
#: repeats it before any random draw)
_UNIFORM = Memo(2)


def _uniform(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(v, f))
    ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(0.01))
    ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PercentageValue(0.8), iterations=4)
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)


def degrade(v: np.ndarray, f: np.ndarray, labels: np.ndarray, s: MorphBenchmarkSettings, size: float,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, Degradation]:
    """Photogrammetry-like artifacts; returns the coarse mesh and a log of what was done."""
    import fast_simplification
    import pymeshlab

    log: dict = {}
    # Uniform density first, so that flat walls have vertices to be bumpy with.
    v2, f2 = (a.copy() for a in _UNIFORM.get(array_key(v, f), lambda: _uniform(v, f)))
    # Part labels follow the nearest point of a dense surface sampling (the parts' own vertices are
    # too sparse: a roof quad has four, a chimney box eight, right next to the roof).
    from scipy.spatial import cKDTree

    pts, fid, _ = sample_surface(v, f, 200_000, rng)
    lab = labels[f[fid, 0]][cKDTree(pts).query(v2)[1]]
    # Eroded / floating small parts: cut half of the chimneys, lift the others off the roof.
    chim_ids = np.unique(lab[lab >= 100])
    cut, lifted = [], []
    for cid in chim_ids:
        sel = lab == cid
        if rng.random() < 0.5:
            top = v2[sel, 1].max()
            kill = sel & (v2[:, 1] > top - 0.75 * (top - v2[sel, 1].min()))
            keep_face = ~np.any(kill[f2], axis=1)
            f2 = f2[keep_face]
            cut.append(int(cid))
        else:
            v2[sel, 1] += 0.15 * size / 10
            lifted.append(int(cid))
    log["chimneys_cut"], log["chimneys_floating"] = cut, lifted
    n = vertex_normals(v2, f2)
    # Flatness from normal variation among neighbours: bumps go on flat regions, wobble on edges.
    nb = cKDTree(v2).query(v2, k=8)[1]
    flat = np.clip(np.mean(np.sum(n[nb] * n[:, None, :], axis=-1), axis=1), 0, 1) ** 8
    bump = _smooth_field(v2, 0.03 * size, rng) * s.bump_amplitude * size * flat
    v2 += n * bump[:, None]
    edge = 1.0 - flat
    wob = np.stack([_smooth_field(v2, 0.02 * size, rng) for _ in range(3)], axis=1)
    v2 += wob * (s.wobble_amplitude * size) * edge[:, None]
    log["bump_rms"] = float(np.sqrt(np.mean(bump**2)))
    # Decimation to the coarse target.
    target = float(np.clip(1.0 - s.coarse_vertices / max(len(v2), 1), 0.0, 0.99))
    v3, f3 = fast_simplification.simplify(v2.astype(np.float32), f2.astype(np.int32), target_reduction=target)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(v3, np.float64), np.asarray(f3, np.int64)))
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_remove_null_faces()
    m = ms.current_mesh()
    log["coarse_vertices"] = int(m.vertex_number())
    log["dense_vertices"] = int(len(v2))
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64), Degradation(**log)


def misregistered_colours(vc: np.ndarray, gt_points: np.ndarray, gt_colours: np.ndarray, s: MorphBenchmarkSettings,
                          size: float, rng: np.random.Generator) -> np.ndarray:
    """Colour per coarse vertex from a blurred lookup at a shifted position (misregistered texture)."""
    from scipy.spatial import cKDTree

    shift = rng.normal(size=3)
    shift *= s.misregistration * size / np.linalg.norm(shift)
    tree = cKDTree(gt_points)
    idx = tree.query_ball_point(vc + shift, r=s.colour_blur * size)
    out = np.empty((len(vc), 3), np.float32)
    near = tree.query(vc + shift)[1]
    for i, ids in enumerate(idx):
        out[i] = gt_colours[ids].mean(0) if ids else gt_colours[near[i]]
    return out


# -- the benchmark -----------------------------------------------------------------------------------------


def truth_shapes(folder: Path, kind: str, s: MorphBenchmarkSettings) -> dict:
    """The ground truth's Mitsuba shapes as the photos show it, from a benchmark folder's ``gt_part*.ply``: the
    village's parts with their materials' textures (:func:`village_parts` of the benchmark's seed), an object's
    one part with its vertex colours; two-sided diffuse, shaded with ``s.truth_normals``."""
    if kind == "village":
        materials = [p.material for p in village_parts(s.n_houses, s.seed)]
        textures = {m: mi.TensorXf(aligned(material_texture(m))) for m in set(materials)}
        reflectance = [{"type": "bitmap", "raw": True, "data": textures[m]} for m in materials]
    else:
        reflectance = [{"type": "mesh_attribute", "name": "vertex_color"}]
    return {f"part{i}": {"type": "ply", "filename": str(Path(folder) / f"gt_part{i}.ply"),
                         "face_normals": s.truth_normals == "face",
                         "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": r}}}
            for i, r in enumerate(reflectance)}


def truth_scene(bench: "MorphBenchmark", integrator: dict | None = None) -> mi.Scene:
    """The scene the benchmark's photos were path traced from (ground truth, HDRI; by default the photos'
    ``path`` integrator): renders of it at a photo's camera, spp and seed reproduce that photo."""
    meta = bench.meta
    integrator = integrator or {"type": "path", "max_depth": meta.settings.photo_max_depth}
    return mi.load_dict({"type": "scene", "integrator": integrator, "env": envmap(meta.hdri),
                         **truth_shapes(bench.path, meta.kind, meta.settings)})


def make_morph_benchmark(source: str | Path, out: str | Path, s: MorphBenchmarkSettings | None = None,
                         show_progress: bool = True) -> Path:
    """Build a benchmark folder from a mesh file or ``"village"``."""
    s = s or MorphBenchmarkSettings()
    out = Path(out)
    rng = np.random.default_rng(s.seed)
    env = envmap(s.hdri)  # validated before any work
    light = hdri_path(s.hdri)
    user_hdri = light if light.resolve().parent != HDRI_DIR.resolve() else None
    if str(source) != "village":
        load_mesh_any(source)  # a missing, unreadable or degenerate mesh is named before the folder is touched
    t0 = time.perf_counter()
    with atomic_dir(out, MARKER, derived=(STORED_STARTS,)) as tmp:
        if str(source) == "village":
            parts = village_parts(s.n_houses, s.seed)
            textures = {m: material_texture(m) for m in {p.material for p in parts}}
            for m, tex in textures.items():
                imageio.write_png(tmp / f"tex_{m}.png", tex)
            gt_v, gt_f, labels, gt_uv, gt_mat = [], [], [], [], []
            off = 0
            for i, part in enumerate(parts):
                part_mesh(part, f"part{i}").write_ply(str(tmp / f"gt_part{i}.ply"))
                nv = len(part.vertices)
                gt_v.append(part.vertices)
                gt_f.append(np.arange(nv).reshape(-1, 3) + off)
                labels.append(np.full(nv, 100 + i if part.kind == "chimney" else i))
                gt_uv.append(part.uvs)
                gt_mat.append([part.material] * nv)
                off += nv
            gt_v, gt_f = np.concatenate(gt_v), np.concatenate(gt_f)
            labels = np.concatenate(labels)
            gt_uv, gt_mat = np.concatenate(gt_uv), np.concatenate(gt_mat)

            def albedo_at(fid, w):
                uv = np.einsum("nk,nkd->nd", w, gt_uv[gt_f[fid]])
                out = np.zeros((len(fid), 3), np.float32)
                mats = gt_mat[gt_f[fid, 0]]
                for m, tex in textures.items():
                    sel = mats == m
                    r, c = tex.shape[:2]
                    # Mitsuba's bitmap lookup: uv.y runs down the rows; repeat wrap.
                    ij = np.stack([(uv[sel, 1] % 1.0) * r, (uv[sel, 0] % 1.0) * c], 1).astype(int)
                    out[sel] = tex[np.minimum(ij[:, 0], r - 1), np.minimum(ij[:, 1], c - 1)]
                return out
            kind = "village"
        else:
            v, f = load_mesh_any(source)
            gt_v, gt_f = normalise_mesh(v), f
            col = procedural_colours(gt_v, s.seed)
            write_ply(tmp / "gt_part0.ply", gt_v, gt_f, col)
            labels = np.zeros(len(gt_v), np.int64)

            def albedo_at(fid, w):
                return np.einsum("nk,nkd->nd", w, col[gt_f[fid]]).astype(np.float32)
            kind = Path(source).stem
        shapes = truth_shapes(tmp, kind, s)
        lo, hi = gt_v.min(0), gt_v.max(0)
        size = float(np.linalg.norm(hi - lo))
        centre = 0.5 * (lo + hi)
        write_ply(tmp / "ground_truth.ply", gt_v, gt_f)

        # Photos.
        fov = 40.0
        if kind == "village":
            # A scene, not an object: frame its central part (the orbit sees the whole ground only at the borders).
            centre[1] = lo[1] + 0.25 * (hi[1] - lo[1])
            radius = 0.5 * size / np.tan(np.radians(fov / 2)) * 0.75
            jitter = 0.02
        else:
            radius = framing_distance(gt_v, centre, fov, s.framing_margin)
            jitter = 0.0  # the bounding sphere is centred exactly: the framing guarantee holds in every view
        cams = drone_orbit(s.n_views, centre, radius, s.elevations(kind), s.seed, jitter=jitter)
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": s.photo_max_depth},
                              "env": env, **shapes})
        photos = {}
        with progress_bar(total=len(cams), desc=f"photos {kind}", unit="view", disable=not show_progress) as bar:
            for i, cam in enumerate(cams):
                sensor = mi.load_dict(sensor_dict(cam, s.resolution, fov))
                for k in range(PHOTO_TRIES):  # a rare path sample can come back NaN (bracket, seed 3: 3 pixels)
                    img = np.array(mi.render(scene, sensor=sensor, spp=s.spp, seed=s.seed + i + 1_000_003 * k))[..., :3]
                    if np.isfinite(img).all():
                        break
                else:
                    raise UsageError(f"{source}: view {i}'s photo has non-finite pixels in {PHOTO_TRIES} renders "
                                     f"(a degenerate part of the mesh?)")
                photos[f"view{i:02d}"] = img
                bar.update(1)
        del scene
        imageio.write_exr(tmp / "photos.exr", photos, half=True)
        if user_hdri is not None:  # the benchmark carries its lighting: the folder can move or be shared
            shutil.copyfile(user_hdri, tmp / "hdri.exr")

        # Degraded reconstruction with vertex colours.
        gt_pts, gt_fid, gt_w = sample_surface(gt_v, gt_f, 200_000, rng)
        gt_col = albedo_at(gt_fid, gt_w)
        cv, cf, log = degrade(gt_v, gt_f, labels, s, size, rng)
        ccol = misregistered_colours(cv, gt_pts, gt_col, s, size, rng)
        write_ply(tmp / "coarse.ply", cv, cf, ccol)
        imageio.write_png(tmp / "preview_view00.png", photos["view00"])
        test = [i for i in range(s.n_views) if i % s.test_every == s.test_every - 1]
        # Lighting by name, never by path: a bundled HDRI's name, or the copy inside the benchmark.
        recorded_hdri = "hdri.exr" if user_hdri is not None else light.stem
        meta = MorphBenchmarkMeta(
            source="village" if kind == "village" else Path(source).name, kind=kind,
            settings=replace(s, hdri=recorded_hdri), cameras=cams,
            fov=fov, train=[i for i in range(s.n_views) if i not in test], test=test, scene_size=size,
            centre=centre.tolist(), hdri=recorded_hdri, degradation=log,
            gt_parts=sorted(k for k in shapes), seconds=time.perf_counter() - t0,
            source_sha256=None if kind == "village" else file_digest(source, 64))
        write_json(tmp / MARKER, to_json(meta))  # last: its presence marks a complete benchmark
    return out


@dataclass
class MorphBenchmark:
    path: Path
    meta: MorphBenchmarkMeta
    photos: dict[str, np.ndarray] = field(default_factory=dict)

    def photo(self, i: int) -> np.ndarray:
        """Photo of camera ``i``, (H, W, 3) float32 linear RGB."""
        return self.photos[f"view{i:02d}"][..., :3].astype(np.float32)

    @property
    def coarse(self) -> Path:
        return self.path / "coarse.ply"

    @property
    def ground_truth(self) -> Path:
        return self.path / "ground_truth.ply"


def load_morph_benchmark(path: str | Path) -> MorphBenchmark:
    """Read a benchmark folder; a missing or inconsistent part is named."""
    path = Path(path)
    mp = path / MARKER
    meta = load_folder_record(path, MARKER, MorphBenchmarkMeta, FORMAT, "morph benchmark",
                              "photoreal morph make-benchmark")
    if meta.hdri == "hdri.exr":  # a user's HDRI, copied into the benchmark
        meta.hdri = str(path / "hdri.exr")
        if not Path(meta.hdri).is_file():
            raise UsageError(f"{meta.hdri}: missing from the benchmark (its photos were lit by it)")
    n = len(meta.cameras)
    if not meta.train or not meta.test or max(meta.train + meta.test) >= n or min(meta.train + meta.test) < 0:
        raise UsageError(f"{mp}: train/test views must be non-empty indices of the {n} cameras")
    for name in ("coarse.ply", "ground_truth.ply"):
        if not (path / name).is_file():
            raise UsageError(f"{path / name}: missing from the benchmark")
    ch = imageio.read_exr(path / "photos.exr")
    names = sorted({k.rsplit(".", 1)[0] for k in ch})
    photos = {nm: imageio.exr_layer(ch, nm) for nm in names}
    missing = [i for i in range(n) if f"view{i:02d}" not in photos]
    if missing:
        raise UsageError(f"{path / 'photos.exr'}: no photo for camera(s) {missing[:5]}")
    res = meta.settings.resolution
    if any(photos[f"view{i:02d}"].shape[:2] != (res, res) for i in range(n)):
        raise UsageError(f"{path / 'photos.exr'}: photos are not {res}×{res} as the benchmark says")
    nonfinite = {k: int((~np.isfinite(v)).sum()) for k, v in photos.items()}
    bad = [f"{k} ({c})" for k, c in sorted(nonfinite.items()) if c]
    if bad:
        raise UsageError(f"{path / 'photos.exr'}: non-finite pixels in {', '.join(bad[:5])}; remake the benchmark "
                         f"(photoreal morph make-benchmark re-renders such a view)")
    return MorphBenchmark(path, meta, photos)


def truth_start_benchmark(bench: str | Path, out: str | Path) -> Path:
    """A copy of a benchmark whose "coarse" input is the ground truth itself: the stability test of the morph.

    A morph started at the answer should stay there; how far it drifts (Chamfer, area facing against the truth),
    and whether its validation L1 ends below that of the truth with fitted colours (the photo loss then prefers
    a mesh other than the truth), is the floor of the method on that mesh. Colours are the truth's own per-vertex albedo where the
    benchmark has it (meshes from files), else the coarse input's colour at the nearest vertex (the village is
    textured: per-vertex colour cannot hold its truth). Photos, cameras and split are the benchmark's.
    """
    from scipy.spatial import cKDTree

    from foundation.mesh import read_ply, read_ply_colours

    src = load_morph_benchmark(bench).path
    gv, gf, _ = read_ply(src / "ground_truth.ply")
    colours, origin = None, "nearest coarse vertex"
    parts = sorted(src.glob("gt_part*.ply"))
    if len(parts) == 1:
        pv, _, pc = read_ply(parts[0])
        if pc is not None and pv.shape == gv.shape and np.allclose(pv, gv, atol=1e-6):
            colours, origin = pc, "ground truth"
    if colours is None:
        cv, _, cc = read_ply_colours(src / "coarse.ply")
        colours = cc[cKDTree(cv).query(gv)[1]]
    with atomic_dir(out, MARKER) as tmp:
        for item in src.iterdir():
            # not the stored start remeshes of the coarse input (run.stored_remesh): this copy has another input
            if item.name not in (MARKER, "coarse.ply") and item.is_file() and not item.match(STORED_STARTS):
                shutil.copy2(item, tmp / item.name)
        write_ply(tmp / "coarse.ply", gv, gf, colours)
        write_json(tmp / "truth_start.json", {"from": str(src.name), "colours": origin})
        shutil.copy2(src / MARKER, tmp / MARKER)  # last: marks the copy complete
    return Path(out)


def silhouette_margins(bench: MorphBenchmark, ids: list[int] | None = None, spp: int = 4) -> list[float]:
    """Per view, the free border around the ground truth's silhouette: the smallest distance from a covered
    pixel to the image edge, as a fraction of the image half-width (0: the object touches or leaves the frame)."""
    meta = bench.meta
    ids = list(meta.test if ids is None else ids)
    res = meta.resolution
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "d:depth"},
                          "gt": {"type": "ply", "filename": str(bench.ground_truth)}})
    out = []
    for i in ids:
        sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov))
        hit = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=int(i)))[..., 0] > 0
        if not hit.any():
            out.append(1.0)
            continue
        r, c = np.nonzero(hit)
        free = min(r.min(), c.min(), res - 1 - r.max(), res - 1 - c.max())
        out.append(float(free / (res / 2)))
    return out


# -- artifact regions in image space (for per-region errors of the refinement stages) ---------------------------

ARTIFACT_REGIONS = ("eroded_parts", "floating_parts", "edges", "flat")


def artifact_masks(bench: MorphBenchmark, ids: list[int], spp: int = 16,
                   edge_deg: float = 30.0, dilate: int = 1) -> dict[str, np.ndarray]:
    """Per-pixel masks (len(ids), H, W) bool of where each degradation of :func:`degrade` shows.

    From ground-truth renders at the benchmark's cameras:

    * ``eroded_parts``   — pixels any sample of which sees a ground-truth chimney that was cut;
    * ``floating_parts`` — pixels of the chimneys that were lifted, dilated by the
      lift's image-space size (the coarse copy floats just above them);
    * ``edges``          — pixels within ``dilate`` px of a geometric discontinuity of
      the truth (normal turning by > ``edge_deg`` or a silhouette): where wobble and
      decimation act;
    * ``flat``           — the rest of the truth's surface: the bumpy walls, roofs,
      ground (or body of a scanned mesh).

    Regions may overlap (a chimney's edge is in two); background pixels are in none.
    """
    from scipy import ndimage

    meta = bench.meta
    res, fov = meta.resolution, meta.fov
    deg = meta.degradation
    parts = {int(p[4:]): bench.path / f"gt_{p}.ply" for p in meta.gt_parts}
    if not parts:
        raise ValueError(f"{bench.path}: benchmark lists no ground-truth parts (gt_parts)")
    for i, p in parts.items():
        if not p.is_file():
            raise FileNotFoundError(f"{p}: ground-truth part missing from the benchmark")

    def coverage(selected: set[int]) -> np.ndarray:
        # Selected parts emit 1, the others are black occluders: path depth 1 = coverage of visible pixels.
        shapes = {}
        for i, p in parts.items():
            sh = {"type": "ply", "filename": str(p), "bsdf": {"type": "diffuse", "reflectance": 0.0}}
            if i in selected:
                sh["emitter"] = {"type": "area", "radiance": 1.0}
            shapes[f"part{i}"] = sh
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1}, **shapes})
        out = np.empty((len(ids), res, res), np.float32)
        for k, i in enumerate(ids):
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, fov))
            out[k] = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=int(i)))[..., 0]
        return out

    cut = {c - 100 for c in deg.chimneys_cut}
    lifted = {c - 100 for c in deg.chimneys_floating}
    masks = {"eroded_parts": coverage(cut) > 0 if cut else np.zeros((len(ids), res, res), bool)}
    if lifted:
        # Lift in pixels: 0.15·size/10 world units seen from the orbit radius (small-angle projection).
        radius = float(np.mean([np.linalg.norm(np.subtract(c.eye, c.target)) for c in meta.cameras]))
        lift_px = 0.015 * meta.scene_size / (2 * radius * np.tan(np.radians(fov / 2))) * res
        grow = max(1, int(np.ceil(lift_px)))
        masks["floating_parts"] = np.stack([ndimage.binary_dilation(m, iterations=grow)
                                            for m in coverage(lifted) > 0])
    else:
        masks["floating_parts"] = np.zeros((len(ids), res, res), bool)

    # Geometric discontinuities from an AOV render of the truth (normals averaged over the pixel's samples).
    gt = {"type": "ply", "filename": str(bench.ground_truth)}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "nn:geo_normal"}, "gt": gt})
    cos_t = np.cos(np.radians(edge_deg))
    edges, surface = [], []
    for i in ids:
        sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, fov))
        n = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=int(i)))[..., :3]
        ln = np.linalg.norm(n, axis=-1)
        hit = ln > 1e-3
        nu = n / np.maximum(ln, 1e-6)[..., None]
        # A pixel mixing directions (|mean normal| < cos) or differing from a 4-neighbour by > edge_deg is an edge;
        # normals are compared up to sign (the truth's parts are two-sided sheets).
        e = hit & (ln < cos_t)
        for ax in (0, 1):
            d = np.abs(np.sum(nu * np.roll(nu, 1, axis=ax), -1))
            h2 = hit & np.roll(hit, 1, axis=ax)
            jump = (d < cos_t) & h2
            sil = hit ^ np.roll(hit, 1, axis=ax)
            e |= jump | sil | np.roll(jump | sil, -1, axis=ax)
        e &= ndimage.binary_dilation(hit)  # surface pixels and the background pixel just outside
        edges.append(ndimage.binary_dilation(e, iterations=dilate) if dilate else e)
        surface.append(hit)
    masks["edges"] = np.stack(edges)
    masks["flat"] = np.stack(surface) & ~masks["edges"] & ~masks["eroded_parts"] & ~masks["floating_parts"]
    return masks


def benchmark_capture(bench: MorphBenchmark):
    """The benchmark as a capture (:mod:`inverse.capture`): its photos and cameras, the coarse mesh, the truth."""
    from inverse.capture import MITSUBA_FROM_COLMAP, CaptureCamera, CaptureMeta, Capture

    meta, res = bench.meta, bench.meta.resolution
    f = 0.5 * res / np.tan(np.radians(meta.fov / 2))
    cams = []
    for i, cam in enumerate(meta.cameras):
        to_world = np.array(mi.ScalarTransform4f().look_at(origin=list(cam.eye), target=list(cam.target),
                                                            up=[0, 1, 0]).matrix, np.float64)
        cams.append(CaptureCamera(f"view{i:02d}", res, res, float(f), res / 2, res / 2,
                                  (to_world @ np.linalg.inv(MITSUBA_FROM_COLMAP)).tolist()))
    cm = CaptureMeta(cams, [f"view{i:02d}" for i in meta.train], [f"view{i:02d}" for i in meta.test],
                     {"format": "morph-benchmark", "path": str(bench.path)}, mesh="coarse.ply", truth="ground_truth.ply")
    return Capture(bench.path, cm, {c.name: bench.photo(i) for i, c in enumerate(cams)})
