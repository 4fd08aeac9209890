"""The morph's silhouette loss (``MorphSettings.mask_weight``): the photos' masks, the mask scene, its gradient,
and a run that uses it.

Oracles: Mitsuba's own film alpha (the coverage it accumulates per pixel) for the masks; finite differences of the
mask L1 for its gradient; a closed form (the covered fraction of a square) for the mask scene's render."""

from dataclasses import replace

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from foundation.mesh import write_ply
from inverse.morph import MorphSettings, run_morph


def test_photo_masks_are_the_truths_coverage_as_mitsubas_film_counts_it(small_armadillo):
    from inverse.morph import photo_masks, sensor_dict

    masks = photo_masks(small_armadillo, 48, [0, 3])
    assert sorted(masks) == [0, 3]
    truth = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "gt": {"type": "ply", "filename": str(small_armadillo.ground_truth)}})
    for i, m in masks.items():
        assert m.shape == (48, 48) and m.dtype == np.float32 and 0.0 <= m.min() and m.max() <= 1.0
        sd = sensor_dict(small_armadillo.meta.cameras[i], 48, small_armadillo.meta.fov)
        sd["film"]["pixel_format"] = "rgba"
        alpha = np.asarray(mi.render(truth, sensor=mi.load_dict(sd), spp=256, seed=100 + i))[..., 3]
        # both are Monte-Carlo estimates of the same coverage (64 and 256 samples a pixel): they agree inside and
        # outside exactly, and at the silhouette within their noise (a pixel's std ≤ 0.5 / √64)
        assert np.abs(m - alpha).mean() < 0.01, np.abs(m - alpha).mean()
        assert 0.05 < m.mean() < 0.95  # the object is in the frame, with background around it


def _square_ply(path, x=0.0):
    v = np.array([[-.5, -.5, 0], [.5, -.5, 0], [.5, .5, 0], [-.5, .5, 0]], np.float64) + [x, 0, 0]
    write_ply(path, v, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.5))
    return path


