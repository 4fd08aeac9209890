"""Where a mesh lies against the ground truth: both directions of the Chamfer distance apart, the truth's open
border against its interior, how much of the coarse input's error a result kept, and signed-distance maps (PLY
with vertex colours and a figure) to look at rather than read.

The headline Chamfer (:func:`foundation.mesh_metrics.chamfer`) is the mean of two directions: the result's points
to the truth (what it got wrong) and the truth's points to the result (what it misses). They tell different stories
(a shrunken open sheet misses its border; a bump that stayed is wrong in both), and a morph result that keeps a
fraction of its input's bumps shows as a slope of its signed distance on the input's at the same place.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation.files import atomic_path
from foundation.mesh import boundary_edges, face_normals, sample_surface, write_ply
from foundation.mesh_metrics import DEFAULT_SAMPLES, facing_mask, signed_distance, triangle_areas, truth_surface

from .scene import views_seeing


@dataclass
class ScaleBand:
    """One band of :func:`error_left_by_scale`: the input's and the result's error between two smoothing scales."""

    band: str  #: e.g. "0.02-0.04": Gaussian σ between 2 % and 4 % of the truth's bounding-box diagonal; "mean": offset
    rms_input: float  #: rms of the input's error in this band
    rms_result: float  #: rms of the result's error in this band
    slope: float | None  #: least-squares slope of the result's band on the input's (1: kept, 0: fixed); None: no error


@dataclass
class SurfaceErrors:
    """:func:`surface_errors` of one mesh; lengths in the scene's units, means over area-uniform samples."""

    name: str
    chamfer: float  #: mean of ``to_truth`` and ``from_truth`` (the headline Chamfer's definition, this sampling)
    to_truth: float  #: mean distance of the mesh's points to the truth (what it got wrong), as the Chamfer measures it
    from_truth: float  #: mean distance of the truth's points to the mesh (what it misses)
    #: mean signed distance of the mesh's points (:func:`~foundation.mesh_metrics.signed_distance`; +: on the side
    #: the truth's normals point to)
    signed_mean: float
    p95: float  #: 95th percentile of the mesh's points' distances to the truth
    #: ``from_truth`` of the truth's points within ``band`` of its open border, and of the others (None: a closed truth)
    from_truth_border: float | None = None
    from_truth_interior: float | None = None
    border_share: float | None = None  #: share of the truth's area within that band
    #: least-squares slope of this mesh's signed distance on the reference's (the input) at the reference's nearest
    #: point: 1 = the input's error kept where it was, 0 = none of it left; None for the reference itself
    input_error_left: float | None = None
    input_error_correlation: float | None = None
    #: rms of the signed distance the slope does not explain: error this mesh made that its input did not have
    new_error_rms: float | None = None
    #: the input's error kept, per spatial scale (:func:`error_left_by_scale`): which sizes of the input's flaws a
    #: result fixed (the fine bumps, the broad undulations) and which it left; None for the reference itself
    input_error_left_by_scale: list[ScaleBand] | None = None
    #: share of the mesh's area facing against the truth (:func:`~foundation.mesh_metrics.facing_against_truth`)
    facing_area: float | None = None
    #: that share split by how many training views see the triangle (:func:`views_seeing`): "0", "1-2", "3+" — whether
    #: the photos observe the surface that is wrong, or only the priors decide it there
    facing_area_by_views: dict[str, float] | None = None
    unseen_area: float | None = None  #: share of the mesh's area no training view sees


