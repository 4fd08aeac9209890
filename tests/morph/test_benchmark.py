"""Morph benchmarks: their contents, the truth scene and truth start, framing, a user's HDRI, the suite's meshes, bad photos."""


import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from foundation.errors import UsageError
from foundation.mesh import MeshError

from foundation.mesh_metrics import chamfer
from inverse.morph import MorphSettings, run_morph
from foundation.mesh import load_mesh_any, write_ply
from inverse.morph import MorphBenchmarkSettings, load_morph_benchmark, make_morph_benchmark

from morph_shapes import sphere

ARMADILLO = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"


def test_benchmark_contents(small_armadillo):
    b = small_armadillo
    assert len(b.photos) == 8 and b.photos["view00"].shape == (48, 48, 3)
    assert b.meta.test == [3, 7] and len(b.meta.train) == 6
    v, f = load_mesh_any(b.coarse)
    assert 600 < len(v) < 1000
    gv, gf = load_mesh_any(b.ground_truth)
    assert chamfer(v, f, gv, gf, n=20_000, n_ref=200_000)["chamfer"] > 0.003  # really degraded


def test_village_benchmark_has_chimney_artifacts(tmp_path):
    s = MorphBenchmarkSettings(n_views=4, resolution=32, spp=4, coarse_vertices=800, n_houses=3)
    b = load_morph_benchmark(make_morph_benchmark("village", tmp_path / "v", s, show_progress=False))
    d = b.meta.degradation
    assert len(d.chimneys_cut) + len(d.chimneys_floating) == 3
    assert (b.path / "tex_brick.png").is_file() and (b.path / "tex_grass.png").is_file()
    # the auto rule sees a man-made scene: its ground plane holds more than the threshold of the area
    from inverse.morph import dominant_plane_fraction

    v, f = load_mesh_any(b.coarse)
    assert dominant_plane_fraction(v, f) > 1.5 * MorphSettings().planarity_auto_threshold
    _assert_truth_scene_reproduces_photos(b)


def _assert_truth_scene_reproduces_photos(b, ids=(0, 1)):
    """Oracle: the stored photos themselves. The truth's scene rendered at a photo's camera, spp and seed gives that
    photo exactly once rounded as the photos are stored (half floats)."""
    import mitsuba as mi

    from inverse.morph import sensor_dict, truth_scene

    m = b.meta
    scene = truth_scene(b)
    for i in ids:
        sensor = mi.load_dict(sensor_dict(m.cameras[i], m.resolution, m.fov))
        img = np.array(mi.render(scene, sensor=sensor, spp=m.settings.spp, seed=m.settings.seed + i))[..., :3]
        np.testing.assert_array_equal(img.astype(np.float16).astype(np.float32), b.photo(i))


def test_truth_scene_reproduces_an_objects_photos(small_armadillo):
    _assert_truth_scene_reproduces_photos(small_armadillo)


def test_truth_start_benchmark_starts_at_the_answer(small_armadillo, tmp_path):
    # The floor part of the bench: the same photos and split, the ground truth (with its own colours) as input.
    from foundation.mesh import read_ply
    from inverse.morph import start_mesh, truth_start_benchmark
    from photoreal.benchmarks.morph.bench import floor_row

    b = load_morph_benchmark(truth_start_benchmark(small_armadillo.path, tmp_path / "t"))
    gv, gf, _ = read_ply(b.ground_truth)
    v, f, c = read_ply(b.coarse)
    np.testing.assert_array_equal(v, gv)
    np.testing.assert_array_equal(f, gf)
    _, _, truth_colours = read_ply(small_armadillo.path / "gt_part0.ply")
    np.testing.assert_array_equal(c, truth_colours)
    assert b.meta.train == small_armadillo.meta.train and b.meta.test == small_armadillo.meta.test
    for k, photo in small_armadillo.photos.items():
        np.testing.assert_array_equal(b.photos[k], photo)
    # a copy, not a move: the source benchmark is untouched; its coarse input is degraded, this one is not
    assert load_mesh_any(small_armadillo.coarse)[0].shape != gv.shape
    s = MorphSettings(iterations=3, resolution=48, min_vertices=None, check_every=3, validation_fraction=0.5,
                      lambda_select=())
    frozen = run_morph(b, tmp_path / "frozen", replace(s, lr=0.0), show_progress=False)
    start_v = start_mesh(b, s)[1][0]  # lr 0: the (remeshed) start does not move, only colours are fitted
    np.testing.assert_allclose(load_mesh_any(tmp_path / "frozen" / "morphed.ply")[0], start_v, atol=1e-6)
    row = floor_row(run_morph(b, tmp_path / "run", s, show_progress=False), frozen)
    # the truth against itself is the estimator's floor (~8e-4 here: the spacing of its samples), far below the
    # degraded input's Chamfer measured by the same estimator
    cv, cf = load_mesh_any(small_armadillo.coarse)
    degraded = chamfer(cv, cf, gv, gf)["chamfer"]
    assert row["chamfer_truth"] < 0.2 * degraded and row["trace_chamfer"]["start"] < 0.3 * degraded
    assert row["iterations"] == 3 and row["photos_prefer_drift"] == (
        row["validation_l1"]["end"] < row["validation_l1"]["truth_colours_fitted"]
        and row["trace_chamfer"]["end"] > row["trace_chamfer"]["start"])