def _sensor(z=3.0, res=32):
    return mi.load_dict({"type": "perspective", "fov": 45,
                         "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, z], target=[0, 0, 0], up=[0, 1, 0]),
                         "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                                  "sample_border": True}})


def test_the_mask_scene_is_one_minus_coverage_from_either_side(tmp_path):
    """A unit square at distance 3 under a 45° field of view covers (1 / (2·3·tan 22.5°))² of the frame: the
    render's mean is 1 minus that, seen from the front or the back (a sheet's back blocks the sky as well)."""
    from inverse.morph import mask_scene

    scene = mask_scene(_square_ply(tmp_path / "sq.ply"))
    covered = (1.0 / (2 * 3.0 * np.tan(np.radians(22.5)))) ** 2
    for z in (3.0, -3.0):
        img = np.asarray(mi.render(scene, sensor=_sensor(z, 64), spp=64, seed=0))[..., :3]
        assert abs((1.0 - img.mean()) - covered) < 0.01, (z, 1.0 - img.mean(), covered)
        assert np.allclose(img[..., 0], img[..., 1]) and np.allclose(img[..., 0], img[..., 2])


def test_the_mask_l1_pulls_a_silhouette_towards_the_target_as_finite_differences_say(tmp_path):
    """The target: the square moved 0.08 to the right (about 1.6 pixels). The derivative of the mask L1 in the
    square's x position, from the projective integrator's boundary term, matches central differences of the same
    loss (±0.02, 256 spp) within 15 %, and points the square towards the target."""
    from inverse.morph import mask_scene

    sensor = _sensor()
    target = mask_scene(_square_ply(tmp_path / "t.ply", x=0.08))
    sky = mi.TensorXf(np.asarray(mi.render(target, sensor=sensor, spp=1024, seed=7))[..., :3])
    scene = mask_scene(_square_ply(tmp_path / "s.ply"))
    params = mi.traverse(scene)
    # a copy: np.asarray maps Dr.Jit's buffer, which the next assignment frees
    v0 = np.array(params["mesh.vertex_positions"], copy=True).reshape(-1, 3)

    def loss(x, grad=False, spp=256, seed=1):
        xs = mi.Float(x)
        if grad:
            dr.enable_grad(xs)
        col = [mi.Float(np.ascontiguousarray(v0[:, k], np.float32)) for k in range(3)]
        params["mesh.vertex_positions"] = dr.ravel(mi.Point3f(col[0] + xs, col[1], col[2]))
        params.update()
        img = mi.render(scene, params, sensor=sensor, spp=spp, seed=seed)[..., :3]
        l1 = dr.mean(dr.abs(img - sky), axis=None)
        if grad:
            dr.backward(l1)
            return float(np.asarray(dr.grad(xs)).sum())
        return float(np.asarray(l1).item())

    h = 0.02
    fd = (loss(h, seed=3) - loss(-h, seed=3)) / (2 * h)
    ad = np.mean([loss(0.0, grad=True, seed=s) for s in (11, 12, 13, 14)])
    assert fd < 0 and ad < 0, (fd, ad)  # moving right (towards the target) lowers the loss
    assert abs(ad - fd) < 0.15 * abs(fd), (ad, fd)


def test_the_mask_integrator_skips_the_continuous_samples_and_changes_no_bit(small_armadillo):
    """The mask scene's mesh is black under a constant sky: its continuous derivative is zero at every pixel, so
    ``mask_integrator`` takes no continuous samples. Oracle: the same render with them (``projective_integrator``:
    4 continuous samples a pixel, the same boundary count) gives the same image and the same vertex gradient, bit
    for bit, at two render seeds and on both sample-count paths (the integrator's own counts, and a run-time spp)."""
    from inverse.morph import mask_integrator, mask_scene, projective_integrator, render_views

    meta = small_armadillo.meta
    sky = mi.TensorXf(np.full((48, 48, 3), 0.5, np.float32))

    def grad(integrator, own_counts, seed):
        scene = mask_scene(small_armadillo.coarse, integrator=integrator)
        params = mi.traverse(scene)
        v = mi.Float(params["mesh.vertex_positions"])
        dr.enable_grad(v)
        params["mesh.vertex_positions"] = v
        params.update()
        imgs = render_views(scene, params, meta.cameras, [0, 5], 48, meta.fov, 2, seed, integrator_spp=own_counts)
        dr.backward(sum(dr.mean(dr.abs(im[..., :3] - sky), axis=None) for im in imgs))
        return [np.array(im, copy=True) for im in imgs], np.array(dr.grad(v), copy=True)

    for own_counts, spp_b in ((True, 1), (False, None)):
        for seed in (0, 17):
            with_c = grad(projective_integrator(4, spp_b if spp_b else 2), own_counts, seed)
            without = grad(mask_integrator(spp_b), own_counts, seed)
            assert all(np.array_equal(a, b) for a, b in zip(with_c[0], without[0]))
            assert np.array_equal(with_c[1], without[1]) and np.abs(without[1]).max() > 0, (own_counts, seed)


def test_a_run_with_the_silhouette_loss_brings_the_silhouettes_closer(small_armadillo, tmp_path):
    """20 iterations from the coarse input under the defaults (weight 2, masks at full resolution, one boundary
    sample), against the same run on the photos alone: the silhouettes' L1 over the training views (at full
    resolution) falls by 10 % or more, and lies 10 % or more below the photos-only run's; the weight is part of the
    checkpoint's settings only when it is not 0 (runs before it resume)."""
    from inverse.morph import MorphStage, mask_scene, photo_masks, sensor_dict

    meta = small_armadillo.meta
    masks = photo_masks(small_armadillo, 48, meta.train)

    def mask_l1(ply):
        scene = mask_scene(ply)
        err = []
        for i, m in masks.items():
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], 48, meta.fov))
            img = np.asarray(mi.render(scene, sensor=sensor, spp=64, seed=i))[..., 0]
            err.append(np.abs((1.0 - img) - m).mean())
        return float(np.mean(err))

    # one run each, no choices (the photos' choices are tested in test_select.py): λ 2 throughout
    s = MorphSettings(iterations=20, resolution=48, min_vertices=None, check_every=10, validation_fraction=0.5,
                      early_stop=False, lambda_select=())
    r = run_morph(small_armadillo, tmp_path / "m", s, show_progress=False)
    run_morph(small_armadillo, tmp_path / "p", replace(s, mask_weight=0.0), show_progress=False)
    start = mask_l1(small_armadillo.coarse)
    after, photos_only = mask_l1(tmp_path / "m" / "morphed.ply"), mask_l1(tmp_path / "p" / "morphed.ply")
    # measured at constant λ 2: 0.01615 → 0.01359 with the masks, 0.01612 without (the photos alone leave the
    # outlines where they are); with the photos' choices first, 0.01349 and 0.01648
    assert after < 0.9 * start and after < 0.9 * photos_only, (start, after, photos_only)
    assert r.spikes == 0
    stage = MorphStage(small_armadillo, tmp_path / "fp", s)
    assert stage.fingerprint()["settings"]["mask_weight"] == MorphSettings.mask_weight == 2.0
    plain = MorphStage(small_armadillo, tmp_path / "fp0", MorphSettings(resolution=48, min_vertices=None,
                                                                          mask_weight=0.0))
    assert "mask_weight" not in plain.fingerprint()["settings"] and not plain.sky


