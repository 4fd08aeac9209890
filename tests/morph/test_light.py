"""Light and pixels: the indirect estimate, bilinear upsampling, shared first bounces, boundary samples, saturation, thickness."""


import json
from pathlib import Path

import numpy as np
import pytest

from foundation.errors import UsageError

from inverse.morph import MorphSettings
from foundation.mesh import write_ply
from inverse.morph import MorphBenchmarkSettings, load_morph_benchmark, make_morph_benchmark

from morph_shapes import box, outward_sphere, sphere

ARMADILLO = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"


def _assert_depth2_is_two_renders(stage, images) -> None:
    """The estimate as it was made before the ``indirect`` integrator: the path tracer at the photos' depth minus the
    path tracer at depth 2, one seed, subtracted (the same random numbers for the first bounce). Float32 rounding
    apart (1e-6 × the brightest pixel) they agree pixel for pixel."""
    import drjit as dr
    import mitsuba as mi

    from inverse.morph import sensor_dict
    from inverse.morph.scene import upsample_bilinear

    meta = stage.bench.meta
    res = -(-stage.res // stage.s.indirect_downsample)
    with dr.suspend_grad():
        for img, i in zip(images, meta.train):
            sensor = mi.load_dict(sensor_dict(meta.cameras[int(i)], res, meta.fov))
            a, b = (np.array(mi.render(stage.scene, stage.params, sensor=sensor, spp=stage.s.indirect_spp,
                                       seed=9_000_011 + int(i), integrator=mi.load_dict({"type": "path", "max_depth": d})))
                    for d in (meta.settings.photo_max_depth, 2))
            np.testing.assert_allclose(img, upsample_bilinear(a[..., :3] - b[..., :3], stage.res), rtol=0,
                                       atol=1e-6 * max(float(a.max()), 1.0))


def _indirect_estimate(tmp_path, name, v, f, **kw) -> tuple[float, float]:
    """Mean and largest magnitude of the stage's indirect-light estimate over a tiny benchmark's training views."""
    from inverse.morph.stage import MorphStage

    src = write_ply(tmp_path / f"{name}.ply", v, f)
    bs = MorphBenchmarkSettings(n_views=4, resolution=24, spp=4, coarse_vertices=400)
    bench_dir = tmp_path / f"bench_{name}"
    bench = load_morph_benchmark(bench_dir if (bench_dir / "morph_benchmark.json").is_file() else
                                 make_morph_benchmark(src, bench_dir, bs, show_progress=False))
    s = MorphSettings(min_vertices=None, resolution=24, indirect_every=100, **kw)
    stage = MorphStage(bench, tmp_path / f"run_{name}_{kw}", s)
    try:
        stage.estimate_indirect()
        images = [np.array(stage.indirect[i]) for i in bench.meta.train]
        if s.indirect_reference == "depth2":  # one render of the `indirect` integrator is the two renders' difference
            _assert_depth2_is_two_renders(stage, images)
    finally:
        stage.close()
    assert len(images) == len(bench.meta.train) and all(np.isfinite(x).all() for x in images)
    return float(np.mean(images)), float(np.max(np.abs(images)))


def test_indirect_estimate_vanishes_on_a_convex_shape_and_is_positive_inside_a_cup(tmp_path):
    # Oracle: under an environment map a convex surface never sees itself, so path tracing and direct lighting
    # have the same expectation and their difference averages to zero (up to noise); the inside of a cup sees
    # itself, so the light bounced there is positive.
    v, f = sphere(1.0, 16)
    cup = np.all(v[f][:, :, 1] < 0.2, axis=1)  # the lower half: a bowl open at the top, the cameras see into it
    used, fc = np.unique(f[cup], return_inverse=True)
    for kw in ({"indirect_reference": "direct", "indirect_spp": 64, "indirect_downsample": 1},
               {"indirect_reference": "depth2", "indirect_spp": 16, "indirect_downsample": 1},
               {"indirect_reference": "depth2", "indirect_spp": 16}):  # the default: at half resolution, upsampled
        convex, convex_max = _indirect_estimate(tmp_path, "sphere", v, f, **kw)
        concave, concave_max = _indirect_estimate(tmp_path, "cup", v[used], fc.reshape(-1, 3), **kw)
        # measured (mean / mean): direct 9e-6 / 0.0035; depth2 0.00028 / 0.0036, at half resolution 0.00034 / 0.0032
        # (the benchmark's coarse sphere carries bumps, and its smooth shading normals let some sampled directions
        # back into the surface: a little light bounces; 1024 spp put it at 0.00026, the cup at 0.0034)
        assert concave > 0.001, kw
        assert abs(convex) < 0.2 * concave, kw
        assert convex_max < concave_max, kw  # depth2: no noise of the direct light, so the sphere's pixels are small
    # the upsampling keeps the estimate's mean: with as many samples per view (64 spp at 24², 256 at 12²) the cup's
    # means agree (measured 0.003504 and 0.003490, 0.4 % apart; each mean's noise here about 2 %)
    full = _indirect_estimate(tmp_path, "cup", v[used], fc.reshape(-1, 3), indirect_spp=64, indirect_downsample=1)[0]
    half = _indirect_estimate(tmp_path, "cup", v[used], fc.reshape(-1, 3), indirect_spp=256, indirect_downsample=2)[0]
    assert half == pytest.approx(full, rel=0.05)


def test_upsample_bilinear_is_exact_on_linear_images_and_keeps_constants():
    # Oracle: bilinear interpolation between pixel centres reproduces a function linear in the frame's
    # coordinates exactly wherever a pixel centre lies between two coarse centres; beyond the outermost coarse
    # centres (half a coarse pixel from the border) it holds the edge value.
    from inverse.morph.scene import upsample_bilinear

    def centres(n):
        return (np.arange(n) + 0.5) / n

    for n, size in ((12, 24), (11, 32), (43, 128), (24, 24)):
        y, x = np.meshgrid(centres(n), centres(n), indexing="ij")
        img = np.stack([2.0 * x + 3.0 * y, x - y, np.full_like(x, 0.25)], -1).astype(np.float32)
        out = upsample_bilinear(img, size)
        assert out.shape == (size, size, 3) and out.dtype == np.float32
        Y, X = np.meshgrid(centres(size), centres(size), indexing="ij")
        inside = (np.minimum(X, Y) >= 0.5 / n) & (np.maximum(X, Y) <= 1 - 0.5 / n)
        np.testing.assert_allclose(out[..., 0][inside], (2.0 * X + 3.0 * Y)[inside], atol=1e-5)
        np.testing.assert_allclose(out[..., 1][inside], (X - Y)[inside], atol=1e-5)
        np.testing.assert_array_equal(out[..., 2], 0.25)
        if n == size:
            np.testing.assert_array_equal(out, img)  # the fitting resolution: the estimate as it was, bit for bit
        clamped = np.clip(X, 0.5 / n, 1 - 0.5 / n) - np.clip(Y, 0.5 / n, 1 - 0.5 / n)  # the edge value held
        np.testing.assert_allclose(out[..., 1], clamped, atol=1e-5)


def test_path_tracers_of_two_depths_share_the_first_bounce_sample_for_sample(tmp_path):
    """What the light estimate's low noise rests on: with one seed, Mitsuba's path tracer at depth 2 and at depth 4
    draw the same random numbers for the first bounce, so on an exactly convex, flat-shaded mesh (no light can
    bounce twice) their renders agree pixel for pixel, while the ``direct`` integrator's differ by its noise."""
    import mitsuba as mi

    from foundation.assets import envmap

    v, f = sphere(1.0, 12)
    ply = write_ply(tmp_path / "convex.ply", v, f, np.full((len(v), 3), 0.6, np.float32))
    scene = mi.load_dict({"type": "scene", "env": envmap("sunset"),
                          "mesh": {"type": "ply", "filename": str(ply), "face_normals": True,
                                   "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
                                       "type": "mesh_attribute", "name": "vertex_color"}}}}})
    sensor = mi.load_dict({"type": "perspective", "fov": 40, "film": {"type": "hdrfilm", "width": 24, "height": 24},
                           "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 4], target=[0, 0, 0],
                                                                      up=[0, 1, 0])})

    def render(integrator: dict) -> np.ndarray:
        return np.array(mi.render(scene, sensor=sensor, integrator=mi.load_dict(integrator), spp=8, seed=7))[..., :3]

    deep, two = render({"type": "path", "max_depth": 4}), render({"type": "path", "max_depth": 2})
    direct = render({"type": "direct"})
    assert np.abs(deep - two).max() <= 1e-5 * deep.max()  # float summation order only (measured 0 / 2e-6)
    assert np.abs(deep - direct).max() > 100 * np.abs(deep - two).max() + 1e-4


