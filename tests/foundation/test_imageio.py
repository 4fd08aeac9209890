"""foundation.imageio.read_image, the one reader of images a user gives: bit depths, modes, EXIF orientation and
transfer functions against Pillow's / OpenCV's own decodings (the oracles), bad files named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

from foundation.imageio import ImageIOError, read_image, srgb_to_linear, write_exr


def test_bit_depths_are_scaled_by_their_range(tmp_path):
    rng = np.random.default_rng(0)
    rgb8 = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "rgb8.png")
    np.testing.assert_array_equal(read_image(tmp_path / "rgb8.png", linear=False), rgb8 / np.float32(255))
    rgb16 = rng.integers(0, 65536, (5, 7, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb16[..., ::-1])  # OpenCV writes BGR
    got = read_image(tmp_path / "rgb16.png", linear=False)
    assert np.abs(got - rgb16 / 65535.0).max() < 1e-7  # all 16 bits, not Pillow's 8
    cv2.imwrite(str(tmp_path / "rgb16.tif"), rgb16[..., ::-1])
    assert np.abs(read_image(tmp_path / "rgb16.tif", linear=False) - rgb16 / 65535.0).max() < 1e-7
    grey16 = rng.integers(0, 65536, (5, 7), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), grey16)
    g = read_image(tmp_path / "g16.png", linear=False)
    assert g.shape == (5, 7, 3) and np.abs(g[..., 1] - grey16 / 65535.0).max() < 1e-7
    Image.fromarray(rgb8[..., 0] > 127).save(tmp_path / "bits.png")  # 1-bit
    np.testing.assert_array_equal(read_image(tmp_path / "bits.png", channels=1)[..., 0], rgb8[..., 0] > 127)


def test_modes_decode_as_pillow_converts_them(tmp_path):
    rng = np.random.default_rng(1)
    rgb = Image.fromarray(rng.integers(0, 256, (6, 6, 3), dtype=np.uint8))
    pal = rgb.quantize(8)
    pal.save(tmp_path / "p.png")
    np.testing.assert_array_equal(read_image(tmp_path / "p.png", linear=False),
                                  np.asarray(pal.convert("RGB")) / np.float32(255))
    rgb.convert("CMYK").save(tmp_path / "c.jpg", quality=100)
    want = np.asarray(Image.open(tmp_path / "c.jpg").convert("RGB")) / np.float32(255)
    np.testing.assert_array_equal(read_image(tmp_path / "c.jpg", linear=False), want)
    la = Image.merge("LA", (rgb.convert("L"), Image.fromarray(np.full((6, 6), 51, np.uint8))))
    la.save(tmp_path / "la.png")
    assert read_image(tmp_path / "la.png").shape == (6, 6, 3)
    np.testing.assert_allclose(read_image(tmp_path / "la.png", channels=1), 0.2, atol=1e-6)  # a cut-out's alpha
    rgba = read_image(tmp_path / "la.png", channels=4, linear=False)
    np.testing.assert_array_equal(rgba[..., 0], np.asarray(rgb.convert("L")) / np.float32(255))
    # transfer: linear=True is the sRGB decoding of what linear=False gives
    np.testing.assert_allclose(read_image(tmp_path / "p.png"), srgb_to_linear(read_image(tmp_path / "p.png",
                                                                                          linear=False)), atol=1e-7)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_turns_the_photo_as_pillow_does(orientation, tmp_path):
    a = np.random.default_rng(orientation).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    im = Image.fromarray(a)
    exif = im.getexif()
    exif[0x0112] = orientation
    im.save(tmp_path / "o.png", exif=exif)
    want = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "o.png")).convert("RGB")) / np.float32(255)
    got = read_image(tmp_path / "o.png", linear=False)
    assert got.shape == want.shape == ((4, 6, 3) if orientation < 5 else (6, 4, 3))
    np.testing.assert_array_equal(got, want)


def test_hdr_is_read_as_stored_and_bad_files_are_named(tmp_path):
    hdr = np.random.default_rng(2).uniform(0, 20, (4, 8, 3)).astype(np.float32)
    write_exr(tmp_path / "sky.exr", {"": hdr})
    np.testing.assert_array_equal(read_image(tmp_path / "sky.exr"), hdr)  # no sRGB decoding, no clipping
    hdr[1, 2, 0] = np.nan
    write_exr(tmp_path / "nan.exr", {"": hdr})
    with pytest.raises(ImageIOError, match="nan.exr: image has NaN/Inf values"):
        read_image(tmp_path / "nan.exr")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(ImageIOError, match="junk.png: not a readable exemplar"):
        read_image(tmp_path / "junk.png", what="exemplar")
    with pytest.raises(ImageIOError, match="gone.jpg: no such photo file"):
        read_image(tmp_path / "gone.jpg", what="photo")
    with pytest.raises(ImageIOError, match="is not a file"):
        read_image(tmp_path)
