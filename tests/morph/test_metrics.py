"""Morph metrics and where a result lies: Chamfer, spikes, signed distance, error reports by scale, the views that see a surface, facing maps."""


from pathlib import Path

import numpy as np
import pytest


from foundation.mesh_metrics import chamfer, spikes

from morph_shapes import outward_sphere, sphere

ARMADILLO = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"




def test_chamfer_of_concentric_spheres_is_their_gap():
    v, f = sphere(1.0)
    ch = chamfer(v * 1.1, f, v, f, n=20_000, n_ref=400_000)
    # Closed form: every point of one sphere is 0.1 from the other. The tessellated spheres and the
    # sampling floor (~1e-3 here) add a little: 5% tolerance.
    assert abs(ch["chamfer"] - 0.1) < 0.005, ch
    assert ch["normal_consistency"] > 0.98
    self_ch = chamfer(v, f, v, f, n=20_000, n_ref=400_000)["chamfer"]
    assert self_ch < 0.01 * 0.1 * 3  # estimator floor well below the gap being measured


def test_spikes_and_inverted_triangles():
    v, f = sphere(1.0, 10)
    moved = v.copy()
    moved[50] *= 3.0  # one vertex pulled far out: a spike
    sp = spikes(v, moved, f)
    assert sp["spike_vertices"] == 1
    flipped = v.copy()
    a, b, c = f[100]
    flipped[a] = v[b] + 1.5 * (v[a] - v[b]) * -1  # reflect one vertex through its neighbour: fold
    assert spikes(v, flipped, f)["inverted_triangles"] >= 1
    # A region moving together (an eroded part growing back) is not a spike, though it moved far.
    cap = v[:, 1] > 0.5
    grown = v.copy()
    grown[cap] += [0.0, 2.0, 0.0]
    sp = spikes(v, grown, f)
    assert sp["far_moved_vertices"] == int(cap.sum()) and sp["spike_vertices"] < 0.5 * cap.sum()


def test_chamfer_reuses_the_truths_samplings_without_changing_results():
    import foundation.mesh_metrics as mm

    v, f = sphere(1.0, 20)
    a = v * 1.05
    mm._REFERENCES.clear()
    mm._RESULTS.clear()
    cold = chamfer(a, f, v, f, n=5_000, n_ref=50_000)
    assert len(mm._REFERENCES) == 1 and len(mm._RESULTS) == 1
    mm._RESULTS.clear()
    warm = chamfer(a, f, v, f, n=5_000, n_ref=50_000)
    assert warm == cold  # the cache holds the very arrays a fresh sampling makes: bit-identical
    # a repeat with equal arrays (other objects) is answered from the results; a caller's edit does not reach them
    again = chamfer(a.copy(), f.copy(), v.copy(), f.copy(), n=5_000, n_ref=50_000)
    assert again == cold and len(mm._RESULTS) == 1
    again["chamfer"] = -1.0
    assert chamfer(a, f, v, f, n=5_000, n_ref=50_000) == cold
    # keyed by the mesh's content, not its identity: a moved truth is sampled anew and scores differently
    moved = v.copy()
    moved[:, 0] += 0.5
    assert chamfer(a, f, moved, f, n=5_000, n_ref=50_000)["chamfer"] > cold["chamfer"] + 0.1
    assert chamfer(a, f, v, f, n=5_000, n_ref=50_000) == cold and len(mm._REFERENCES) == 2
    b = a.copy()
    b[0] *= 1.01  # one vertex moved: a new result, not the remembered one
    assert chamfer(b, f, v, f, n=5_000, n_ref=50_000) != cold
    # the dense truth sampling of the orientation check: one object per truth content, equal to a fresh one
    t1, t2 = mm.truth_surface(v, f, n=20_000), mm.truth_surface(v.copy(), f.copy(), n=20_000)
    fresh = mm.TruthSurface(v, f, n=20_000)
    assert t1 is t2 and np.array_equal(t1.normals, fresh.normals) and np.array_equal(t1.tree.data, fresh.tree.data)
    # Oracle, as the concentric-spheres test: every point of one sphere lies 0.05 from the other (5 % tolerance)
    assert abs(cold["chamfer"] - 0.05) < 0.0025




