"""GAN refinement stages (issue 6): model shapes, the image bridge vs finite differences, loss closed forms,
training/resume on a tiny synthetic paired task, joint geometry + GAN training, CLI errors."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from foundation.errors import CheckpointError, UsageError
from foundation.loop import read_checkpoint

from foundation.bridge import drjit_images_to_torch
from generative.gan.cyclegan import CycleGAN, CycleGANConfig, ResnetGenerator
from generative.gan.data import PairedViews, random_crops
from generative.gan.train import GanTrainSettings, build_model, train_gan
from generative.gan.morph_gan import MorphGAN, paired_input
from generative.gan.pix2pix import PatchDiscriminator, Pix2Pix, Pix2PixConfig, UNetGenerator, gan_loss, receptive_field

TINY = Pix2PixConfig(ngf=4, ndf=4, levels=3)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One torch thread: with the 2 cores shared, torch's default 2 threads spin-wait (100× slower here)."""
    from foundation.threads import torch_threads

    with torch_threads(1):
        yield


# -- shapes -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("residual", [True, False])
def test_pix2pix_shapes_default_config(residual):
    m = Pix2Pix(replace(Pix2PixConfig(), residual=residual))
    x = torch.rand(2, 3, 64, 64)
    y = m(x)
    assert y.shape == (2, 3, 64, 64)
    assert m.D(torch.cat([x, y], 1)).shape == (2, 1, 6, 6)  # 64/8 − 2 patches per side
    assert m(torch.rand(1, 3, 128, 128)).shape == (1, 3, 128, 128)  # fully convolutional: whole views at inference
    if residual:  # zero-initialised last layer: G(x) = x before training
        torch.testing.assert_close(y, x, rtol=0, atol=0)
    else:
        assert 0 <= float(y.detach().min()) and float(y.detach().max()) <= 1  # tanh head mapped to [0, 1]
    with pytest.raises(ValueError, match="divisible by 32"):
        m(torch.rand(1, 3, 48, 48))


