"""neural_btf plugin and the basis training code: oracles are the training code path (tensor mode),
Mitsuba's chi² harness, finite differences, closed-form blurs and a learnable closed-form BTF."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from inverse.btf import fit as bf
from foundation.errors import CheckpointError
from mi_plugins import neural_basis as nb
from tests.conftest import CUDA, local_si, random_dirs


def _files(tmp_path, res=16, seed=0, scale=0.5, config=None):
    rng = np.random.default_rng(seed)
    basis = nb.Basis.init(config or nb.BasisConfig(), seed)
    mat = nb.NeuralMaterial((rng.standard_normal((res, res, 8)) * scale).astype(np.float32),
                            (rng.standard_normal((res, res, 8)) * scale).astype(np.float32))
    b, m = tmp_path / "basis.npz", tmp_path / "mat.npz"
    nb.save_basis(b, basis)
    nb.save_material(m, mat)
    return basis, mat, str(b), str(m)


def _hemi(rng, n):
    v = rng.standard_normal((n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


# each network form of the plugin; constants with a narrow basis (their compile grows with the weights)
FORMS = [("coop", nb.BasisConfig(width=32)), ("constants", nb.BasisConfig(width=32)), ("auto", nb.BasisConfig(width=32))]


@pytest.mark.parametrize("form,config", FORMS, ids=[f for f, _ in FORMS])
def test_plugin_eval_equals_training_code_path(tmp_path, ctx, form, config):
    """The plugin's network (constants or CoopVec) and tensor mode (training) evaluate the same eqs. 2–3; wrap
    included."""
    basis, mat, b, m = _files(tmp_path, config=config)
    bsdf = mi.load_dict({"type": "neural_btf", "basis": b, "material": m, "network": form})
    if not CUDA:  # auto: a width-32 basis is written as constants
        assert isinstance(bsdf.m_rgb, nb.ConstantNet if form != "coop" else nb.CoopNet)
    rng = np.random.default_rng(1)
    n = 4000
    wi, wo = _hemi(rng, n), _hemi(rng, n)
    uv = rng.uniform(-1.5, 2.5, (n, 2)).astype(np.float32)  # outside [0, 1): repeat wrap
    si = local_si(mi.Vector3f(wo.T))
    si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    got = bsdf.eval(ctx, si, mi.Vector3f(wi.T)).numpy().T
    pred, _, _ = bf._forward(basis.config, basis.arrays(), mi.Float(mat.t_off.ravel()), mi.Float(mat.t_rgb.ravel()),
                             mat.res, np.zeros(n, np.int64), uv, wi, wo, False)
    want = np.maximum(np.stack([p.numpy() for p in pred], 1), 0)
    assert want.max() > 0.05  # a non-trivial network
    if CUDA:  # half-precision cooperative vectors there (CoopNet): the float16 bound of the test below
        np.testing.assert_allclose(got, want, rtol=1e-2, atol=5e-3 * want.max())
    else:  # f32 matvec vs f32 matmul: same maths, different summation order at worst
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_a_wide_basis_gives_the_same_values_in_both_dr_jit_modes(tmp_path, ctx):
    """auto with the default width-64 basis (ModeNet on LLVM): constants inside symbolic calls, CoopVec in evaluated
    mode; the two are the same f32 maths (summation order aside)."""
    from mi_plugins.bsdfs.neural_btf import evaluated_mode

    _, _, b, m = _files(tmp_path)
    bsdf = mi.load_dict({"type": "neural_btf", "basis": b, "material": m})
    rng = np.random.default_rng(2)
    wi, wo = _hemi(rng, 500), _hemi(rng, 500)
    si = local_si(mi.Vector3f(wo.T))
    si.uv = mi.Point2f(*rng.random((2, 500)).astype(np.float32))
    symbolic = bsdf.eval(ctx, si, mi.Vector3f(wi.T)).numpy()
    with evaluated_mode():
        evaluated = bsdf.eval(ctx, si, mi.Vector3f(wi.T)).numpy()
    assert symbolic.max() > 0.05
    np.testing.assert_allclose(evaluated, symbolic, rtol=1e-2 if CUDA else 1e-4, atol=1e-5)


def test_half_precision_cooperative_vectors_stay_within_float16_rounding():
    """CoopNet in float16 (what CUDA packs) against the float32 network, evaluated here on LLVM: a 14-32-32-3
    MLP of unit-variance weights, inputs in [−1, 1]. float16 rounds to 2⁻¹¹ ≈ 4.9e-4 relative; over two hidden
    layers of 32 products the error measured 1.6e-3 at outputs up to 1.34: the bound is 5e-3 × max|y|."""
    rng = np.random.default_rng(0)
    dims = [14, 32, 32, 3]
    layers = [(rng.normal(size=(o, i)).astype(np.float32) / np.sqrt(i), rng.normal(size=o).astype(np.float32) * 0.1)
              for i, o in zip(dims[:-1], dims[1:])]
    x = [mi.Float(rng.uniform(-1, 1, 5000).astype(np.float32)) for _ in range(dims[0])]
    h = np.array([v.numpy() for v in x])
    for k, (w, b) in enumerate(layers):  # oracle: the same MLP in float64 numpy
        h = w @ h + b[:, None]
        h = np.maximum(h, 0) if k < len(layers) - 1 else h
    half = nb.CoopNet(layers, training=True, half=True)
    assert half.half
    if not CUDA:  # CUDA packs float16 only
        full = nb.CoopNet(layers, training=True, half=False)
        y32 = np.array([y.numpy() for y in full(x)])
        assert not full.half and np.abs(y32 - h).max() < 1e-5 * np.abs(h).max()
    y16 = np.array([y.numpy() for y in half(x)])
    err = np.abs(y16 - h).max()
    assert 1e-5 * np.abs(h).max() < err < 5e-3 * np.abs(h).max()  # really half, and within its rounding


def test_below_horizon_and_disabled_lobe_are_zero(tmp_path, ctx):
    _, _, b, m = _files(tmp_path)
    bsdf = mi.load_dict({"type": "neural_btf", "basis": b, "material": m})
    wi = random_dirs(1000, 2)
    si = local_si(wi)
    below = mi.Vector3f(random_dirs(1000, 3, upper=True).x, random_dirs(1000, 3).y, -random_dirs(1000, 3).z)
    assert dr.all(bsdf.eval(ctx, si, below) == 0, axis=None)
    assert dr.all(bsdf.pdf(ctx, si, below) == 0)
    off = mi.BSDFContext()
    off.type_mask = int(mi.BSDFFlags.DiffuseReflection)
    assert dr.all(bsdf.eval(off, si, wi) == 0, axis=None)


@pytest.mark.parametrize("theta_deg", [0.0, 40.0, 75.0])
def test_chi2_sampling_matches_pdf(tmp_path, theta_deg):
    _, _, b, m = _files(tmp_path)
    t = np.radians(theta_deg)
    wi = [float(np.sin(t)), 0.0, float(np.cos(t))]
    sample_func, pdf_func = mi.chi2.BSDFAdapter("neural_btf", {"type": "neural_btf", "basis": b, "material": m}, wi=wi)
    chi2 = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                                 sample_dim=3, sample_count=1_000_000, res=201, ires=16)
    assert chi2.run(), chi2.messages


def test_sample_weight_equals_eval_over_pdf(tmp_path, ctx):
    _, _, b, m = _files(tmp_path)
    bsdf = mi.load_dict({"type": "neural_btf", "basis": b, "material": m})
    n = 5000
    si = local_si(random_dirs(n, 4))
    rng = np.random.default_rng(5)
    si.uv = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    bs, w = bsdf.sample(ctx, si, mi.Float(rng.random(n).astype(np.float32)),
                        mi.Point2f(rng.random((2, n)).astype(np.float32)))
    value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    ok = (bs.pdf > 0).numpy()
    np.testing.assert_allclose(bs.pdf.numpy()[ok], pdf.numpy()[ok], rtol=1e-5)
    np.testing.assert_allclose(w.numpy()[:, ok], (value.numpy() / pdf.numpy())[:, ok], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("form,config", FORMS[:2], ids=[f for f, _ in FORMS[:2]])
def test_gradients_wrt_feature_textures_match_finite_differences(tmp_path, ctx, form, config):
    """d(sum of eval)/d texel through the plugin (constants or CoopVec backward) vs central differences."""
    _, mat, b, m = _files(tmp_path, res=8, config=config)
    bsdf = mi.load_dict({"type": "neural_btf", "basis": b, "material": m, "network": form})
    params = mi.traverse(bsdf)
    n = 2000
    rng = np.random.default_rng(6)
    wi, wo = _hemi(rng, n), _hemi(rng, n)
    uv = rng.random((n, 2)).astype(np.float32)

    def loss(key):
        si = local_si(mi.Vector3f(wo.T))
        si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
        return dr.sum(bsdf.eval(ctx, si, mi.Vector3f(wi.T)), axis=None)

    for key in ("t_rgb", "t_off"):
        dr.enable_grad(params[key])
        params.update()
        dr.backward(loss(key))
        g = dr.grad(params[key]).numpy()
        dr.disable_grad(params[key])
        base = params[key].numpy().copy()
        for idx in [(1, 2, 0), (5, 3, 4), (7, 7, 7)]:
            # CUDA evaluates in float16 (CoopNet): each of the 2000 terms is rounded to ~5e-4 relative, ~2e-3 on
            # the sum, i.e. 10 % of a ±1e-2 difference (seen: −2.65 vs FD −2.40); a 10× wider step shrinks it
            eps = 1e-1 if CUDA else 1e-2
            vals = []
            for sgn in (1, -1):
                t = base.copy()
                t[idx] += sgn * eps
                params[key] = mi.TensorXf(t)
                params.update()
                vals.append(float(loss(key).numpy()[0]))
            params[key] = mi.TensorXf(base)
            params.update()
            fd = (vals[0] - vals[1]) / (2 * eps)
            # f32 sums of 2000 terms: FD noise ~1e-3 relative; ReLU kinks inside ±eps are rare
            tol = 0.05 * abs(fd) + 5e-2 if CUDA else 0.03 * abs(fd) + 2e-2
            assert abs(g[idx] - fd) <= tol, (key, idx, g[idx], fd)


def test_gaussian_periodic_closed_forms():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((2, 32, 32, 3)).astype(np.float32)
    y = rng.standard_normal((2, 32, 32, 3)).astype(np.float32)
    # self-adjoint: <Gx, y> = <x, Gy> (used to pull gradients through the prefilter)
    a = np.sum(bf.gaussian_periodic(x, 2.0) * y)
    b = np.sum(x * bf.gaussian_periodic(y, 2.0))
    assert abs(a - b) < 1e-3 * abs(a) + 1e-3
    # constant preserved; a delta becomes the normalised periodic Gaussian with std tau
    np.testing.assert_allclose(bf.gaussian_periodic(np.ones((32, 32, 1), np.float32), 3.0), 1.0, atol=1e-5)
    d = np.zeros((64, 64, 1), np.float32)
    d[0, 0] = 1.0
    g = bf.gaussian_periodic(d, 2.0)[:, 0, 0]
    k = np.minimum(np.arange(64), 64 - np.arange(64))
    ref = np.exp(-k**2 / (2 * 2.0**2))
    np.testing.assert_allclose(g / g.sum(), ref / ref.sum(), atol=1e-5)


def _lambert_btf(seed: int, slices=16, res=16):
    """Closed-form BTF: a smooth albedo pattern, value = ρ(u)/π·cosθ_i."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    alb = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * (xx + c * 3) / res) * np.cos(2 * np.pi * yy / res)
                    for c in range(3)], -1) * rng.uniform(0.6, 1.0, 3)
    wi = np.stack([_hemi(rng, res * res).reshape(res, res, 3) for _ in range(slices)])
    wo = np.stack([_hemi(rng, res * res).reshape(res, res, 3) for _ in range(slices)])
    vals = alb[None] / np.pi * wi[..., 2:3]
    return SimpleNamespace(values=vals.astype(np.float16), wi=wi, wo=wo, meta={"name": f"lambert{seed}"})


