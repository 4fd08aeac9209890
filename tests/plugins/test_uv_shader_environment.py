"""Environment light in the UV-space shader: real SH against quadrature, the glossy lobe's directional albedo
against brute-force integration, and a texel against a Mitsuba render of the same surface under the same
(band-limited) environment map; the per-texel transfer on a sphere against its closed form."""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mi_plugins import sh
from mi_plugins import shading
from mi_plugins.uv_shader import UVEnvironment, UVMaps, UVView, shade_uv

TILTED_RGB = (np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93]) * 0.5 + 0.5).tolist()


def test_sh_basis_is_orthonormal_and_the_cosine_lobe_is_ramamoorthi_hanrahan():
    d, dw = sh.envmap_directions(256, 512)
    y = np.stack(sh.basis(d[..., 0], d[..., 1], d[..., 2], 4), -1)
    gram = np.einsum("hwi,hwj,hw->ij", y, y, dw)
    np.testing.assert_allclose(gram, np.eye(25), atol=1e-4)  # quadrature of a smooth integrand
    n = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    proj = np.einsum("hwj,hw,hw->j", y, np.clip(d @ n, 0, None), dw)
    yn = np.array(sh.basis(*n, 4))
    expect = np.array([sh.cosine_lobe(sh.band(j)) for j in range(25)]) * yn
    np.testing.assert_allclose(proj, expect, atol=2e-3)  # the clamp's kink limits the quadrature
    assert sh.cosine_lobe(2) == pytest.approx(np.pi / 4) and sh.cosine_lobe(4) == pytest.approx(-np.pi / 24)


def test_envmap_round_trip():
    rng = np.random.default_rng(0)
    c = rng.normal(size=(9, 3))
    np.testing.assert_allclose(sh.project_envmap(sh.envmap_from_coeffs(c, 128, 256), 2), c, atol=2e-3)


@pytest.mark.parametrize("rough,cos_i", [(0.2, 0.9), (0.5, 0.5), (0.8, 0.2)])
def test_directional_albedo_table_matches_brute_force_integration(rough, cos_i):
    """∫ f_s cosθo dωo by a fine midpoint rule over the hemisphere with the same brdf_lobes."""
    n_t, n_p = 400, 800
    th = (np.arange(n_t) + 0.5) / n_t * np.pi / 2
    ph = (np.arange(n_p) + 0.5) / n_p * 2 * np.pi
    t, p = [a.ravel() for a in np.meshgrid(th, ph, indexing="ij")]
    wo = mi.Vector3f(*(np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]).astype(np.float32)))
    wi = mi.Vector3f(float(np.sqrt(1 - cos_i ** 2)), 0.0, float(cos_i))
    spec = 0.9  # F0 = 0.072
    _, fs = shading.brdf_lobes(mi.Color3f(0.0), mi.Float(rough), mi.Float(spec), mi.Float(0.0), wi, wo)
    brute = float(np.sum(np.array(fs)[0] * np.sin(t)) * (np.pi / 2 / n_t) * (2 * np.pi / n_p))
    f0 = shading.f0_from_maps(mi.Color3f(0.0), mi.Float(spec), mi.Float(0.0))
    table = np.array(shading.directional_albedo(f0, shading.f90_from_f0(f0), mi.Float(rough), mi.Float(cos_i)))[0, 0]
    # 1024 VNDF samples per cell and bilinear interpolation: 3 %; the sharpest lobe limits the midpoint rule
    assert table == pytest.approx(brute, rel=0.03), (table, brute)


def _patch_render(c, albedo, rough, spec, normal_map, to_cam, spp=2048):
    env = sh.envmap_from_coeffs(c, 128, 256)
    assert env.min() > 0  # Mitsuba samples the map by its luminance: keep it positive
    bsdf = {"type": "ggx_uv", "albedo": {"type": "rgb", "value": albedo}, "roughness": rough, "specular": spec}
    if normal_map:
        bsdf["normal"] = {"type": "rgb", "value": TILTED_RGB}
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=(to_cam * 5).tolist(), target=[0, 0, 0],
                                                              up=[0, 1, 0]) @ mi.ScalarTransform4f().scale([0.2, 0.2, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "patch": {"type": "rectangle", "bsdf": bsdf, "to_world": mi.ScalarTransform4f().scale(3)},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)}})
    return np.array(mi.render(scene, spp=spp, seed=1))[..., :3].reshape(-1, 3).mean(0)


@pytest.mark.parametrize("rough,spec,normal_map,rtol", [
    (0.5, 0.0, False, 0.015),  # diffuse, unperturbed: exact for band-limited light (noise and the map's pixels)
    (0.5, 0.0, True, 0.015),   # a 21° mapped normal: its lobe cut by the geometric horizon, h = (1 + n'·n)/2
    (0.3, 0.9, False, 0.015),  # with gloss: the zonal GGX lobe and the split sum
    (0.8, 0.9, True, 0.035),   # wide gloss about a tilted normal: the horizon cuts the lobe too (not modelled)
])
def test_environment_texel_equals_mitsuba_render(rough, spec, normal_map, rtol):
    rng = np.random.default_rng(1)
    c = rng.normal(size=(9, 3)) * 0.25
    c[0] = [1.6, 1.4, 1.2]
    to_cam = np.array([-0.5, 0.2, 0.84]) / np.linalg.norm([-0.5, 0.2, 0.84])
    albedo = [0.6, 0.4, 0.3]
    rendered = _patch_render(c, albedo, rough, spec, normal_map, to_cam)
    h = w = 2
    pos = mi.TensorXf(np.zeros((h, w, 3), np.float32))
    nrm = mi.TensorXf(np.tile(np.float32([0, 0, 1]), (h, w, 1)))
    tan = mi.TensorXf(np.tile(np.float32([1, 0, 0]), (h, w, 1)))
    maps = UVMaps(albedo=albedo, roughness=rough, specular=spec, normal=TILTED_RGB if normal_map else None)
    texel = np.array(shade_uv(pos, nrm, tan, maps, [], UVView(direction=tuple(to_cam)),
                              environment=UVEnvironment(c)))[0, 0]
    np.testing.assert_allclose(texel, rendered, rtol=rtol)