def test_boundary_samples_change_only_the_silhouette_gradient_and_not_its_mean(small_armadillo):
    """``boundary_spp`` sets the projective integrator's silhouette samples apart from the image's: at ``spp`` the
    renders and gradients are those of one shared count, bit for bit; with fewer, the image is the same and the
    gradient an unbiased estimate of the same derivative (mean over render seeds within the seeds' spread)."""
    import drjit as dr
    import mitsuba as mi

    from inverse.morph import morph_scene, render_views
    from inverse.morph import projective_integrator

    b = small_armadillo
    views, res = [0, 3], 24

    def grad(integrator, integrator_spp, seed):
        scene = morph_scene(b.coarse, "lit", b.meta.hdri, integrator=integrator)
        p = mi.traverse(scene)
        dr.enable_grad(p["mesh.vertex_positions"])
        p.update()
        imgs = render_views(scene, p, b.meta.cameras, views, res, b.meta.fov, 4, seed, integrator_spp=integrator_spp)
        dr.backward(sum(dr.mean(dr.square(im[..., :3]), axis=None) for im in imgs))
        return np.array(imgs[0]), np.array(dr.grad(p["mesh.vertex_positions"]), np.float64)

    shared = grad(None, False, 5)
    same = grad(projective_integrator(4, 4), True, 5)
    assert np.array_equal(shared[0], same[0]) and np.array_equal(shared[1], same[1])
    fewer = grad(projective_integrator(4, 1), True, 5)
    assert np.array_equal(shared[0], fewer[0]) and not np.array_equal(shared[1], fewer[1])
    # unbiased: the mean over 8 render seeds of the 1-sample estimate against that of 16 boundary samples
    ref = np.mean([grad(projective_integrator(4, 16), True, s)[1] for s in range(8)], 0)
    ones = np.array([grad(projective_integrator(4, 1), True, 100 + s)[1] for s in range(8)])
    err = np.linalg.norm(ones.mean(0) - ref)
    spread = np.linalg.norm(ones.std(0)) / np.sqrt(len(ones))  # standard error of the 8-seed mean
    assert err < 3.0 * spread, (err, spread)
    with pytest.raises(UsageError, match="^boundary_spp must"):
        MorphSettings(boundary_spp=0)