def test_bad_inputs_leave_nothing(tmp_path):
    with pytest.raises(MeshError, match="nope.ply: no such mesh file"):
        make_morph_benchmark(tmp_path / "nope.ply", tmp_path / "b", show_progress=False)
    with pytest.raises(UsageError, match="HDRI 'nowhere': not a bundled environment map"):
        make_morph_benchmark(ARMADILLO, tmp_path / "b", MorphBenchmarkSettings(hdri="nowhere"), show_progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(UsageError, match="not a morph benchmark folder"):
        load_morph_benchmark(tmp_path)


def test_object_views_frame_the_whole_silhouette_and_the_source_is_a_hash(small_armadillo):
    from foundation.files import file_digest
    from inverse.morph.benchmark import silhouette_margins

    meta = small_armadillo.meta
    margins = silhouette_margins(small_armadillo, list(range(len(meta.cameras))))
    # framing_margin 0.1 of the half-width (2.4 px at 48²); a pixel of quantisation either way
    assert min(margins) >= 0.1 - 2 / 24, margins
    assert max(margins) < 0.6  # and the object is not lost in the frame
    assert meta.source == "armadillo.ply" and meta.source_sha256 == file_digest(ARMADILLO, 64)
    els = [np.degrees(np.arcsin((c.eye[1] - c.target[1]) / np.linalg.norm(np.subtract(c.eye, c.target))))
           for c in meta.cameras]
    assert min(els) < 0 and max(els) > 45  # sides, a little underside, and the top


def test_a_users_hdri_travels_with_the_benchmark(tmp_path):
    import shutil

    from foundation.assets import HDRI_DIR
    from inverse.morph.scene import morph_scene

    mine = tmp_path / "my_light.exr"
    shutil.copyfile(HDRI_DIR / "forest.exr", mine)
    s = MorphBenchmarkSettings(n_views=4, resolution=16, spp=2, coarse_vertices=300, hdri=str(mine))
    made = make_morph_benchmark(ARMADILLO, tmp_path / "b", s, show_progress=False)
    moved = tmp_path / "elsewhere"
    made.rename(moved)
    mine.unlink()  # the benchmark no longer needs the user's file
    b = load_morph_benchmark(moved)
    assert b.meta.hdri == str(moved / "hdri.exr") and (moved / "hdri.exr").is_file()
    assert morph_scene(b.coarse, "lit", b.meta.hdri) is not None
    assert json.loads((moved / "morph_benchmark.json").read_text())["settings"]["hdri"] == "hdri.exr"  # no path
    bundled = make_morph_benchmark(ARMADILLO, tmp_path / "d", replace(s, hdri=str(HDRI_DIR / "forest.exr")),
                                   show_progress=False)
    assert load_morph_benchmark(bundled).meta.hdri == "forest" and not (bundled / "hdri.exr").exists()
    for bad, match in ((tmp_path / "none.exr", "none.exr: no such HDRI file"),
                       ("no_such_name", "not a bundled environment map")):
        with pytest.raises(UsageError, match=match):
            make_morph_benchmark(ARMADILLO, tmp_path / "c", replace(s, hdri=str(bad)), show_progress=False)
    corrupt = tmp_path / "corrupt.exr"
    corrupt.write_bytes(b"not an exr")
    with pytest.raises(Exception, match="corrupt.exr"):
        make_morph_benchmark(ARMADILLO, tmp_path / "c", replace(s, hdri=str(corrupt)), show_progress=False)
    assert not (tmp_path / "c").exists()


def test_generated_suite_meshes_are_closed_outward_and_of_known_volume(tmp_path):
    from inverse.morph.suite import SUITE, UNSEEN, bracket_mesh, pedestal_mesh, suite_mesh, table_mesh

    def volume(v, f):  # divergence theorem: positive for a closed outward-oriented surface
        return float(np.sum(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]]))) / 6)

    v, f = table_mesh()
    assert volume(v, f) == pytest.approx(1.2 * 0.06 * 0.8 + 4 * 0.05 * 0.05 * 0.7, rel=1e-9)
    v, f = pedestal_mesh(n_theta=64)
    y = np.linspace(0.1, 1.0, 20001)
    t = (y - 0.1) / 0.9
    r = 0.22 + 0.12 * np.sin(np.pi * t * 1.5) ** 2 - 0.08 * t + 0.05 * np.exp(-((t - 0.95) / 0.05) ** 2)
    polygon = 64 * np.sin(2 * np.pi / 64) / (2 * np.pi)  # a 64-gon's area / the circle's
    vase = polygon * np.pi * np.trapezoid(r**2, y)
    assert volume(v, f) == pytest.approx(1.6 * 0.1 * 1.6 + vase, rel=2e-3)  # the profile's chords: < 0.2 %
    # marching cubes at 0.015: within 0.2 % of the closed form 1.6·0.2·0.8 + 0.3·1.0·0.8 − 0.3·0.1·0.8 − π·0.15²·0.3
    v, f = bracket_mesh()
    assert volume(v, f) == pytest.approx(0.256 + 0.24 - 0.024 - np.pi * 0.15**2 * 0.3, rel=2e-3)
    for name in SUITE + UNSEEN:
        load_mesh_any(suite_mesh(name, tmp_path))
    with pytest.raises(UsageError, match="unknown case 'nope'.*bracket"):
        suite_mesh("nope", tmp_path)
    from photoreal.benchmarks.morph.bench import MorphBenchSettings

    assert MorphBenchSettings(suite=UNSEEN).suite == UNSEEN  # the bench runs them by name