def test_signed_distance_of_concentric_spheres_is_their_gap_with_its_side():
    """Closed form: a point at radius r lies r − 1 from the unit sphere, in front (+) of its outward normals
    outside, behind (−) inside; tolerance 0.003 (the tessellation's sag at n = 40 is 0.0008, the sampling's
    spacing below that)."""
    from foundation.mesh_metrics import signed_distance, truth_surface

    v, f = outward_sphere()
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    truth = truth_surface(v, f)
    np.testing.assert_allclose(signed_distance(1.1 * x, truth), 0.1, atol=0.003)
    np.testing.assert_allclose(signed_distance(0.9 * x, truth), -0.1, atol=0.003)


def test_surface_errors_split_the_error_into_what_the_input_left_and_what_is_new():
    """Oracles with closed forms on the unit sphere: an input bumped along its normals by b, a result with 0.4 b
    keeps 0.4 of the input's error (slope 0.4 ± 0.03, correlation > 0.97, almost no new error), one with 0.4 b plus
    another field e splits as the surface's least-squares fit says (slope ± 0.03, new error ± 10 %); both Chamfer directions of a uniformly
    offset sphere are its offset; a closed truth has no border figures."""
    from foundation.mesh import vertex_normals
    from foundation.mesh_metrics import triangle_areas
    from inverse.morph.errors import surface_errors

    v, f = outward_sphere()
    n = vertex_normals(v, f)

    def field(k, phase):
        return np.sin(k[0] * v[:, 0] + phase) * np.cos(k[1] * v[:, 1]) * np.sin(k[2] * v[:, 2] + 1.0)

    b = 0.05 * field((3, 2, 4), 0.3)
    e = 0.02 * field((5, 6, 2), 1.7)
    meshes = {"input": (v + b[:, None] * n, f), "kept": (v + 0.4 * b[:, None] * n, f),
              "new": (v + (0.4 * b + e)[:, None] * n, f), "offset": (1.03 * v, f)}
    r = surface_errors(v, f, meshes, reference="input", n=20_000)
    assert r["input"].input_error_left is None and r["input"].from_truth_border is None
    assert abs(r["kept"].input_error_left - 0.4) < 0.03 and r["kept"].input_error_correlation > 0.97
    assert r["kept"].new_error_rms < 0.003
    # with e: the least-squares split over the surface, by quadrature (vertex values, each vertex a third of its
    # triangles' area) — e is not orthogonal to b on the sphere, so the slope is 0.4 + <b, e> / <b, b>
    w = np.zeros(len(v))
    np.add.at(w, f.ravel(), np.repeat(triangle_areas(v, f) / 3, 3))
    slope = 0.4 + np.sum(w * b * e) / np.sum(w * b * b)
    rms = float(np.sqrt(np.sum(w * (0.4 * b + e - slope * b) ** 2) / w.sum()))
    assert abs(r["new"].input_error_left - slope) < 0.03, (r["new"].input_error_left, slope)
    assert abs(r["new"].new_error_rms - rms) < 0.1 * rms, (r["new"].new_error_rms, rms)
    assert abs(r["offset"].to_truth - 0.03) < 0.002 and abs(r["offset"].from_truth - 0.03) < 0.002
    assert abs(r["offset"].signed_mean - 0.03) < 0.002 and abs(r["offset"].chamfer - 0.03) < 0.002
    with pytest.raises(ValueError, match="reference 'nope'"):
        surface_errors(v, f, meshes, reference="nope", n=1000)
    # a truth stored unwelded (three vertices of its own per triangle) is still closed: no border figures
    vu, fu = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
    assert surface_errors(vu, fu, {"s": (v, f)}, n=1000)["s"].from_truth_border is None