def test_a_silhouette_against_the_sun_leaves_the_loss_with_the_saturated_pixels():
    """A mesh edge in front of a light 10⁴ times brighter than the rest carries a silhouette gradient scaled by
    that radiance (paul at seed 1: one view's largest gradient 3,000 times the others', which froze uniform
    Adam). Saturated pixels and their neighbours leave the L1 (:func:`inverse.morph.scene.photo_l1`): the gradient falls to the
    size the same edge has against the sky, and a view with no saturated pixel keeps the plain L1 exactly."""
    import drjit as dr
    import mitsuba as mi

    from inverse.morph.scene import photo_l1, photo_saturation, unsaturated_mask

    def scene(sun: float):
        sq = mi.Mesh("sq", 4, 2)
        p = mi.traverse(sq)
        p["vertex_positions"] = mi.Float(np.array([[-.5, -.5, 0], [.5, -.5, 0], [.5, .5, 0], [-.5, .5, 0]],
                                                  np.float32).ravel())
        p["faces"] = mi.UInt32(np.array([0, 1, 2, 0, 2, 3], np.uint32))
        p.update()
        sq.set_bsdf(mi.load_dict({"type": "diffuse", "reflectance": 0.5}))
        return mi.load_dict({"type": "scene", "integrator": {"type": "direct_projective", "sppi": 0},
                             "env": {"type": "constant", "radiance": 1.0}, "sq": sq,
                             # behind the square's left edge as the camera sees it
                             "sun": {"type": "rectangle", "emitter": {"type": "area", "radiance": sun},
                                     "to_world": mi.ScalarTransform4f().translate([-0.667, 0, -1]).scale(0.1)}})

    sensor = mi.load_dict({"type": "perspective", "fov": 45,
                           "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
                           "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"},
                                    "sample_border": True}})

    def grad(sun: float, factor: float) -> tuple[float, bool]:
        sc = scene(sun)
        params = mi.traverse(sc)
        v0 = np.asarray(params["sq.vertex_positions"]).reshape(-1, 3)
        photo = mi.TensorXf(np.asarray(mi.render(sc, sensor=sensor, spp=16, seed=1))[..., :3])
        level, hot = photo_saturation({0: photo}, [0], factor)
        x = mi.Float((v0 + [0.03, 0.0, 0.0]).ravel().astype(np.float32))  # the fit: off by 1/3 pixel
        dr.enable_grad(x)
        params["sq.vertex_positions"] = x
        params.update()
        img = mi.render(sc, params, sensor=sensor, spp=4, seed=2)[..., :3]
        masked = level > 0 and unsaturated_mask(hot[0], dr.detach(img), level) is not None
        dr.backward(photo_l1(img, photo, hot.get(0), level))
        return float(np.abs(np.asarray(dr.grad(x))).max()), masked

    sky, sky_masked = grad(1.0, 4.0)  # the same edge against a light as bright as the sky
    sun_plain, _ = grad(1e4, 0.0)
    sun_masked, masked = grad(1e4, 4.0)
    assert not sky_masked and masked
    assert sun_plain > 100 * sky, (sun_plain, sky)
    assert sun_masked < 3 * sky, (sun_masked, sky)
    assert grad(1.0, 0.0)[0] == sky  # nothing saturated: exactly the plain L1

    hot = np.zeros((6, 6), bool)
    hot[0, 0] = True
    keep = unsaturated_mask(hot, np.zeros((6, 6, 3), np.float32), 10.0)
    assert keep.shape == (6, 6, 3) and keep[:2, :2].sum() == 0 and keep.sum() == 3 * (36 - 4)
    assert unsaturated_mask(np.zeros((6, 6), bool), np.zeros((6, 6, 3), np.float32), 10.0) is None