def _border_points(gv: np.ndarray, gf: np.ndarray, spacing: float) -> np.ndarray | None:
    """Points every ``spacing`` (at most) along the mesh's open border; None when it has none. Vertices at one
    place are welded first: a truth stored with its seams unwelded (the suite's table, a box per part) is closed."""
    tol = 1e-7 * float(np.linalg.norm(np.ptp(gv, axis=0)))
    _, first, inverse = np.unique(np.round(gv / tol), axis=0, return_index=True, return_inverse=True)
    e = boundary_edges(first[inverse.ravel()][gf])
    if not len(e):
        return None
    a, b = gv[e[:, 0]], gv[e[:, 1]]
    k = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing).astype(int))
    t = np.concatenate([np.arange(n) / n for n in k])
    i = np.repeat(np.arange(len(e)), k)
    return a[i] + t[:, None] * (b[i] - a[i])


#: the bands' edges of :func:`error_left_by_scale`, as Gaussian σ in fractions of the truth's bounding-box diagonal
SCALES = (0.01, 0.02, 0.04, 0.08)


def error_left_by_scale(g_pts: np.ndarray, fields: dict[str, np.ndarray], size: float, reference: str,
                        scales: tuple[float, ...] = SCALES) -> dict[str, list[ScaleBand]]:
    """Per mesh (``fields``: name → its signed offset at the truth points ``g_pts``, area-uniform), its error split
    into bands of spatial scale and regressed, band by band, on the ``reference``'s (the input): what a result kept
    of its input's fine bumps and of its broad undulations. The bands come from Gaussian smoothing over the truth's
    points at σ = ``scales`` × ``size`` (Euclidean neighbours: across a part thinner than 2.5 σ, both sides mix),
    each band the difference of two successive smoothings, the coarsest less the mean, the mean its own band."""
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    tree = cKDTree(g_pts)
    lows = {k: [x] for k, x in fields.items()}
    for sigma in (float(x) * size for x in scales):
        m = tree.sparse_distance_matrix(tree, 2.5 * sigma, output_type="coo_matrix")
        w = sp.coo_matrix((np.exp(-0.5 * (m.data / sigma) ** 2), (m.row, m.col)), shape=(len(g_pts),) * 2).tocsr()
        w = w + sp.identity(len(g_pts), format="csr")  # each point itself (distance 0: not stored as a pair)
        norm = np.asarray(w.sum(axis=1)).ravel()
        for k, x in fields.items():
            lows[k].append((w @ x) / norm)
    for k, x in fields.items():
        lows[k].append(np.full_like(x, x.mean()))
    names = [f"<{scales[0]:g}"] + [f"{a:g}-{b:g}" for a, b in zip(scales[:-1], scales[1:])] + [f">{scales[-1]:g}"]
    ref = lows[reference]
    out = {}
    for k, low in lows.items():
        if k == reference:
            continue
        bands = []
        for j, name in enumerate([*names, "mean"]):
            a, b = (ref[j] - ref[j + 1], low[j] - low[j + 1]) if name != "mean" else (ref[-1], low[-1])
            aa = float(np.dot(a, a))
            bands.append(ScaleBand(name, float(np.sqrt(np.mean(a**2))), float(np.sqrt(np.mean(b**2))),
                                   float(np.dot(a, b)) / aa if aa > 0 else None))
        out[k] = bands
    return out


def border_band(gv: np.ndarray, band: float | None = None) -> float:
    """The border band's width: ``band``, or 2.5 % of the truth's bounding-box diagonal."""
    band = 0.025 * float(np.linalg.norm(np.ptp(gv, axis=0))) if band is None else float(band)
    if not np.isfinite(band) or band <= 0:
        raise ValueError(f"band must be > 0, got {band}")
    return band