def test_patchgan_receptive_field_is_70_measured_by_gradient():
    """Closed form (70 for 3 strided layers) equals the support of d(centre logit)/d(input)."""
    assert receptive_field(3) == 70
    d = PatchDiscriminator(3, ndf=4, d_layers=3).eval()
    for k, mod in enumerate(d.net):  # instance norm couples all pixels; the claim is about the conv stack
        if isinstance(mod, torch.nn.InstanceNorm2d):
            d.net[k] = torch.nn.Identity()
    x = torch.rand(1, 3, 160, 160, requires_grad=True)
    out = d(x)
    out[0, 0, out.shape[2] // 2, out.shape[3] // 2].backward()
    rows = torch.nonzero(x.grad.abs().sum((0, 1)).sum(1)).ravel()
    assert int(rows.max() - rows.min() + 1) == 70


def test_cyclegan_and_morph_gan_shapes():
    c = CycleGAN(CycleGANConfig(ngf=4, ndf=4, n_blocks=2))
    x = torch.rand(2, 3, 32, 32)
    assert c(x).shape == c.F_(x).shape == (2, 3, 32, 32)
    assert c.D_X(x).shape == c.D_Y(x).shape == (2, 1, 2, 2)
    assert ResnetGenerator(CycleGANConfig(ngf=4, n_blocks=1))(torch.rand(1, 3, 20, 28)).shape == (1, 3, 20, 28)
    torch.testing.assert_close(c(x), x, rtol=0, atol=0)  # residual head starts as the identity
    r, m = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    full, part = MorphGAN(TINY), MorphGAN(TINY, partial=True)
    assert full.make_input(r, m).shape == (2, 6, 32, 32) and full(full.make_input(r, m)).shape == (2, 3, 32, 32)
    assert torch.equal(part.make_input(r, m), m) and part(m).shape == (2, 3, 32, 32)
    assert full.D(torch.cat([full.make_input(r, m), m], 1)).shape == (2, 1, 2, 2)  # D sees p ‖ y: 9 channels
    with pytest.raises(ValueError, match="shapes differ"):
        paired_input(r, m[:, :, :16])


def test_seeded_init_is_reproducible_and_seed_dependent():
    a, b, c = UNetGenerator(TINY, seed=3), UNetGenerator(TINY, seed=3), UNetGenerator(TINY, seed=4)
    wa, wb, wc = (torch.cat([p.detach().ravel() for p in m.parameters()]) for m in (a, b, c))
    assert torch.equal(wa, wb) and not torch.equal(wa, wc)
    conv = [p for n, p in a.named_parameters() if n.endswith("weight") and p.ndim == 4][:-1]  # last: zero
    assert abs(float(torch.cat([w.detach().ravel() for w in conv]).std()) - 0.02) < 0.002  # N(0, 0.02), the paper's init


# -- bridge: Dr.Jit image → torch function, gradients both ways vs central differences ------------------------------


def test_drjit_images_to_torch_gradients_match_central_differences():
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(6, 2, 3, padding=1).double()

    def f(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # quadratic: central FD is exact up to rounding
        return (conv(torch.cat([a, b], 1).double()) ** 2).mean()

    conv_f = drjit_images_to_torch(lambda a, b: f(a, b).float())
    rng = np.random.default_rng(1)
    a0, b0 = rng.random((5, 4, 3)).astype(np.float32), rng.random((5, 4, 3)).astype(np.float32)
    a, b = mi.TensorXf(a0), mi.TensorXf(b0)
    dr.enable_grad(a)
    loss = 3.0 * conv_f(a, b)  # Dr.Jit code around the torch call
    dr.backward(loss)
    ga = np.array(dr.grad(a))
    gw = conv.weight.grad.detach().numpy().copy()

    def value(aa: np.ndarray) -> float:
        t = torch.from_numpy(aa.astype(np.float64)).permute(2, 0, 1)[None]
        tb = torch.from_numpy(b0.astype(np.float64)).permute(2, 0, 1)[None]
        with torch.no_grad():
            return 3.0 * float(f(t, tb))

    eps = 1e-3
    fd = np.zeros_like(a0, np.float64)
    for idx in np.ndindex(*a0.shape):
        e = np.zeros_like(a0, np.float64)
        e[idx] = eps
        fd[idx] = (value(a0 + e) - value(a0 - e)) / (2 * eps)
    # float32 forward inside Dr.Jit vs float64 FD: relative 1e-4 of the gradient scale.
    np.testing.assert_allclose(ga, fd, atol=1e-4 * np.abs(fd).max())
    assert np.abs(fd).max() > 1e-3

    # Into the torch parameters (the generator-weights side): FD on one weight per output channel.
    for k in range(2):
        w = conv.weight.data
        old = float(w[k, 0, 1, 1])
        vals = []
        for s in (+eps, -eps):
            w[k, 0, 1, 1] = old + s
            vals.append(value(a0))
        w[k, 0, 1, 1] = old
        assert abs(gw[k, 0, 1, 1] - (vals[0] - vals[1]) / (2 * eps)) < 1e-4 * max(abs(gw).max(), 1e-6)
    assert float(loss.array[0]) == pytest.approx(value(a0), rel=1e-5)


def test_drjit_images_to_torch_rejects_non_images():
    with pytest.raises(ValueError, match="expected \\(H, W, C\\)"):
        drjit_images_to_torch(lambda a: a.sum())(mi.TensorXf(np.zeros((4, 3), np.float32)))


# -- losses: closed forms ---------------------------------------------------------------------------------------------


def test_gan_losses_closed_forms():
    z = torch.tensor([[-2.0, -0.5], [0.0, 3.0]])
    assert float(gan_loss(z, True, "lsgan")) == pytest.approx(float(((z - 1) ** 2).mean()), rel=1e-6)
    assert float(gan_loss(z, False, "lsgan")) == pytest.approx(float((z**2).mean()), rel=1e-6)
    # BCE with logits: −log σ(z) = softplus(−z), −log(1 − σ(z)) = softplus(z).
    assert float(gan_loss(z, True)) == pytest.approx(float(np.mean(np.log1p(np.exp(-z.numpy())))), rel=1e-6)
    assert float(gan_loss(z, False)) == pytest.approx(float(np.mean(np.log1p(np.exp(z.numpy())))), rel=1e-6)
    with pytest.raises(ValueError):
        gan_loss(z, True, "wgan")


def test_pix2pix_objectives_are_gan_plus_100_l1_and_half_d():
    torch.manual_seed(0)
    m = Pix2Pix(TINY)
    x, y = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    fake = m.G(x)
    lg, terms = m.generator_loss(x, y, fake)
    adv = F.softplus(-m.D(torch.cat([x, fake], 1))).mean()
    assert m.cfg.lambda_l1 == 100.0
    assert float(lg.detach()) == pytest.approx(float((adv + 100.0 * (fake - y).abs().mean()).detach()), rel=1e-5)
    assert terms["g_l1"] == pytest.approx(float((fake - y).abs().mean().detach()), rel=1e-5)
    ld, _ = m.discriminator_loss(x, y, fake)
    real = F.softplus(-m.D(torch.cat([x, y], 1))).mean()
    fk = F.softplus(m.D(torch.cat([x, fake], 1))).mean()
    assert float(ld.detach()) == pytest.approx(0.5 * float((real + fk).detach()), rel=1e-5)
    ld.backward()
    assert all(p.grad is None for p in m.G.parameters())  # D's loss does not reach G (fake detached)


def test_cyclegan_objective_lsgan_cycle_10_identity_half():
    torch.manual_seed(0)
    c = CycleGAN(CycleGANConfig(ngf=4, ndf=4, n_blocks=1))
    x, y = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    loss, terms, (fy, fx) = c.generator_loss(x, y)
    adv = ((c.D_Y(c.G(x)) - 1) ** 2).mean() + ((c.D_X(c.F_(y)) - 1) ** 2).mean()
    cyc = (c.F_(c.G(x)) - x).abs().mean() + (c.G(c.F_(y)) - y).abs().mean()
    idt = (c.G(y) - y).abs().mean() + (c.F_(x) - x).abs().mean()
    assert float(loss.detach()) == pytest.approx(float((adv + 10.0 * cyc + 0.5 * 10.0 * idt).detach()), rel=1e-5)
    assert terms["cycle"] == pytest.approx(float(cyc.detach()), rel=1e-5)
    ld, _ = c.discriminator_loss(x, y, fy, fx)
    expect = 0.5 * (((c.D_Y(y) - 1) ** 2).mean() + (c.D_Y(fy) ** 2).mean()) \
        + 0.5 * (((c.D_X(x) - 1) ** 2).mean() + (c.D_X(fx) ** 2).mean())
    assert float(ld.detach()) == pytest.approx(float(expect.detach()), rel=1e-5)


# -- data and training -----------------------------------------------------------------------------------------------


def synthetic_views(n: int = 8, res: int = 48, seed: int = 0) -> PairedViews:
    """Blurred-noise "renders"; the "photo" is a fixed colour transform of them, the "morphed" render halfway."""
    rng = np.random.default_rng(seed)
    base = rng.random((n, res // 4, res // 4, 3)).astype(np.float32)
    rendered = np.repeat(np.repeat(base, 4, 1), 4, 2) * 0.6 + 0.1
    photos = np.clip(rendered[..., [1, 2, 0]] * 0.9 + 0.05, 0, 1).astype(np.float32)
    morphed = (0.5 * rendered + 0.5 * photos).astype(np.float32)
    return PairedViews(photos, rendered.astype(np.float32), morphed, list(range(n - 2)), [n - 2, n - 1], "synthetic")


def test_random_crops_are_aligned_seeded_and_whole_when_large():
    d = synthetic_views()
    a = random_crops([d.rendered, d.photos], np.array([0, 3]), 16, np.random.default_rng(5))
    b = random_crops([d.rendered, d.photos], np.array([0, 3]), 16, np.random.default_rng(5))
    assert a[0].shape == (2, 3, 16, 16) and torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    # Same window in both stacks: the photo crop is the channel-permuted transform of the render crop.
    np.testing.assert_allclose(a[1].numpy(), np.clip(a[0].numpy()[:, [1, 2, 0]] * 0.9 + 0.05, 0, 1), atol=1e-6)
    (w,) = random_crops([d.rendered], np.array([1]), 64, np.random.default_rng(0), flip=False)
    np.testing.assert_array_equal(w[0].permute(1, 2, 0).numpy(), d.rendered[1])


def _tiny(model: str, steps: int) -> GanTrainSettings:
    return GanTrainSettings(model=model, steps=steps, max_seconds=None, batch=2, crop=32, ngf=4, ndf=4, levels=3,
                            lr=2e-3, checkpoint_every=5, eval_every=10, seed=0)


def test_training_reduces_heldout_error_on_a_paired_task(tmp_path):
    d = synthetic_views()
    m = train_gan(d, tmp_path / "p2p", _tiny("pix2pix", 80), show_progress=False)
    curve = [p.heldout_mse for p in m.curve]
    assert curve[-1] < 0.5 * curve[0], curve
    assert m.training.steps == 80 and (tmp_path / "p2p" / "metrics.json").is_file()
    assert m.train_views == 5 and m.val_views == 1 and m.best_step in [p.step for p in m.curve]
    assert m.heldout.mse <= m.last.mse * 1.5  # the selected G is a held-out-sane choice, not a diverged one


def test_split_validation_every_kth_view():
    from generative.gan.train import split_validation

    t, v = split_validation(list(range(12)), 6)
    assert v.tolist() == [5, 11] and t.tolist() == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10]
    assert split_validation([1, 2, 3], 0)[1].size == 0


@pytest.mark.parametrize("model", ["morph_gan", "cyclegan"])
def test_resume_reproduces_an_uninterrupted_run(tmp_path, model):
    d = synthetic_views()
    s = replace(_tiny(model, 12), checkpoint_every=4)
    full = train_gan(d, tmp_path / "a", s, show_progress=False)
    assert train_gan(d, tmp_path / "b", s, show_progress=False, budget_steps=5) is None  # "killed" after 5 steps
    assert train_gan(d, tmp_path / "b", s, show_progress=False, budget_steps=4) is None
    resumed = train_gan(d, tmp_path / "b", s, show_progress=False)
    a, b = read_checkpoint(tmp_path / "a" / "checkpoint.npz"), read_checkpoint(tmp_path / "b" / "checkpoint.npz")
    assert a.run.step == b.run.step == 12
    for k, v in a.stage["model"].items():  # one torch thread (conftest): the same ops give the same bits
        torch.testing.assert_close(b.stage["model"][k], v, rtol=0, atol=0)
    assert b.run.losses == a.run.losses
    assert resumed.heldout.mse == full.heldout.mse
    with pytest.raises(CheckpointError, match=r"other settings or data \(settings.lr: 0.002 → 0.001\)"):
        train_gan(d, tmp_path / "b", replace(s, lr=1e-3), show_progress=False)


def test_build_model_rejects_unknown_names():
    with pytest.raises(UsageError, match="model must be one of pix2pix, cyclegan, morph_gan_partial, morph_gan, "
                                         "got 'pix3pix'"):
        build_model(GanTrainSettings(model="pix3pix"))


# -- joint geometry + GAN training through Mitsuba -------------------------------------------------------------------


@pytest.mark.slow
def test_joint_training_descends_through_generator_and_renderer(tmp_path):
    """One loss, two optimisers: a joint step must lower that loss on its own batch, through both parts.

    Oracle (first-order descent): with the loop's RNG state restored, step 0 is evaluated again after its
    update — same view, same render seed, one Dr.Jit and one torch thread, so the only change is the update.
    Adam's first step moves every parameter against the sign of its gradient, so a correct gradient through
    dr.wrap (G) and through Mitsuba (vertices, colours) lowers the L1 terms (the same apply also trains D, so
    the adversarial term is not a descent measure); a wrong sign or a lost gradient does not. Both parts must also have moved, and a full run must end finite.
    """
    from foundation.loop import rng_state, set_rng_state
    from generative.gan.data import load_paired_views
    from generative.gan.joint import JointSettings, JointStage, train_joint
    from inverse.morph import MorphBenchmarkSettings, load_morph_benchmark, make_morph_benchmark

    mesh = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"
    bdir = make_morph_benchmark(mesh, tmp_path / "bench", MorphBenchmarkSettings(
        n_views=4, test_every=4, resolution=32, spp=4, coarse_vertices=600), show_progress=False)
    bench = load_morph_benchmark(bdir)
    (tmp_path / "morph").mkdir()
    shutil.copyfile(bench.coarse, tmp_path / "morph" / "morphed.ply")  # stand-in morph result
    data = load_paired_views(bench, tmp_path / "morph", show_progress=False)
    gs = replace(_tiny("morph_gan", 1), levels=3, lr=1e-4)
    s = JointSettings(steps=3, max_seconds=None, gan=gs, spp=8, lr=0.005, lr_colour=0.005, checkpoint_every=1)

    stage = JointStage(bench, data, tmp_path / "one", s)
    v0, c0 = stage.mesh_state()
    g0 = {k: v.clone() for k, v in stage.model.G.state_dict().items()}
    state, torch_state = rng_state(stage.rng), torch.get_rng_state()
    before = stage.step(0)
    stage.apply(0)
    set_rng_state(stage.rng, state)
    torch.set_rng_state(torch_state)
    after = stage.step(0)
    stage.discard(0)
    v1, c1 = stage.mesh_state()
    stage.close()
    # apply() also updates D, whose improvement may raise G's adversarial term: the terms through G (its L1 to the
    # photo, via dr.wrap) and through Mitsuba (the render's L1) must fall.
    for term in ("g_l1", "morph_l1"):
        assert after.log[term] < before.log[term], (term, before.log, after.log)
    assert np.abs(v1 - v0).max() > 0 and np.abs(c1 - c0).max() > 0  # the renderer's gradient reached the mesh
    assert max(float((stage.model.G.state_dict()[k] - v).abs().max()) for k, v in g0.items()
               if v.is_floating_point()) > 0  # … and dr.wrap's reached G

    m = train_joint(bench, data, tmp_path / "joint", s, show_progress=False)
    assert np.isfinite(m.heldout.mse) and m.training.steps == 3 and m.training.skipped_steps == 0
    assert (tmp_path / "joint" / "joint.ply").is_file()


# -- CLI ------------------------------------------------------------------------------------------------------------


def test_cli_errors_name_the_bad_path(tmp_path, capsys):
    from photoreal.cli import main

    bad = tmp_path / "no_such_benchmark"
    assert main(["gan", "train", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert str(bad) in capsys.readouterr().err
    assert main(["gan", "eval", str(bad), "--run", str(tmp_path / "o")]) == 2
    assert str(bad) in capsys.readouterr().err
    # A benchmark folder without a morph run: the missing morphed mesh is named.
    from inverse.morph import MorphBenchmarkSettings, make_morph_benchmark

    mesh = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"
    bdir = make_morph_benchmark(mesh, tmp_path / "bench", MorphBenchmarkSettings(
        n_views=4, resolution=32, spp=2, coarse_vertices=300), show_progress=False)
    nomorph = tmp_path / "nomorph"
    assert main(["gan", "train", str(bdir), "--morph", str(nomorph), "--out", str(tmp_path / "o")]) == 2
    assert str(nomorph / "morphed.ply") in capsys.readouterr().err
    # A resolution the U-Net cannot take is refused before anything is rendered (not after).
    b24 = make_morph_benchmark(mesh, tmp_path / "b24", MorphBenchmarkSettings(
        n_views=4, resolution=24, spp=2, coarse_vertices=300), show_progress=False)
    assert main(["gan", "train", str(b24), "--out", str(tmp_path / "o24")]) == 2
    assert "24² views do not divide by 2^levels = 32" in capsys.readouterr().err
    assert not (b24 / "morph").exists() and not (tmp_path / "o24").exists()
    for argv, flag in ((["--steps", "0"], "--steps must be ≥ 1"), (["--seconds", "-5"], "--seconds must be > 0")):
        assert main(["gan", "train", str(bdir), "--out", str(tmp_path / "o"), *argv]) == 2
        assert flag in capsys.readouterr().err


def test_demo_section_shows_the_bench_table_only_when_the_json_exists(tmp_path):
    import json

    from photoreal.demo import demo_gan
    from photoreal.benchmarks.gan import ordering

    assert demo_gan(tmp_path, tmp_path / "nothing_here") is None
    assert demo_gan(tmp_path, None) is None
    row = {"mse": 0.01, "me": 0.05, "one_minus_ssim": 0.2, "nrmse": 0.1, "sam_deg": 3.0, "flip": 0.1, "psnr": 20.0}
    names = ("input", "morphed", "pix2pix", "cyclegan", "morph_gan_partial", "morph_gan", "joint")
    heldout = {n: dict(row, mse=0.01 - 0.001 * k) for k, n in enumerate(names)}
    r = {"heldout": heldout, "train_seconds": {"pix2pix": 5.0}, "infer_ms_per_image": {"pix2pix": 2.0}}
    b = {**r, "cases": {"village": r}, "ordering": ordering(heldout), "settings": {
        "cases": ["village"], "morph_iterations": 1, "seconds_per_model": 5.0, "crop": 64, "joint_seconds": 5.0}}
    (tmp_path / "gan.json").write_text(json.dumps(b))
    assert demo_gan(tmp_path, tmp_path)["joint"] == pytest.approx(0.004)
    page = (tmp_path / "sections" / "45_gan.html").read_text()
    assert "morph_gan_partial" in page and "0.004" in page and "morph_gan_beats_pix2pix_mse = True" in page


# -- artifact regions and fine-tuning (joint vs two-stage at equal extra time) ---------------------------------------


def test_region_metrics_match_whole_image_metrics_and_ignore_outside_pixels():
    from foundation.metrics import image_metrics, region_metrics

    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 1, (32, 32, 3))
    test = np.clip(ref + rng.normal(0, 0.05, ref.shape), 0, 1)
    full = region_metrics(test, ref, np.ones((32, 32), bool))
    whole = image_metrics(test, ref)
    assert full["mse"] == pytest.approx(whole.mse, rel=1e-12) and full["me"] == pytest.approx(whole.me, rel=1e-12)
    assert full["pixels"] == 32 * 32
    # errors only in the left half: the right-half region sees none of them, the left half all
    half = ref.copy()
    half[:, :16] = test[:, :16]
    left, right = np.zeros((32, 32), bool), np.zeros((32, 32), bool)
    left[:, :16], right[:, 16:] = True, True
    assert region_metrics(half, ref, right)["mse"] == 0.0
    assert region_metrics(half, ref, left)["mse"] == pytest.approx(np.mean((test[:, :16] - ref[:, :16]) ** 2))
    assert region_metrics(half, ref, ~(left | right))["pixels"] == 0


@pytest.mark.slow
def test_artifact_masks_cover_what_the_degradation_changed(tmp_path):
    """Oracle: pixels whose ground-truth depth changes when the cut chimneys are removed lie in the
    ``eroded_parts`` mask (and vice versa, up to a pixel); regions lie on the truth's surface."""
    from scipy import ndimage

    from inverse.morph import (MorphBenchmarkSettings, artifact_masks, load_morph_benchmark,
                                    make_morph_benchmark, sensor_dict)

    bench = load_morph_benchmark(make_morph_benchmark("village", tmp_path / "v", MorphBenchmarkSettings(
        n_views=4, test_every=2, resolution=64, spp=2), show_progress=False))
    ids = [0, 1, 2, 3]
    masks = artifact_masks(bench, ids)
    deg = bench.meta.degradation
    assert deg.chimneys_cut and masks["eroded_parts"].any() and masks["floating_parts"].any()
    assert masks["flat"].mean() > 0.2 and masks["edges"].mean() > 0.02
    assert not (masks["flat"] & masks["edges"]).any()

    def depth(skip: set[int]) -> np.ndarray:
        shapes = {p: {"type": "ply", "filename": str(bench.path / f"gt_{p}.ply")}
                  for p in bench.meta.gt_parts if int(p[4:]) not in skip}
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "d:depth"}, **shapes})
        res, fov = bench.meta.resolution, bench.meta.fov
        return np.stack([np.array(mi.render(scene, sensor=mi.load_dict(sensor_dict(bench.meta.cameras[i], res, fov)),
                                            spp=16, seed=i))[..., 0] for i in ids])

    changed = np.abs(depth(set()) - depth({c - 100 for c in deg.chimneys_cut})) > 1e-3
    grow = lambda m: np.stack([ndimage.binary_dilation(x, iterations=1) for x in m])  # noqa: E731
    assert changed.any()
    assert not (changed & ~grow(masks["eroded_parts"])).any()
    assert not (masks["eroded_parts"] & ~grow(changed)).any()


@pytest.mark.slow
def test_finetunes_start_from_the_two_stage_model_and_mesh(tmp_path):
    """With (near-)zero learning rates both fine-tunes must reproduce the two-stage Morph-GAN's held-out
    outputs: the joint one re-renders its start mesh with the paired data's renderer (same seeds), so any
    mismatch in initial weights, start mesh or test-time light transport shows up here."""
    from generative.gan.data import load_paired_views
    from generative.gan.joint import JointSettings, train_joint
    from generative.gan.train import load_heldout_predictions
    from inverse.morph import MorphBenchmarkSettings, load_morph_benchmark, make_morph_benchmark

    mesh = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"
    bench = load_morph_benchmark(make_morph_benchmark(mesh, tmp_path / "bench", MorphBenchmarkSettings(
        n_views=4, test_every=4, resolution=32, spp=4, coarse_vertices=600), show_progress=False))
    (tmp_path / "morph").mkdir()
    shutil.copyfile(bench.coarse, tmp_path / "morph" / "morphed.ply")
    data = load_paired_views(bench, tmp_path / "morph", show_progress=False)
    gs = replace(_tiny("morph_gan", 4), levels=3, crop=32, val_every=0)
    train_gan(data, tmp_path / "mg", gs, show_progress=False)
    ref = load_heldout_predictions(tmp_path / "mg", data.test)
    frozen = replace(gs, lr=1e-12, init_from=str(tmp_path / "mg"))
    train_gan(data, tmp_path / "mg_ft", replace(frozen, steps=2), show_progress=False)
    np.testing.assert_allclose(load_heldout_predictions(tmp_path / "mg_ft", data.test), ref, atol=2e-3)
    s = JointSettings(steps=2, max_seconds=None, gan=frozen, spp=2, lr=0.0, lr_colour=0.0,
                      init_from=str(tmp_path / "mg"), init_mesh=str(tmp_path / "morph" / "morphed.ply"))
    train_joint(bench, data, tmp_path / "jf", s, show_progress=False)
    # The large-steps round trip u = (I + λL)v → v moves vertices by ~1e-6: a few silhouette pixels
    # (< 0.5 %) may see another triangle; everything else matches to float16 output precision.
    diff = np.abs(load_heldout_predictions(tmp_path / "jf", data.test) - ref)
    assert np.mean(diff > 2e-3) < 5e-3 and diff.mean() < 1e-4, (np.mean(diff > 2e-3), diff.mean())
    # and a fresh G is far from it (the comparison above can fail)
    fresh = replace(s, init_from=None, gan=replace(frozen, init_from=None))
    train_joint(bench, data, tmp_path / "jfresh", fresh, show_progress=False)
    assert np.abs(load_heldout_predictions(tmp_path / "jfresh", data.test) - ref).max() > 1e-2
    with pytest.raises(ValueError, match="holds a 'morph_gan' run, not 'pix2pix'"):
        train_gan(data, tmp_path / "bad", replace(_tiny("pix2pix", 2), levels=3, init_from=str(tmp_path / "mg")),
                  show_progress=False)
