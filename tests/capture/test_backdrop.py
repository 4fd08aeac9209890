"""Masks from a uniform backdrop (:mod:`inverse.capture.backdrop`) against photos whose object pixels are known by
construction, and the test that tells an object on a backdrop from a scene."""

from __future__ import annotations

import numpy as np

from inverse.capture.backdrop import BACKDROP_TOLERANCE, backdrop_mask, decide_backdrop


def _object_photo(seed: int, size: int = 96, frame: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A grey backdrop (linear 0.3, noise σ 0.004) with a disk of random colour patches; inside the disk a hole of
    the backdrop's own colour that does not touch the backdrop; a black frame where undistortion left no data.
    Returns (photo, the object's pixels)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:size, :size]
    cy, cx = size / 2 + rng.uniform(-6, 6, 2)
    r = np.hypot(y - cy, x - cx)
    obj = r < size * 0.3
    photo = 0.3 + rng.normal(0, 0.004, (size, size, 3))
    patches = rng.uniform(0.02, 1.0, (size // 8 + 1, size // 8 + 1, 3))
    # patch colours kept away from the backdrop's, so that the disk's edge is an edge
    near = np.abs(patches ** (1 / 2.2) - 0.3 ** (1 / 2.2)).max(-1) < 3 * BACKDROP_TOLERANCE
    patches[near] = 0.9
    photo[obj] = patches[y[obj] // 8, x[obj] // 8]
    photo[r < size * 0.08] = 0.3  # the backdrop's colour, enclosed by the object: object all the same
    photo[:frame], photo[-frame:], photo[:, :frame], photo[:, -frame:] = 0, 0, 0, 0
    valid = np.zeros_like(obj)
    valid[frame:-frame, frame:-frame] = True
    return np.clip(photo, 0, None).astype(np.float32), obj & valid


def test_the_mask_is_the_object_and_what_it_encloses():
    """Exactly the disk, the frame without data left out; the backdrop-coloured hole the disk encloses is object and
    unsure, and nothing else is unsure."""
    for seed in range(3):
        photo, want = _object_photo(seed)
        got, unsure = backdrop_mask(photo)
        assert np.array_equal(got, want), (seed, int((got != want).sum()))
        size = photo.shape[0]
        y, x = np.mgrid[:size, :size]
        hole = np.abs(photo ** (1 / 2.2) - 0.3 ** (1 / 2.2)).max(-1) <= BACKDROP_TOLERANCE
        assert np.array_equal(unsure, want & hole) and unsure.sum() >= np.pi * (0.08 * size) ** 2 * 0.8, seed


def test_photos_of_an_object_on_a_backdrop_have_one_and_a_scene_has_none():
    """Objects on the grey backdrop: uniform, its colour the backdrop's in sRGB (0.3^(1/2.2) = 0.579 within 0.01). A
    scene (sky above, textured ground below, as a landscape photo is): not uniform, and no masks follow from it."""
    d = decide_backdrop(_object_photo(s)[0] for s in range(5))
    assert d.uniform and d.uniform_photos == 5 and d.border_share > 0.99
    assert np.allclose(d.colour, 0.3 ** (1 / 2.2), atol=0.01), d.colour
    rng = np.random.default_rng(1)
    scenes = []
    for _ in range(5):
        img = np.empty((64, 96, 3), np.float32)
        img[:30] = np.linspace(0.4, 0.9, 30)[:, None, None] * np.array([0.5, 0.7, 1.0])
        img[30:] = rng.uniform(0.05, 0.4, (34, 96, 3))
        scenes.append(img)
    d = decide_backdrop(scenes)
    assert not d.uniform and d.uniform_photos == 0, d
    assert not decide_backdrop([]).uniform