def surface_errors(gv: np.ndarray, gf: np.ndarray, meshes: dict[str, tuple[np.ndarray, np.ndarray]],
                   reference: str | None = None, band: float | None = None, n: int | None = None,
                   seed: int = 0, n_scale: int = 8000) -> dict[str, SurfaceErrors]:
    """:class:`SurfaceErrors` of each mesh (name → vertices, faces) against the truth ``gv, gf``.

    ``reference``: the name of the mesh whose error the others are regressed on (the coarse input). ``band``: width
    of the truth's border band (default 2.5 % of the truth's bounding-box diagonal). ``n``: points per surface (default
    the Chamfer's query count, :data:`~foundation.mesh_metrics.DEFAULT_SAMPLES`; the mesh side of the truth → mesh
    direction uses the Chamfer's denser reference count). ``seed``: of those samplings (fixed: reports repeat).
    ``n_scale``: truth points of the split by scale (:func:`error_left_by_scale`, with a reference; 0: none)."""
    from scipy.spatial import cKDTree

    n_q, n_ref = (DEFAULT_SAMPLES[0] if n is None else n), DEFAULT_SAMPLES[1]
    if reference is not None and reference not in meshes:
        raise ValueError(f"reference {reference!r} is not one of the meshes {sorted(meshes)}")
    truth = truth_surface(gv, gf, n_ref, seed)
    g_pts, g_fid, _ = sample_surface(gv, gf, n_q, np.random.default_rng(seed + 1))
    band = border_band(gv, band)
    border = _border_points(gv, gf, band / 4)
    near = cKDTree(border).query(g_pts)[0] < band if border is not None else None
    samples = {}
    for name, (v, f) in meshes.items():
        pts = sample_surface(v, f, n_q, np.random.default_rng(seed + 2))[0]
        samples[name] = (pts, signed_distance(pts, truth), truth.tree.query(pts)[0])
    ref_tree = cKDTree(samples[reference][0]) if reference is not None else None
    by_scale = reference is not None and n_scale > 0 and len(meshes) > 1
    if by_scale:  # a prefix of the area-uniform points is area-uniform too (and shares their nearest-point query)
        s_pts, s_nrm = g_pts[:n_scale], face_normals(gv, gf)[g_fid[:n_scale]]
    offsets = {}
    out = {}
    for name, (v, f) in meshes.items():
        pts, sd, dist = samples[name]
        dense = sample_surface(v, f, n_ref, np.random.default_rng(seed + 3))[0]
        back, nearest = cKDTree(dense, balanced_tree=False, compact_nodes=False).query(g_pts)
        if by_scale:  # signed offset of this mesh from each truth point, along the truth's normal there
            offsets[name] = np.sum((dense[nearest[:n_scale]] - s_pts) * s_nrm, axis=1)
        e = SurfaceErrors(name, chamfer=float(0.5 * (dist.mean() + back.mean())), to_truth=float(dist.mean()),
                          from_truth=float(back.mean()), signed_mean=float(sd.mean()),
                          p95=float(np.percentile(dist, 95)))
        if near is not None and near.any() and (~near).any():
            e.from_truth_border, e.from_truth_interior = float(back[near].mean()), float(back[~near].mean())
            e.border_share = float(near.mean())
        if ref_tree is not None and name != reference:
            x = samples[reference][1][ref_tree.query(pts)[1]]
            xx = float(np.dot(x, x))
            if xx > 0:
                slope = float(np.dot(x, sd)) / xx
                e.input_error_left = slope
                e.input_error_correlation = float(np.corrcoef(x, sd)[0, 1]) if x.std() > 0 and sd.std() > 0 else None
                e.new_error_rms = float(np.sqrt(np.mean((sd - slope * x) ** 2)))
        out[name] = e
    if by_scale:
        size = float(np.linalg.norm(np.ptp(gv, axis=0)))
        for name, bands in error_left_by_scale(s_pts, offsets, size, reference).items():
            out[name].input_error_left_by_scale = bands
    return out


def signed_colours(d: np.ndarray, scale: float) -> np.ndarray:
    """Diverging colours of signed distances: blue behind the truth, white on it, red in front; ±``scale`` saturates."""
    import matplotlib

    return np.asarray(matplotlib.colormaps["RdBu_r"](0.5 + 0.5 * np.clip(d / scale, -1, 1))[:, :3], np.float32)