def test_error_left_by_scale_separates_broad_from_fine_flaws():
    """Closed-form oracle on the unit sphere (bands' σ in units of its bounding-box diagonal, 2√3): an input bumped
    along its normals by a broad field (the l = 2 zonal harmonic, 0.03) plus a fine one (wavelength 0.2, 0.004), and a
    result keeping 0.9 of the broad and 0.2 of the fine. The coarse bands (σ > 0.04) hold the broad field (rms > 5 ×
    the finest band's) and keep 0.9 ± 0.03 of it; the two finest bands keep 0.2 — measured 0.26 / 0.32, biased up
    because both meshes' offsets are taken at the same sample points (a common noise floor, kept at 1) and a little of
    the broad field leaks down — so they are checked in [0.15, 0.4], below the broad bands by > 0.5. The input itself
    as a result keeps exactly 1 in every band."""
    from foundation.mesh import vertex_normals
    from inverse.morph.errors import surface_errors

    v, f = outward_sphere(121)
    n = vertex_normals(v, f)
    broad = 0.03 * 0.5 * (3 * v[:, 1] ** 2 - 1)
    k = 2 * np.pi / 0.2
    fine = 0.004 * np.sin(k * v[:, 0]) * np.sin(k * v[:, 1] + 0.5) * np.sin(k * v[:, 2] + 1.0)
    bumped = v + (broad + fine)[:, None] * n
    meshes = {"input": (bumped, f), "result": (v + (0.9 * broad + 0.2 * fine)[:, None] * n, f), "same": (bumped, f)}
    r = surface_errors(v, f, meshes, reference="input", n=20_000, n_scale=8000)
    assert r["input"].input_error_left_by_scale is None
    bands = {b.band: b for b in r["result"].input_error_left_by_scale}
    assert list(bands) == ["<0.01", "0.01-0.02", "0.02-0.04", "0.04-0.08", ">0.08", "mean"]
    for name in ("0.04-0.08", ">0.08"):
        assert bands[name].slope == pytest.approx(0.9, abs=0.03), bands[name]
    assert bands[">0.08"].rms_input > 5 * bands["<0.01"].rms_input
    for name in ("<0.01", "0.01-0.02"):
        assert 0.15 <= bands[name].slope <= 0.4, bands[name]
        assert bands[name].slope < bands[">0.08"].slope - 0.5
    for b in r["same"].input_error_left_by_scale:
        assert b.slope == pytest.approx(1.0, abs=1e-9) and b.rms_result == pytest.approx(b.rms_input, rel=1e-9)
    assert surface_errors(v, f, meshes, reference="input", n=2000, n_scale=0)["result"].input_error_left_by_scale \
        is None  # off


def test_surface_errors_find_what_a_result_misses_at_an_open_border():
    """A hemisphere (open at y = 0) as the truth and the same cap cropped at y > 0.02: what the result misses lies
    within the border band (0.05), so that band's truth points are far from it and the rest are not; the band holds
    about 5 % of the area (closed form: a zone of height h on the unit sphere is h of the hemisphere's area)."""
    from inverse.morph.errors import surface_errors

    v, f = outward_sphere(61)  # 60 intervals of θ: the equator is a row of the grid
    cap = f[v[f].mean(axis=1)[:, 1] > 0]
    cropped = f[v[f].min(axis=1)[:, 1] > 0.02]
    r = surface_errors(v, cap, {"cap": (v, cap), "cropped": (v, cropped)}, band=0.05, n=40_000)
    assert abs(r["cap"].border_share - 0.05) < 0.005, r["cap"].border_share
    # the cap against itself is the estimator's floor (two samplings of one surface); cropping adds only in the band
    floor = r["cap"].from_truth
    assert r["cropped"].from_truth_border > 3 * floor and r["cropped"].from_truth_interior < 1.2 * floor