def test_morph_saturation_reports_the_lighting_behind_the_silhouette(small_armadillo, tmp_path, capsys):
    """``photoreal morph saturation``: the level the morph uses, and per view the saturated light and the part of
    it at the truth's silhouette; bad input named, nothing written."""
    from inverse.morph.scene import saturation_level
    from photoreal.cli import main

    out = tmp_path / "sat.json"
    assert main(["morph", "saturation", str(small_armadillo.path), "--json", str(out)]) == 0
    r = json.loads(out.read_text())[str(small_armadillo.path)]
    b = small_armadillo
    assert r["level"] == saturation_level([b.photo(i) for i in b.meta.train], 4.0) > 0
    assert set(map(int, r["views"])) <= set(b.meta.train)
    assert all(0 <= v["at_silhouette"] <= v["saturated"] for v in r["views"].values())
    assert r["at_silhouette"] == sum(v["at_silhouette"] for v in r["views"].values())
    capsys.readouterr()
    assert main(["morph", "saturation", str(b.path), "--factor", "0", "--json", str(tmp_path / "x.json")]) == 2
    assert "--factor must be > 0" in capsys.readouterr().err
    assert main(["morph", "saturation", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_inward_thickness_of_a_plate_a_sphere_and_an_open_sheet():
    """Closed forms: a box plate 2 × 2 × 2t (outward winding) is 2t thick through its large faces and 2 through its
    rims; a unit sphere's inward ray from a triangle's centroid meets the far side after the chord 2·|n·c| (the far
    side's facets lie up to a tessellation's sag inside: tolerance 0.01); an open sheet, and a sphere wound inward,
    let the ray out (inf)."""
    from foundation.mesh import face_normals
    from inverse.morph.scene import inward_thickness

    v, f = box(4)
    plate = v * [1.0, 1.0, 0.05]
    t = inward_thickness(plate, f)
    c = plate[f].mean(axis=1)
    large = np.abs(np.abs(c[:, 2]) - 0.05) < 1e-9
    assert large.sum() == 2 * 32 and np.allclose(t[large], 0.1, atol=1e-4)
    assert np.allclose(t[~large], 2.0, atol=1e-4)
    vs, fs = outward_sphere(40)
    ts = inward_thickness(vs, fs)
    chord = 2 * np.abs(np.sum(face_normals(vs, fs) * vs[fs].mean(axis=1), axis=1))
    hit = np.isfinite(ts)  # a ray exactly through a vertex of the far side can slip through (2 of 6,080 here)
    assert hit.mean() > 0.999 and np.abs(ts[hit] - chord[hit]).max() < 0.01
    assert np.isinf(inward_thickness(vs, fs[:, ::-1])).all()
    top = f[c[:, 2] > 0.049]  # one large face of the plate alone: a sheet
    assert np.isinf(inward_thickness(plate, top)).all()