def error_maps(gv: np.ndarray, gf: np.ndarray, meshes: dict[str, tuple[np.ndarray, np.ndarray]], out: Path,
               scale: float | None = None) -> tuple[float, dict[str, Path]]:
    """``OUT/errors_<name>.ply`` per mesh: its vertices coloured by their signed distance to the truth
    (:func:`signed_colours`, one ``scale`` for all: default the 95th percentile of the first mesh's distances).
    Returns the scale and the files."""
    truth = truth_surface(gv, gf)
    d = {name: signed_distance(v, truth) for name, (v, _) in meshes.items()}
    if scale is None:
        scale = float(np.percentile(np.abs(next(iter(d.values()))), 95)) or 1.0
    files = {}
    for name, (v, f) in meshes.items():
        files[name] = write_ply(Path(out) / f"errors_{name}.ply", v, f, signed_colours(d[name], scale))
    return scale, files


#: colours of :func:`facing_maps`: the triangles facing against the truth, the others
FACING_COLOUR, PLAIN_COLOUR = (0.85, 0.0, 0.75), (0.72, 0.72, 0.72)


def facing_maps(gv: np.ndarray, gf: np.ndarray, meshes: dict[str, tuple[np.ndarray, np.ndarray]],
                out: Path) -> tuple[dict[str, Path], dict[str, np.ndarray]]:
    """``OUT/facing_<name>.ply`` per mesh: the triangles facing against the truth
    (:func:`~foundation.mesh_metrics.facing_mask`) in :data:`FACING_COLOUR`, the others grey. Each triangle gets its
    own three vertices (a PLY's colours are per vertex, and a shared vertex would blend a marked triangle into its
    neighbours). Returns the files and each mesh's per-triangle mask."""
    truth = truth_surface(gv, gf)
    files, masks = {}, {}
    for name, (v, f) in meshes.items():
        v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
        m = facing_mask(v, f, truth)
        col = np.where(m[:, None], FACING_COLOUR, PLAIN_COLOUR).astype(np.float32)
        files[name] = write_ply(Path(out) / f"facing_{name}.ply", v[f].reshape(-1, 3),
                                np.arange(3 * len(f)).reshape(-1, 3), np.repeat(col, 3, axis=0))
        masks[name] = m
    return files, masks


def most_facing_view(meshes: dict[str, tuple[np.ndarray, np.ndarray]], masks: dict[str, np.ndarray], cameras: list,
                     fov: float) -> int | None:
    """Index into ``cameras`` of the one that sees the most area facing against the truth, summed over ``meshes``
    (:func:`~inverse.morph.scene.views_seeing`); None when no camera sees any."""
    seen = np.zeros(len(cameras))
    for name, (v, f) in meshes.items():
        m = masks[name]
        if m.any():
            v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
            a = triangle_areas(v, f)
            # the facing triangles are cast against the whole mesh: the rest of it can hide them
            seen += views_seeing(v, f, cameras, fov, per_camera=True)[:, m] @ (a[m] / max(float(a.sum()), 1e-30))
    return int(np.argmax(seen)) if seen.max() > 0 else None


