"""UV-space shader: agreement with a Mitsuba render of the same surface (oracle d),
closed-form ambient term, and finite-difference gradients (oracle e)."""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mi_plugins.uv_shader import UVLight, UVMaps, UVView, shade_uv

TILTED_RGB = (np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93]) * 0.5 + 0.5).tolist()


def _const_map(h, w, value):
    return mi.TensorXf(np.tile(np.float32(value), (h, w, 1)))


def _flat_patch_geometry(h=4, w=4):
    """Geometry maps of Mitsuba's rectangle: z = 0 plane, normal +z, dp/du along +x."""
    pos = np.zeros((h, w, 3), np.float32)
    return mi.TensorXf(pos), _const_map(h, w, [0, 0, 1]), _const_map(h, w, [1, 0, 0])


@pytest.mark.parametrize("roughness,normal_map", [(0.3, False), (0.3, True), (0.8, True)])
def test_texel_equals_mitsuba_render_of_flat_patch(roughness, normal_map):
    to_light = np.array([0.4, 0.3, 0.87]); to_light /= np.linalg.norm(to_light)
    to_cam = np.array([-0.5, 0.2, 0.84]); to_cam /= np.linalg.norm(to_cam)
    irradiance = [2.0, 1.5, 1.0]
    albedo, specular = [0.6, 0.4, 0.3], 0.9

    bsdf = {"type": "ggx_uv", "albedo": {"type": "rgb", "value": albedo},
            "roughness": roughness, "specular": specular}
    if normal_map:
        bsdf["normal"] = {"type": "rgb", "value": TILTED_RGB}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=(to_cam * 5).tolist(),
                                                              target=[0, 0, 0], up=[0, 1, 0])
                   @ mi.ScalarTransform4f().scale([0.2, 0.2, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "patch": {"type": "rectangle", "bsdf": bsdf, "to_world": mi.ScalarTransform4f().scale(3)},
        "sun": {"type": "directional", "direction": (-to_light).tolist(),
                "irradiance": {"type": "rgb", "value": irradiance}},
    })
    img = np.array(mi.render(scene))
    rendered = img[4, 4, :3]
    # The patch has constant maps, so every pixel sees the same BSDF value: the image is flat.
    assert np.ptp(img[..., :3], axis=(0, 1)).max() < 1e-5

    pos, nrm, tan = _flat_patch_geometry()
    maps = UVMaps(albedo=albedo, roughness=roughness, specular=specular,
                  normal=TILTED_RGB if normal_map else None)
    shaded = shade_uv(pos, nrm, tan, maps, [UVLight("directional", tuple(to_light), tuple(irradiance))],
                      UVView(direction=tuple(to_cam)))
    texel = np.array(shaded)[1, 2]
    # Same float32 maths on both sides; 1e-3 absolute is the bound (values are ~0.1–1).
    np.testing.assert_allclose(texel, rendered, atol=1e-3)
    assert rendered.max() > 0.05  # the comparison is not between two zeros


def test_ambient_term_and_mask_are_the_closed_form():
    h, w = 3, 5
    pos, nrm, tan = _flat_patch_geometry(h, w)
    rng = np.random.default_rng(0)
    albedo = rng.random((h, w, 3)).astype(np.float32)
    mask = (rng.random((h, w)) > 0.5).astype(np.float32)
    out = shade_uv(pos, nrm, tan, UVMaps(albedo=mi.TensorXf(albedo)), [], UVView(direction=(0, 0, 1)),
                   ambient=0.2, mask=mi.TensorXf(mask))
    np.testing.assert_allclose(np.array(out), 0.2 * albedo * mask[..., None], rtol=1e-6)


def test_point_light_inverse_square_falloff():
    pos, nrm, tan = _flat_patch_geometry(1, 1)
    maps = UVMaps(albedo=[1, 1, 1], specular=0.0)
    near = shade_uv(pos, nrm, tan, maps, [UVLight("point", (0, 0, 1), (1, 1, 1))], UVView(direction=(0, 0, 1)))
    far = shade_uv(pos, nrm, tan, maps, [UVLight("point", (0, 0, 2), (1, 1, 1))], UVView(direction=(0, 0, 1)))
    # Lambert, light straight above: L = I/r² · 1/π.
    np.testing.assert_allclose(np.array(near)[0, 0], 1 / np.pi, rtol=1e-5)
    np.testing.assert_allclose(np.array(far)[0, 0], 1 / (4 * np.pi), rtol=1e-5)


def _fd_check(loss_fn, tensor: mi.TensorXf, indices, h=1e-2, rtol=2e-2):
    """Central finite differences of a scalar loss w.r.t. chosen entries of a tensor.

    Tolerance: 2% of the entry plus 2% of the largest gradient entry. The loss is
    float32, so an FD quotient with h = 1e-2 carries ~1e-5/h absolute noise and
    an O(h²) truncation error; 2% covers both with margin and still catches a
    wrong factor or sign.
    """
    t = mi.TensorXf(tensor)
    dr.enable_grad(t)
    loss = loss_fn(t)
    dr.backward(loss)
    grad = np.array(dr.grad(t)).ravel()
    base = np.array(tensor).ravel()
    atol = rtol * np.abs(grad).max()
    for i in indices:
        plus, minus = base.copy(), base.copy()
        plus[i] += h
        minus[i] -= h
        f_p = float(loss_fn(mi.TensorXf(plus.reshape(tensor.shape))).array[0])
        f_m = float(loss_fn(mi.TensorXf(minus.reshape(tensor.shape))).array[0])
        fd = (f_p - f_m) / (2 * h)
        assert abs(fd - grad[i]) <= atol + rtol * abs(fd), (i, fd, grad[i])
    return grad


