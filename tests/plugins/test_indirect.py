"""The ``indirect`` integrator (mi_plugins/integrators/indirect.py).

Oracles: Mitsuba's own ``path``. At ``min_depth`` 1 the plugin must *be* ``path`` — same random numbers in the same
order, same contributions — so the two renders agree bit for bit at every depth; at ``min_depth`` k it keeps what
``path`` at ``max_depth`` ≥ k adds over ``path`` at k − 1, so with one seed it equals that difference to float32
rounding (tolerance 1e-6 × the image's peak: measured 7e-7 absolute at a peak of 13.5).
"""

from pathlib import Path

import numpy as np
import pytest

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.assets import envmap

HDRI = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "hdri" / "courtyard.exr"


def _scene(integrator: dict) -> mi.Scene:
    """A diffuse sphere on a two-sided diffuse floor under an environment: light bounces between them."""
    diffuse = lambda rgb: {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}  # noqa: E731
    return mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 4], target=[0, 0.3, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "env": envmap(HDRI),
        "sphere": {"type": "sphere", "bsdf": diffuse([0.7, 0.5, 0.3]),
                   "to_world": mi.ScalarTransform4f().translate([0, 0.5, 0]).scale(0.5)},
        "floor": {"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": diffuse([0.6, 0.6, 0.6])},
                  "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3)},
    })


def _render(integrator: dict, spp: int = 8, seed: int = 3) -> np.ndarray:
    return np.array(mi.render(_scene(integrator), spp=spp, seed=seed))[..., :3]


@pytest.mark.parametrize("depth", [1, 2, 3, 4, 6, -1])
def test_min_depth_one_is_the_path_tracer_bit_for_bit(depth):
    ours = _render({"type": "indirect", "max_depth": depth, "min_depth": 1})
    ref = _render({"type": "path", "max_depth": depth})
    assert ref.max() > 1.0  # the environment is visible: not an empty comparison
    np.testing.assert_array_equal(ours, ref)


@pytest.mark.parametrize("lo,hi", [(3, 4), (3, 6), (2, 2), (4, 6)])
def test_min_depth_keeps_what_the_longer_paths_add(lo, hi):
    ours = _render({"type": "indirect", "max_depth": hi, "min_depth": lo})
    diff = _render({"type": "path", "max_depth": hi}) - _render({"type": "path", "max_depth": lo - 1})
    peak = float(_render({"type": "path", "max_depth": hi}).max())
    assert np.abs(diff).max() > 1e-3  # light does bounce between the sphere and the floor
    np.testing.assert_allclose(ours, diff, rtol=0, atol=1e-6 * peak)
    assert (ours >= 0).all()  # a sum of non-negative contributions, unlike the difference's rounding


def test_loads_from_xml_and_refuses_bad_depths():
    xml = '<integrator version="3.0.0" type="indirect"><integer name="max_depth" value="4"/></integrator>'
    integ = mi.load_string(xml)
    assert "min_depth=3" in str(integ) and "max_depth=4" in str(integ)
    with pytest.raises(Exception, match="min_depth"):
        mi.load_dict({"type": "indirect", "min_depth": 0})
    with pytest.raises(Exception, match="max_depth"):
        mi.load_dict({"type": "indirect", "max_depth": -2})