def error_figure(files: dict[str, Path], cameras: list, fov: float, scale: float | None, path: Path,
                 res: int = 384, spp: int = 128, row_labels: dict[str, str] | None = None,
                 marked: str | None = None) -> Path:
    """A figure of the signed-distance PLYs (rows) from ``cameras`` (columns), with the colour bar: each rendered
    two-sided diffuse under a uniform white sky, direct light only, so that the colours read as they are and
    ambient occlusion shows the shape. ``scale`` None (the PLYs of :func:`facing_maps`): no colour bar, a legend
    naming :data:`FACING_COLOUR` ``marked``. ``row_labels``: per file, its row's label (default its name)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import mi_plugins  # noqa: F401
    import mitsuba as mi

    from foundation.scene import mitsuba_log_level

    from .benchmark import sensor_dict

    rows, cols = len(files), len(cameras)
    imgs = {}
    for r, ply in enumerate(files.values()):
        with mitsuba_log_level(mi.LogLevel.Error):
            scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "path", "max_depth": 2},
                "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
                "mesh": {"type": "ply", "filename": str(ply), "bsdf": {"type": "twosided", "bsdf": {
                    "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}}}})
            depth = mi.load_dict({"type": "depth"})
        for c, cam in enumerate(cameras):
            sensor = mi.load_dict(sensor_dict(cam, res, fov))
            img = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=c))[..., :3]
            cover = np.array(mi.render(scene, sensor=sensor, integrator=depth, spp=4, seed=c))[..., 0] > 0
            imgs[r, c] = np.concatenate([img, cover[..., None]], axis=-1)
    # each column cropped to where any of its meshes covers the image (objects fill part of a benchmark's frame)
    boxes = []
    for c in range(cols):
        cover = np.any([imgs[r, c][..., 3] > 0 for r in range(rows)], axis=0)
        ys, xs = np.nonzero(cover)
        if not len(ys):
            boxes.append((0, res, 0, res))
            continue
        pad = max(2, res // 40)
        boxes.append((max(ys.min() - pad, 0), min(ys.max() + pad + 1, res), max(xs.min() - pad, 0),
                      min(xs.max() + pad + 1, res)))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols + 0.8, 3.2 * rows), squeeze=False)
    for (r, c), img in imgs.items():
        y0, y1, x0, x1 = boxes[c]
        ax = axes[r][c]
        # shown as stored, like a mesh viewer shows the PLY's colours (no sRGB curve: the colours are display values)
        ax.imshow(np.clip(img[y0:y1, x0:x1, :3], 0, 1))
        ax.set_xticks([]), ax.set_yticks([])
        if c == 0:
            name = list(files)[r]
            ax.set_ylabel((row_labels or {}).get(name, name))
    if scale is not None:
        sm = plt.cm.ScalarMappable(cmap="RdBu_r", norm=matplotlib.colors.Normalize(-scale, scale))
        fig.colorbar(sm, ax=axes, shrink=0.8, label="signed distance to the truth (blue: behind, red: in front)")
    else:
        from matplotlib.patches import Patch

        fig.legend(handles=[Patch(color=FACING_COLOUR, label=marked or "facing against the truth")],
                   loc="upper center", ncol=1, frameon=False)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


@dataclass
class ErrorReport:
    """``photoreal morph errors``: :class:`SurfaceErrors` of the benchmark's coarse input (``input``, the reference)
    and of each result, with the settings of the maps (``errors_<name>.ply``, ``errors.png``)."""

    benchmark: str
    band: float  #: width of the truth's border band
    scale: float  #: signed distance at which the maps' colours saturate
    views: list[int]  #: the held-out cameras of the figure
    meshes: list[SurfaceErrors]
    files: dict[str, str]
    #: the cameras of the facing figure: the benchmark's camera that sees the most area facing against the truth
    #: (:func:`most_facing_view`; omitted when none does), then :attr:`views`
    facing_views: list[int] | None = None


def facing_by_views(v: np.ndarray, f: np.ndarray, truth, seen: np.ndarray) -> tuple[float, dict[str, float], float]:
    """The area share facing against the truth, that share by the number of views seeing each triangle ``seen``
    ("0", "1-2", "3+"), and the share no view sees."""
    against = facing_mask(np.asarray(v, np.float64), f, truth)
    area = triangle_areas(v, f)
    total = max(float(area.sum()), 1e-30)
    groups = {"0": seen == 0, "1-2": (seen >= 1) & (seen <= 2), "3+": seen >= 3}
    by = {k: float(area[against & m].sum() / total) for k, m in groups.items()}
    return float(area[against].sum() / total), by, float(area[seen == 0].sum() / total)


def _benchmark_meshes(bench, results: dict[str, Path]) -> tuple[tuple[np.ndarray, np.ndarray], dict]:
    """The benchmark's truth, and its coarse input (``input``) with ``results`` (name → mesh file), loaded."""
    from foundation.mesh import load_mesh_any

    if "input" in results:
        raise ValueError("'input' names the benchmark's coarse input; give the results other names")
    meshes = {"input": load_mesh_any(bench.coarse), **{k: load_mesh_any(p) for k, p in results.items()}}
    return load_mesh_any(bench.ground_truth), meshes