@pytest.mark.parametrize("which", ["albedo", "roughness", "normal"])
def test_uv_shader_gradients_match_central_differences(which):
    hgt, wid = 2, 3
    rng = np.random.default_rng(1)
    pos = mi.TensorXf(rng.normal(scale=0.1, size=(hgt, wid, 3)).astype(np.float32))
    nrm = mi.TensorXf(np.tile(np.float32([0.1, 0.0, 1.0]), (hgt, wid, 1)))
    tan = mi.TensorXf(np.tile(np.float32([1.0, 0.0, 0.0]), (hgt, wid, 1)))
    base = {
        "albedo": mi.TensorXf(rng.uniform(0.2, 0.8, (hgt, wid, 3)).astype(np.float32)),
        "roughness": mi.TensorXf(rng.uniform(0.3, 0.7, (hgt, wid, 1)).astype(np.float32)),
        "normal": mi.TensorXf(np.float32(np.array(TILTED_RGB)[None, None, :]
                                         + rng.uniform(-0.05, 0.05, (hgt, wid, 3)))),
    }
    lights = [UVLight("directional", (0.3, 0.2, 0.9), (1.5, 1.5, 1.5)), UVLight("point", (-1, 0.5, 2), (3, 3, 3))]
    view = UVView(position=(0.2, -0.3, 3.0))
    weights = mi.TensorXf(rng.uniform(0.5, 1.5, (hgt, wid, 3)).astype(np.float32))

    def loss(t):
        maps = dict(base)
        maps[which] = t
        out = shade_uv(pos, nrm, tan, UVMaps(specular=0.8, **maps), lights, view, ambient=0.1)
        return dr.sum(out * weights, axis=None)

    grad = _fd_check(loss, base[which], indices=range(0, dr.width(base[which].array), 2))
    assert np.abs(grad).max() > 1e-3  # the gradient is not trivially zero


def _steep_dirs(n, seed):
    from conftest import random_dirs

    v = np.array(random_dirs(n, seed))
    v[2] = np.maximum(v[2], 1.2)
    v /= np.linalg.norm(v, axis=0)
    return mi.Vector3f(v.astype(np.float32))


@pytest.mark.parametrize("which", ["albedo", "roughness", "normal"])
def test_bsdf_eval_gradients_match_central_differences(which, ctx):
    """Same check through the ggx_uv plugin's eval (textures as 1×1 bitmaps)."""
    from conftest import local_si

    values = {"albedo": [0.6, 0.4, 0.3], "roughness": [0.45], "normal": TILTED_RGB}
    bsdf = mi.load_dict({"type": "ggx_uv", "specular": 0.8, **{
        k: {"type": "bitmap", "raw": True, "filter_type": "nearest",
            "data": mi.TensorXf(np.tile(np.float32(v).reshape(1, 1, -1), (2, 2, 1)))} for k, v in values.items()}})
    params = mi.traverse(bsdf)
    key = f"{which}.data"
    base = mi.TensorXf(params[key])
    n = 2000
    # Directions well above both horizons: FD would otherwise straddle the
    # (correctly non-differentiated) horizon cut-offs of the normal-mapped lobe.
    si = local_si(_steep_dirs(n, 21))
    wo = _steep_dirs(n, 22)
    w = mi.Float(np.random.default_rng(23).uniform(0.5, 1.5, n).astype(np.float32))

    def loss(t):
        params[key] = t
        params.update()
        return dr.sum(dr.sum(bsdf.eval(ctx, si, wo), axis=0) * w, axis=None)

    grad = _fd_check(loss, base, indices=range(dr.width(base.array)), h=5e-3)
    assert np.abs(grad).max() > 1e-3


def test_gradients_accumulate_over_lights():
    """One shade_uv call per light on the same maps: the gradients must add up.

    Regression test for Dr.Jit 1.5's ``dr.unravel``, whose backward pass
    overwrites instead of accumulating (only the last call's gradient survived).
    Oracle: Lambert is linear in albedo, so d/dalbedo Σ_k T_k = Σ_k E_k cosθ_k / π.
    """
    pos, nrm, tan = _flat_patch_geometry(2, 2)
    albedo = mi.TensorXf(np.full((2, 2, 3), 0.5, np.float32))
    dr.enable_grad(albedo)
    dirs = [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.0, 0.8, 0.6)]
    total = 0
    for d in dirs:
        total += dr.sum(shade_uv(pos, nrm, tan, UVMaps(albedo=albedo, specular=0.0),
                                 [UVLight("directional", d, (1, 1, 1))], UVView(direction=(0, 0, 1))), axis=None)
    dr.backward(total)
    expected = sum(d[2] for d in dirs) / np.pi
    np.testing.assert_allclose(np.array(dr.grad(albedo)), expected, rtol=1e-5)