@pytest.mark.slow
def test_basis_learns_a_closed_form_btf_and_resume_is_exact(tmp_path):
    """Train on 2 closed-form materials; a held-out one is fitted (textures only) to ≥ 30 dB on held-out
    slices. Then kill-and-resume: a run interrupted at 40 iterations continues to the same weights."""
    mats = [_lambert_btf(s) for s in range(2)]
    tr, ho = bf.split_slices(16)
    # 250 + 200 iterations of 4096 samples reach 32.3 dB here (400 + 300 of 8192: 33.3 dB, three times the time)
    s = bf.OptimSettings(iterations=250, batch=1 << 12, tau_rgb=bf.Prefilter(2, 0.5, 40), tau_off=bf.Prefilter(2, 1, 40))
    basis, hist = bf.train_basis(mats, s=s, slices=tr, progress=False)
    assert hist[-1]["l1"] < 0.5 * hist[0]["l1"]
    new = _lambert_btf(7)
    fs = bf.OptimSettings(iterations=200, batch=1 << 12, lr_tex=2e-2, tau_rgb=bf.Prefilter(2, 0.5, 30),
                          tau_off=bf.Prefilter(2, 1, 30))
    mat, _ = bf.fit_material(basis, new, tr, fs, progress=False)
    p = bf.heldout_psnr(basis, mat, new, ho)
    assert p >= 30.0, p

    ck = tmp_path / "ck.npz"
    short = bf.OptimSettings(iterations=42, batch=1 << 12, checkpoint_every=40)
    half = bf.OptimSettings(**{**short.__dict__, "iterations": 40})
    # One Dr.Jit thread (conftest) makes both runs bit-reproducible, so resume must be exact.
    full, h_full = bf.train_basis(mats[:1], s=short, slices=tr, progress=False)
    bf.train_basis(mats[:1], s=half, slices=tr, checkpoint=ck, progress=False)   # "killed" at 40
    resumed, h_res = bf.train_basis(mats[:1], s=short, slices=tr, checkpoint=ck, progress=False)
    assert h_res[0]["iteration"] == 0 and h_res[-1]["iteration"] == 41  # history continued, not restarted
    if CUDA:  # atomics reorder float sums there: after 42 Adam steps two runs' L1 differed by 1.1e-6 of 0.041 and
        # their weights (typically ±0.2) by up to 2.6e-4 in one H100 run and 1.0e-3 in another (Adam amplifies
        # the reordering chaotically): 5e-3, 2.5 % of a typical weight, is the bound there
        assert abs(h_res[-1]["l1"] - h_full[-1]["l1"]) < 1e-3 * h_full[-1]["l1"]
        for k, a in full.arrays().items():
            np.testing.assert_allclose(resumed.arrays()[k], a, rtol=0, atol=5e-3, err_msg=k)
    else:
        assert h_res[-1]["l1"] == h_full[-1]["l1"]
        for k, a in full.arrays().items():
            np.testing.assert_array_equal(resumed.arrays()[k], a, err_msg=k)
    other = bf.OptimSettings(**{**short.__dict__, "seed": 1})
    with pytest.raises(CheckpointError, match=r"other settings or data \(settings.seed: 0 → 1\)"):
        bf.train_basis(mats[:1], s=other, slices=tr, checkpoint=ck, progress=False)