def test_a_benchmark_can_photograph_its_truth_flat_as_the_chamfer_measures_it(tmp_path):
    """``truth_normals="face"``: the photos shade each triangle flat. Oracles: the truth's scene still reproduces the
    stored photos exactly (it reads the setting), and on a truth with few vertices (josie, 1,600) the flat photos
    differ from the smooth ones made with the same seeds (same noise) by more than their rounding; an old benchmark
    (no such field) loads as "vertex"; a bad value is named."""
    josie = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "face" / "cyberheads" / "josie.obj"
    s = MorphBenchmarkSettings(n_views=4, resolution=32, spp=8, coarse_vertices=300)
    smooth = load_morph_benchmark(make_morph_benchmark(josie, tmp_path / "smooth", s, show_progress=False))
    flat = load_morph_benchmark(make_morph_benchmark(josie, tmp_path / "flat", replace(s, truth_normals="face"),
                                                     show_progress=False))
    _assert_truth_scene_reproduces_photos(flat)
    diff = np.mean([np.abs(flat.photo(i) - smooth.photo(i)).mean() for i in range(4)])
    assert diff > 10 * 2.0 ** -11 * np.mean([smooth.photo(i).mean() for i in range(4)]), diff
    meta = json.loads((tmp_path / "smooth" / "morph_benchmark.json").read_text())
    meta["settings"].pop("truth_normals")
    (tmp_path / "smooth" / "morph_benchmark.json").write_text(json.dumps(meta))
    assert load_morph_benchmark(tmp_path / "smooth").meta.settings.truth_normals == "vertex"
    with pytest.raises(UsageError, match="truth_normals"):
        MorphBenchmarkSettings(truth_normals="phong")


def test_a_photo_with_non_finite_pixels_is_rendered_again_or_refused(tmp_path, monkeypatch):
    """A path-traced photo can come back with NaN pixels (the bracket's benchmark at seed 3: 3 pixels of view 5,
    which made every validation L1 of its runs NaN). make-benchmark renders such a view again with another seed
    (the first render of every view keeps its own seed, so benchmarks without such pixels are unchanged); a stored
    benchmark with one is refused by name, not fitted."""
    import mitsuba as mi

    from foundation import imageio

    v, f = sphere(1.0, 16)
    src = write_ply(tmp_path / "ball.ply", v, f)
    bs = MorphBenchmarkSettings(n_views=4, resolution=24, spp=4, coarse_vertices=400)
    clean = load_morph_benchmark(make_morph_benchmark(src, tmp_path / "clean", bs, show_progress=False))
    real, calls = mi.render, []

    def render(scene, *a, seed=0, **kw):  # the first photo of view 1 comes back with a NaN pixel
        img = real(scene, *a, seed=seed, **kw)
        calls.append(seed)
        if seed == bs.seed + 1 and calls.count(seed) == 1 and kw.get("spp") == bs.spp:
            arr = np.array(img)
            arr[3, 4, 0] = np.nan
            return mi.TensorXf(arr)
        return img

    monkeypatch.setattr(mi, "render", render)
    again = load_morph_benchmark(make_morph_benchmark(src, tmp_path / "again", bs, show_progress=False))
    monkeypatch.undo()
    assert bs.seed + 1 + 1_000_003 in calls  # view 1 rendered again with the next seed
    assert np.isfinite(again.photos["view01"]).all()
    assert not np.array_equal(again.photos["view01"], clean.photos["view01"])
    for k in ("view00", "view02", "view03"):  # the other views: their own seed, bit for bit
        np.testing.assert_array_equal(again.photos[k], clean.photos[k])
    # a stored benchmark with such a pixel: refused by name
    ch = imageio.read_exr(tmp_path / "clean" / "photos.exr")
    photos = {f"view{i:02d}": imageio.exr_layer(ch, f"view{i:02d}") for i in range(4)}
    photos["view02"][5, 6, 1] = np.nan
    imageio.write_exr(tmp_path / "clean" / "photos.exr", photos, half=True)
    with pytest.raises(UsageError, match=r"photos.exr: non-finite pixels in view02 \(1\); remake the benchmark"):
        load_morph_benchmark(tmp_path / "clean")