def test_the_gcn_morph_runs_without_the_silhouette_loss_and_says_so():
    """The GCN morph has no silhouette loss: settings that ask for one (the defaults do) run without it, with a
    warning naming the parameter, and record 0; settings without one pass unchanged and silently."""
    import warnings

    from inverse.morph import gcn_settings

    assert MorphSettings().mask_weight > 0
    with pytest.warns(UserWarning, match=r"^mask_weight: the GCN morph has no silhouette loss.*2\.0 → 0"):
        s = gcn_settings(MorphSettings(iterations=7))
    assert s.mask_weight == 0.0 and s.iterations == 7
    plain = MorphSettings(mask_weight=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert gcn_settings(plain) is plain


def test_a_cheaper_mask_renders_every_kth_step_at_k_times_the_weight_and_a_coarser_resolution(small_armadillo,
                                                                                              tmp_path):
    """``mask_every`` 2, ``mask_downsample`` 2 at 48²: the photos' masks are 24²; at an odd step the loss is the
    photos' alone (equal to a run without masks, same seed, same views), at an even step it is that plus 2 × the
    mask L1 of 24² renders (computed here from the same scene and seed); both fields enter the fingerprint only
    when they change the steps. A mask under 8² is refused by name."""
    from foundation.errors import UsageError
    from inverse.morph import MorphStage, render_views

    # conftest runs Dr.Jit on one thread: the two stages' photo renders agree bit for bit
    base = dict(resolution=48, min_vertices=None, validation_fraction=0.5, seed=3)
    cheap = MorphStage(small_armadillo, tmp_path / "c", MorphSettings(mask_weight=1.0, mask_every=2,
                                                                       mask_downsample=2, boundary_spp=1, **base))
    plain = MorphStage(small_armadillo, tmp_path / "p", MorphSettings(mask_weight=0.0, **base))
    assert {tuple(t.shape) for t in cheap.sky.values()} == {(24, 24, 3)}
    meta, s = small_armadillo.meta, cheap.s
    for it in (0, 1):
        state = cheap.rng.bit_generator.state
        views = cheap.rng.choice(cheap.train_ids, size=min(s.views_per_step, len(cheap.train_ids)), replace=False)
        cheap.rng.bit_generator.state = state
        lc, lp = cheap.step(it).loss, plain.step(it).loss
        if it % 2:
            assert lc == lp, (it, lc, lp)
            continue
        skies = render_views(cheap.mask_scene, cheap.mask_params, meta.cameras, views, 24, meta.fov, s.spp,
                             s.seed * 7919 + it * 101 + 1_000_003, integrator_spp=not cheap.shared_spp)
        l1 = np.mean([np.abs(np.asarray(img)[..., :3] - np.asarray(cheap.sky[int(i)])).mean()
                      for img, i in zip(skies, views)])
        assert l1 > 0.001 and abs((lc - lp) - 2.0 * l1) < 1e-4 * max(1.0, lc), (lc, lp, l1)
    fp = cheap.fingerprint()["settings"]
    assert fp["mask_every"] == 2 and fp["mask_downsample"] == 2
    assert "mask_every" not in plain.fingerprint()["settings"]
    assert "mask_downsample" not in plain.fingerprint()["settings"]
    cheap.close()
    plain.close()
    with pytest.raises(UsageError, match="^mask_downsample: 8 leaves 6² masks"):
        MorphStage(small_armadillo, tmp_path / "x", MorphSettings(mask_weight=1.0, mask_downsample=8, **base))