def test_bad_files_and_parameters_are_named(tmp_path):
    _, _, b, m = _files(tmp_path)
    with pytest.raises(RuntimeError, match="'basis'"):
        mi.load_dict({"type": "neural_btf", "material": m})
    with pytest.raises(RuntimeError, match="nope.npz"):
        mi.load_dict({"type": "neural_btf", "basis": b, "material": str(tmp_path / "nope.npz")})
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(nb.NeuralBTFError, match="corrupt.npz"):
        nb.load_basis(bad)
    with pytest.raises(RuntimeError, match="tiling"):
        mi.load_dict({"type": "neural_btf", "basis": b, "material": m, "tiling": -1.0})
    with pytest.raises(RuntimeError, match="'network' = 'gpu'"):
        mi.load_dict({"type": "neural_btf", "basis": b, "material": m, "network": "gpu"})
    if not CUDA:  # auto, the default width-64 basis (> 4096 weights): constants if symbolic, CoopVec if evaluated
        assert isinstance(mi.load_dict({"type": "neural_btf", "basis": b, "material": m}).m_rgb, nb.ModeNet)
    t = np.zeros((8, 8, 4), np.float32)
    nb.save_material(tmp_path / "four.npz", nb.NeuralMaterial(t, t))
    with pytest.raises(nb.NeuralBTFError, match="4 channels"):
        nb.load_material(tmp_path / "four.npz", channels=8)
    with pytest.raises(nb.NeuralBTFError, match="NaN"):
        nb.NeuralMaterial(t * np.nan, t)


