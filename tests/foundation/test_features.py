"""Pretrained MobileNetV2 features (foundation.features): the ImageNet weights are the real ones (they classify
photographs), a missing or damaged file is named, and FID / KID / the perceptual distance meet their closed forms."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from foundation import features
from foundation.errors import FailureError, UsageError


@pytest.fixture(autouse=True)
def one_torch_thread():
    from foundation.threads import torch_threads

    with torch_threads(1):
        yield


def _top1(img: np.ndarray) -> int:
    net = features.load_mobilenet()
    x = torch.from_numpy(np.ascontiguousarray(img[..., :3].transpose(2, 0, 1)[None], np.float32) / 255)
    x = torch.nn.functional.interpolate(x, size=(224, 224), mode="bilinear", antialias=True)
    with torch.no_grad():
        return int(net(features.normalise(x, linear=False)).argmax())


def test_imagenet_weights_classify_photographs():
    """Oracle: ImageNet labels of two scikit-image photographs (281–285 are the domestic cats, 967 espresso)."""
    import skimage.data

    assert _top1(skimage.data.chelsea()) in range(281, 286)
    assert _top1(skimage.data.coffee()) == 967
    assert features.file_sha256(features.weights_path()) == features.WEIGHTS_SHA256


def test_missing_and_damaged_weights_are_named(tmp_path, monkeypatch):
    monkeypatch.setenv(features.WEIGHTS_ENV, str(tmp_path / "nope.pth"))
    with pytest.raises(UsageError, match="nope.pth: MobileNetV2 weights file not found"):
        features.load_mobilenet()
    bad = tmp_path / "damaged.pth"
    monkeypatch.delenv(features.WEIGHTS_ENV)
    shutil.copyfile(features.weights_path(), bad)
    with open(bad, "r+b") as f:
        f.seek(1000)
        f.write(b"\x00\x01\x02")
    with pytest.raises(FailureError, match="damaged.pth: SHA-256 .* is not torchvision's"):
        features.load_mobilenet(bad)


def test_image_features_shapes_and_linear_input():
    rng = np.random.default_rng(0)
    imgs = rng.random((3, 64, 64, 3)).astype(np.float32)
    f = features.image_features(imgs)
    assert f.shape == (3, features.FEATURE_DIM) and np.isfinite(f).all()
    assert (f >= 0).all()  # pooled ReLU6 outputs
    # batch-independent up to float32 summation order (measured ≤ 3e-6 on values ~0.1–1)
    np.testing.assert_allclose(features.image_features(imgs[1:2]), f[1:2], rtol=0, atol=2e-5)
    with pytest.raises(UsageError, match=r"\(N, H, W, 3\)"):
        features.image_features(rng.random((2, 8, 8)))


def test_spatial_features_are_the_positions_whose_mean_is_the_image_feature():
    """Oracle: image_features is the spatial mean of the last feature map, so the 16 position vectors of a 128²
    image (4×4 map) average to it (float32 summation order: atol 2e-5)."""
    rng = np.random.default_rng(2)
    imgs = rng.random((2, 128, 128, 3)).astype(np.float32)
    sp = features.spatial_features(imgs)
    assert sp.shape == (2 * 16, features.FEATURE_DIM) and (sp >= 0).all()
    np.testing.assert_allclose(sp.reshape(2, 16, -1).mean(1), features.image_features(imgs), rtol=0, atol=2e-5)


def test_fid_closed_forms():
    """FID(x, x) = 0; a translation by d of the same sample adds exactly |d|² (equal covariances)."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 6)) @ rng.normal(size=(6, 6))
    d = np.array([0.5, -1.0, 0.0, 2.0, 0.1, 0.0])
    assert features.fid(x, x) == pytest.approx(0.0, abs=1e-8)
    assert features.fid(x, x + d) == pytest.approx(float(d @ d), rel=1e-6)
    # two Gaussians with diagonal covariances: tr(Cx + Cy − 2 √(Cx Cy)) = Σ (√a − √b)²
    a, b = np.array([1.0, 4.0, 9.0]), np.array([4.0, 1.0, 9.0])
    # sample covariances equal the targets exactly after whitening the samples
    z = rng.normal(size=(500, 3))
    z = (z - z.mean(0)) @ np.linalg.inv(np.linalg.cholesky(np.cov(z, rowvar=False))).T
    assert features.fid(z * np.sqrt(a), z * np.sqrt(b)) == pytest.approx(float(((np.sqrt(a) - np.sqrt(b)) ** 2).sum()),
                                                                          rel=1e-6)
    with pytest.raises(UsageError, match="at least 2"):
        features.fid(x[:1], x)


def test_kid_is_unbiased_and_grows_with_a_shift():
    """Unbiased: the mean over independent draws of two same-law sets is 0 within 3 standard errors;
    a shifted law gives a KID far above that spread."""
    rng = np.random.default_rng(2)
    same = [features.kid(rng.normal(size=(30, 8)), rng.normal(size=(30, 8))) for _ in range(300)]
    se = np.std(same) / np.sqrt(len(same))
    assert abs(np.mean(same)) < 3 * se, (np.mean(same), se)
    shifted = features.kid(rng.normal(size=(30, 8)), rng.normal(size=(30, 8)) + 1.0)
    assert shifted > 10 * np.std(same)


def test_kid_std_matches_the_spread_of_kid_over_independent_draws():
    """The jackknife standard error against the empirical std of KID over 300 independent pairs of 16-sample sets
    (the bench's size): within a factor 0.7–1.5 (jackknife variances are known to be conservative). Grouping rows
    that are copies of one another must widen it (the copies are one sample, not four)."""
    rng = np.random.default_rng(3)
    vals, ses = [], []
    for _ in range(300):
        x, y = rng.normal(size=(16, 8)), rng.normal(size=(16, 8)) + 0.3
        vals.append(features.kid(x, y))
        ses.append(features.kid_std(x, y))
    ratio = np.mean(ses) / np.std(vals)
    assert 0.7 < ratio < 1.5, ratio
    x, y = rng.normal(size=(16, 8)), rng.normal(size=(16, 8))
    xr, yr = np.repeat(x, 4, 0), np.repeat(y, 4, 0)
    g = np.repeat(np.arange(16), 4)
    assert features.kid_std(xr, yr, g, g) > 1.5 * features.kid_std(xr, yr)
    with pytest.raises(UsageError, match="group labels"):
        features.kid_std(x, y, g, None)


def test_perceptual_distance_zero_symmetric_and_monotone_in_blur():
    import skimage.data
    from scipy.ndimage import gaussian_filter

    img = skimage.data.astronaut()[::4, ::4, :3].astype(np.float32) / 255  # 128²
    blurred = [gaussian_filter(img, (s, s, 0)) for s in (0.5, 1.5, 4.0)]
    d = [float(features.perceptual_distance(img[None], b[None])[0]) for b in blurred]
    assert float(features.perceptual_distance(img[None], img[None])[0]) == pytest.approx(0.0, abs=1e-12)
    assert d[0] < d[1] < d[2], d
    assert float(features.perceptual_distance(blurred[1][None], img[None])[0]) == pytest.approx(d[1], rel=1e-5)