def test_views_seeing_a_sphere_is_the_spherical_cap_the_camera_sees():
    """Closed form: a camera at distance d from a unit sphere sees the cap above z = 1/d, (1 − 1/d)/2 of the area;
    either side of a triangle counts; a sphere in front hides part of the one behind; a narrow view sees no centroid
    outside its frustum."""
    from foundation.mesh_metrics import triangle_areas
    from inverse.morph import Camera
    from inverse.morph.errors import views_seeing

    v, f = sphere(1.0, 60)
    a = triangle_areas(v, f)
    front, back = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)), Camera((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    seen = views_seeing(v, f, [front], 60.0)
    assert a[seen == 1].sum() / a.sum() == pytest.approx(1 / 3, abs=0.01)
    flipped = views_seeing(v, f[:, ::-1], [front], 60.0)  # seen the same, but for grazing rays at the rim
    assert a[flipped != seen].sum() / a.sum() < 0.002
    both = views_seeing(v, f, [front, back], 60.0)
    assert both.max() == 1 and a[both == 1].sum() / a.sum() == pytest.approx(2 / 3, abs=0.02)
    each = views_seeing(v, f, [front, back], 60.0, per_camera=True)  # the same casts, kept apart
    assert each.shape == (2, len(f)) and np.array_equal(each[0], seen == 1) and np.array_equal(each.sum(0), both)
    # a half-size sphere at z = 2 between the camera (now at z = 4) and the unit sphere
    vs, fs = sphere(0.5, 40)
    vv, ff = np.r_[v, vs + [0.0, 0.0, 2.0]], np.r_[f, fs + len(v)]
    cam = Camera((0.0, 0.0, 4.0), (0.0, 0.0, 0.0))
    alone = a[views_seeing(v, f, [cam], 60.0) == 1].sum() / a.sum()
    seen2 = views_seeing(vv, ff, [cam], 60.0)
    big, small = seen2[:len(f)], seen2[len(f):]
    a_small = triangle_areas(vs, fs)
    assert alone == pytest.approx((1 - 1 / 4) / 2, abs=0.01)
    assert a[big == 1].sum() / a.sum() < alone - 0.05  # the small sphere hides a part of the big one's cap
    assert a_small[small == 1].sum() / a_small.sum() == pytest.approx((1 - 0.5 / 2) / 2, abs=0.015)
    narrow = views_seeing(v, f, [front], 10.0)
    c = v[f].mean(axis=1)[narrow == 1]
    assert len(c) > 0 and np.all(np.abs(c[:, :2]) <= np.tan(np.radians(5.0)) * (3.0 - c[:, 2:3]) + 1e-9)


def test_facing_maps_mark_the_facing_triangles_and_the_view_that_sees_them(tmp_path):
    """A unit sphere against itself with the triangles of its +z cap turned inside out: the map marks exactly the
    triangles :func:`~foundation.mesh_metrics.facing_against_truth` counts (oracle: the metric), each triangle in
    one colour; of a camera on +z and one on −z the +z one sees them; the sphere as it is marks none, and no view
    is chosen."""
    from foundation.mesh import read_ply_colours
    from foundation.mesh_metrics import facing_against_truth, truth_surface
    from inverse.morph import Camera
    from inverse.morph.errors import FACING_COLOUR, facing_maps, most_facing_view

    v, f = outward_sphere(40)
    cap = v[f].mean(axis=1)[:, 2] > 0.8
    bad = f.copy()
    bad[cap] = bad[cap][:, ::-1]
    meshes = {"turned": (v, bad), "plain": (v, f)}
    files, masks = facing_maps(v, f, meshes, tmp_path)
    want = facing_against_truth(v, bad, truth_surface(v, f))
    assert want["count"] == cap.sum() > 20 and np.array_equal(masks["turned"], cap) and not masks["plain"].any()
    pv, pf, pc = read_ply_colours(files["turned"])
    assert len(pv) == 3 * len(f) and np.allclose(pc[0::3], pc[1::3]) and np.allclose(pc[0::3], pc[2::3])
    marked = np.all(np.abs(pc[0::3] - FACING_COLOUR) < 1e-2, axis=1)
    assert np.array_equal(marked, cap)
    cams = [Camera((0.0, 0.0, -3.0), (0.0, 0.0, 0.0)), Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0))]
    assert most_facing_view(meshes, masks, cams, 60.0) == 1
    assert most_facing_view({"plain": (v, f)}, {"plain": masks["plain"]}, cams, 60.0) is None