def benchmark_surface_errors(bench, results: dict[str, Path], band: float | None = None) -> dict[str, SurfaceErrors]:
    """:func:`surface_errors` of ``results`` (name → mesh file) against a morph benchmark's truth, its coarse input
    (``input``) the reference."""
    (gv, gf), meshes = _benchmark_meshes(bench, results)
    return _with_facing(bench, gv, gf, meshes, surface_errors(gv, gf, meshes, reference="input", band=band))


def _with_facing(bench, gv, gf, meshes: dict, errs: dict[str, SurfaceErrors]) -> dict[str, SurfaceErrors]:
    """``errs`` with each mesh's facing area, split by the benchmark's training views that see it."""
    meta = bench.meta
    truth = truth_surface(np.asarray(gv, np.float64), gf)
    train = [meta.cameras[i] for i in meta.train]
    for name, (v, f) in meshes.items():
        v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
        e = errs[name]
        e.facing_area, e.facing_area_by_views, e.unseen_area = facing_by_views(v, f, truth,
                                                                               views_seeing(v, f, train, meta.fov))
    return errs


def benchmark_errors(bench, results: dict[str, Path], out: Path, band: float | None = None,
                     res: int = 384) -> ErrorReport:
    """:func:`surface_errors`, :func:`error_maps`, :func:`facing_maps` and their figures (``errors.png``,
    ``facing.png``, :func:`error_figure`) of ``results`` (name → mesh file) against a morph benchmark's truth, with
    its coarse input as the reference; writes ``OUT/errors.json`` last (atomically: a report on disk means its maps
    are there). Every mesh is read before ``out`` is made."""
    from foundation.files import write_json

    (gv, gf), meshes = _benchmark_meshes(bench, results)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = bench.meta
    errs = _with_facing(bench, gv, gf, meshes, surface_errors(gv, gf, meshes, reference="input", band=band))
    scale, files = error_maps(gv, gf, meshes, out)
    # the first held-out view and the held-out view farthest from it (the other side, for an open sheet its back)
    eyes = {i: np.asarray(meta.cameras[i].eye, np.float64) for i in meta.test}
    first = meta.test[0]
    other = max(meta.test, key=lambda i: float(np.linalg.norm(eyes[i] - eyes[first])))
    views = [first] if other == first else [first, other]
    fig = error_figure(files, [meta.cameras[i] for i in views], meta.fov, scale, out / "errors.png", res=res)
    # where the orientation is wrong: small areas (a crease, a pleat) that the signed distance does not show
    facing_files, masks = facing_maps(gv, gf, meshes, out)
    most = most_facing_view(meshes, masks, meta.cameras, meta.fov)
    facing_views = ([most] if most is not None and most not in views else []) + views
    labels = {k: f"{k}: {100 * errs[k].facing_area:.3f} %" for k in facing_files}
    facing_fig = error_figure(facing_files, [meta.cameras[i] for i in facing_views], meta.fov, None,
                              out / "facing.png", res=res, row_labels=labels,
                              marked="facing against the truth (row: its share of the area)")
    report = ErrorReport(str(bench.path), border_band(gv, band), scale, views, list(errs.values()),
                         {**{k: str(p) for k, p in files.items()}, "figure": str(fig),
                          **{f"facing_{k}": str(p) for k, p in facing_files.items()}, "facing_figure": str(facing_fig)},
                         facing_views)
    write_json(out / "errors.json", report)
    return report