@pytest.mark.slow
def test_material_can_be_fitted_through_full_renders(tmp_path):
    """prb renders of a neural_btf plane: Adam on t_rgb moves a perturbed material towards the
    target's renders (image loss falls by ≥ 50% in 12 steps), and the texture error falls too. Three layers, not
    the default four: the prb kernel inlines the network, and compiling the deeper one was most of this test's time."""
    basis, mat, b, m = _files(tmp_path, res=8, scale=0.5, config=nb.BasisConfig(depth=3))
    rng = np.random.default_rng(3)
    start = nb.NeuralMaterial(mat.t_off, mat.t_rgb + (rng.standard_normal(mat.t_rgb.shape) * 0.5).astype(np.float32))
    nb.save_material(tmp_path / "start.npz", start)

    def scene(material):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "prb", "max_depth": 2},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at([0.3, 0.4, 2.5], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
            "sun": {"type": "directional", "direction": [-0.3, -0.2, -1.0], "irradiance": {"type": "rgb", "value": 3.0}},
            "plane": {"type": "rectangle", "bsdf": {"type": "neural_btf", "basis": b, "material": material}},
        })

    target = mi.render(scene(m), spp=16, seed=0)
    sc = scene(str(tmp_path / "start.npz"))
    params = mi.traverse(sc)
    key = "plane.bsdf.t_rgb"
    opt = mi.ad.Adam(lr=0.05)
    opt[key] = params[key]
    params.update(opt)
    losses = []
    for it in range(12):
        img = mi.render(sc, params, spp=4, seed=it + 1)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        params.update(opt)
        losses.append(float(np.asarray(loss.numpy()).ravel()[0]))
    assert losses[-1] < 0.5 * losses[0], losses
    err0 = np.abs(start.t_rgb - mat.t_rgb).mean()
    err1 = np.abs(params[key].numpy() - mat.t_rgb).mean()
    assert err1 < err0, (err0, err1)


def test_corrupt_checkpoint_is_named(tmp_path):
    ck = tmp_path / "ck.npz"
    ck.write_bytes(b"truncated")
    with pytest.raises(CheckpointError, match="ck.npz: damaged checkpoint .*delete it to start over"):
        bf.train_basis([_lambert_btf(0)], s=bf.OptimSettings(iterations=2, batch=256), checkpoint=ck, progress=False)


def test_training_iterations_reuse_their_kernels():
    # Every iteration uploads a fresh random batch; with aligned uploads (mi_plugins/arrays.py) the
    # iterations after the first ones run kernels compiled already. Before, each batch's alignment
    # picked one of 2^k kernel variants (183 compilations of one kernel in the BTF bench test).
    from conftest import compiled_kernels

    mats = [_lambert_btf(0, slices=4, res=8)]
    tr = np.arange(4)
    s = bf.OptimSettings(iterations=3, batch=1 << 10)
    bf.train_basis(mats, s=s, slices=tr, progress=False)
    with compiled_kernels() as k:
        bf.train_basis(mats, s=bf.OptimSettings(iterations=6, batch=1 << 10, seed=5), slices=tr, progress=False)
    assert k.count == 0, k.count