def test_morph_errors_cli_writes_maps_a_figure_and_a_report(small_armadillo, tmp_path, capsys):
    """The command on the small benchmark with its coarse input as a 'result' (what a run that changed nothing
    leaves): the report's input and result rows agree, keeping all of the input's error (slope 1), the maps carry
    one colour per vertex and the figure exists; a missing mesh and a bad band are named, nothing written."""
    import json

    from foundation.mesh import read_ply_colours
    from photoreal.cli import main

    b = small_armadillo
    out = tmp_path / "err"
    assert main(["morph", "errors", str(b.path), str(b.coarse), "--out", str(out), "--json",
                 str(tmp_path / "e.json")]) == 0
    rep = json.loads((out / "errors.json").read_text())
    assert json.loads((tmp_path / "e.json").read_text()) == rep
    rows = {m["name"]: m for m in rep["meshes"]}
    assert set(rows) == {"input", "coarse"}
    assert abs(rows["coarse"]["input_error_left"] - 1.0) < 1e-6 and rows["coarse"]["new_error_rms"] < 1e-9
    assert rows["coarse"]["chamfer"] == pytest.approx(rows["input"]["chamfer"], rel=0.05)
    # orientation against the truth, split by how many training views see it: the same mesh, the same figures
    assert rows["coarse"]["facing_area"] == rows["input"]["facing_area"] > 0
    assert rows["coarse"]["facing_area_by_views"] == rows["input"]["facing_area_by_views"]
    assert sum(rows["input"]["facing_area_by_views"].values()) == pytest.approx(rows["input"]["facing_area"])
    assert 0 <= rows["input"]["unseen_area"] < 0.5
    v, f, c = read_ply_colours(out / "errors_coarse.ply")
    assert len(c) == len(v) and c.std() > 0
    assert (out / "errors.png").stat().st_size > 10_000
    # where it faces against the truth: one PLY per mesh, their figure, its cameras (the held-out pair, after the
    # camera that sees the most of it when that is another)
    assert (out / "facing.png").stat().st_size > 10_000 and (out / "facing_coarse.ply").is_file()
    assert rep["facing_views"][-len(rep["views"]):] == rep["views"]
    assert len(rep["facing_views"]) == len(set(rep["facing_views"])) <= len(rep["views"]) + 1
    capsys.readouterr()
    assert main(["morph", "errors", str(b.path), str(tmp_path / "none.ply"), "--out", str(tmp_path / "e2")]) == 2
    assert "none.ply: no such mesh file" in capsys.readouterr().err
    assert main(["morph", "errors", str(b.path), str(b.coarse), "--out", str(tmp_path / "e3"), "--band", "-1"]) == 2
    assert "--band must be > 0" in capsys.readouterr().err
    assert not (tmp_path / "e2").exists() and not (tmp_path / "e3").exists()


def test_the_suite_bench_row_says_where_the_error_sits(small_armadillo):
    """``where_errors`` (each suite row's ``errors``): the coarse input as its own result keeps all of its error
    (slope 1, no new error) and both directions agree with the Chamfer the run reports (within 5 %)."""
    from foundation.mesh import load_mesh_any
    from foundation.mesh_metrics import chamfer
    from photoreal.benchmarks.morph.bench import where_errors

    b = small_armadillo
    e = where_errors(b, b.coarse)
    assert e["input_error_left"] == pytest.approx(1.0, abs=1e-9) and e["new_error_rms"] < 1e-12
    ch = chamfer(*load_mesh_any(b.coarse), *load_mesh_any(b.ground_truth))["chamfer"]
    assert 0.5 * (e["to_truth"] + e["from_truth"]) == pytest.approx(ch, rel=0.05)
    assert e["from_truth_border"] is None  # the armadillo is closed
    # the facing split: the input as its own result has the input's, and it adds up to the area the run reports
    from foundation.mesh_metrics import facing_against_truth, truth_surface

    assert e["facing_area_by_views"] == e["facing_area_by_views_input"] and e["unseen_area"] == e["unseen_area_input"]
    gv, gf = load_mesh_any(b.ground_truth)[:2]
    fa = facing_against_truth(*load_mesh_any(b.coarse)[:2], truth_surface(gv, gf))["area_fraction"]
    assert sum(e["facing_area_by_views"].values()) == pytest.approx(fa, rel=1e-9)