def test_environment_gradients_reach_the_coefficients_and_the_albedo():
    pos = mi.TensorXf(np.zeros((1, 1, 3), np.float32))
    nrm = mi.TensorXf(np.float32([[[0, 0, 1]]]))
    tan = mi.TensorXf(np.float32([[[1, 0, 0]]]))
    c0 = np.random.default_rng(2).normal(size=(9, 3)).astype(np.float32)
    coeffs = mi.Color3f(c0.T)
    albedo = mi.TensorXf(np.float32([[[0.5, 0.4, 0.3]]]))
    dr.enable_grad(coeffs, albedo)
    out = shade_uv(pos, nrm, tan, UVMaps(albedo=albedo, specular=0.0), [], UVView(direction=(0.2, 0.1, 0.97)),
                   environment=UVEnvironment(coeffs))
    dr.backward(dr.sum(out, axis=None))
    g = np.array(dr.grad(coeffs))  # (3, 9): ∂/∂L_j = ρ/π Â_l Y_j(n), closed form for a specular-free texel
    y = np.array(sh.basis(0.0, 0.0, 1.0, 2))
    expect = np.array([0.5, 0.4, 0.3])[:, None] / np.pi * np.array([sh.cosine_lobe(sh.band(j)) for j in range(9)]) * y
    np.testing.assert_allclose(g, expect, rtol=1e-4, atol=1e-7)
    assert np.abs(np.array(dr.grad(albedo))).sum() > 0


def _uv_sphere(path, n_lat=24, n_lon=48):
    """A unit UV sphere OBJ (outward winding, latitude–longitude texture coordinates)."""
    lines = []
    for i in range(n_lat + 1):
        for j in range(n_lon + 1):
            t, p = np.pi * i / n_lat, 2 * np.pi * j / n_lon
            lines.append(f"v {np.sin(t) * np.cos(p):.6f} {np.cos(t):.6f} {np.sin(t) * np.sin(p):.6f}")
            lines.append(f"vt {j / n_lon:.6f} {1 - i / n_lat:.6f}")
    idx = lambda i, j: i * (n_lon + 1) + j + 1  # noqa: E731
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            lines.append(f"f {a}/{a} {d}/{d} {c}/{c} {b}/{b}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_transfer_of_a_convex_sphere_is_the_unoccluded_cosine(tmp_path):
    from foundation.mesh import load_obj
    from inverse.face.benchmark import environment_transfer
    from inverse.face.uv_bake import bake_geometry

    mesh = load_obj(_uv_sphere(tmp_path / "sphere.obj"))
    geo = bake_geometry(mesh, 32)
    t = environment_transfer(tmp_path / "sphere.obj", geo, 2, rays=400, seed=0)
    m = geo.mask.copy()
    m[[0, -1]] = False  # the poles' texel rows: degenerate triangles, no single normal
    n = geo.normal[m]
    if np.mean(np.sum(n * geo.position[m], 1)) < 0:
        pytest.fail("the test sphere is wound inside out")
    y = np.stack(sh.basis(n[:, 0], n[:, 1], n[:, 2], 2), 1)
    expect = y * np.array([sh.cosine_lobe(sh.band(j)) for j in range(9)])
    # nothing occludes a convex sphere; 400 stratified cosine-weighted rays per texel (Â_0 Y_0 = 0.886)
    err = np.abs(t[m] - expect)
    assert err.max() < 0.12 and err.mean() < 0.03, (err.max(), err.mean())
    # the visible fraction a = T_00 / (π Y_00) is 1 to within the faceted sphere's own grazing hits
    assert np.median(t[m][:, 0] / (np.pi * sh.basis(0.0, 0.0, 1.0, 0)[0])) > 0.99


def test_directional_albedo_of_a_nan_cosine_reads_inside_its_table():
    """A texel no view sees can carry a NaN view cosine into the split-sum lookup: it reads the table's first column
    (cos θ = 0), never an index made from NaN (out of bounds: a segfault of the LLVM backend on AVX2 machines)."""
    from mi_plugins import shading as sh

    f0, f90 = mi.Color3f(0.04), mi.Float(1.0)
    rough = mi.Float([0.3, 0.3, float("nan")])
    cos_i = mi.Float([float("nan"), 0.0, 0.5])
    got = np.array(sh.directional_albedo(f0, f90, rough, cos_i))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got[:, 0], got[:, 1], rtol=1e-6)  # NaN cosine: as cos θ = 0
    want = np.array(sh.directional_albedo(f0, f90, mi.Float(0.0), mi.Float(0.5)))
    np.testing.assert_allclose(got[:, 2], want[:, 0], rtol=1e-6)  # NaN roughness: as roughness 0
