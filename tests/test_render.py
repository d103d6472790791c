"""Tests of the preview renderer (``jaxcos.render._render``) and the ``jaxcos render`` command.

References:

* a zero-thickness stack over a white Lambertian base is a white Lambertian
  surface: under the directional light alone its radiance is ``cos(theta_i)``
  (irradiance ``pi`` times ``1 / pi``), computed here from the documented
  geometry (sphere radius 0.9 of the half panel, light from the upper left 40
  degrees off the viewing axis, patch lit at 75 degrees);
* :func:`jaxcos.simulate` at the grid nodes of a table, with the same key;
* synthetic tables whose multilinear interpolation is known exactly.

Budgets are small, and the isotropic renders share one table shape and one
image size, so each program is compiled once.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcos import InputError, Layer, Material
from jaxcos.cli import main
from jaxcos.render import BSDFTable, on_base, render, shade, tabulate
from jaxcos.render._render import _despeckle
from jaxcos.model._walk import Query, simulate

SIZE = 16
WALKS, BOUNCES = 256, 8  # shared by the isotropic renders (one compilation)

_LAYER = dict(t=1.0, c_d=0.9, albedo_d=(0.99, 0.98, 0.95), g1=0.55, g2=0.09, w_g=1.0,
              albedo_p=(0.75, 0.85, 0.99), alpha_p=0.13, theta_p=0.0)


def _material(**changes):
    return Material(layers=(Layer(**{**_LAYER, **changes}),))


def _sphere_cosine(size):
    """``max(n . light, 0)`` on the sphere panel, and its mask, from the documented geometry."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c / 0.9, -c / 0.9)
    inside = x * x + y * y < 1.0
    n = np.stack([x, y, np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))], axis=-1)
    s = math.sin(math.radians(40.0)) / math.sqrt(2.0)
    light = np.array([-s, s, math.cos(math.radians(40.0))])
    return np.maximum(n @ light, 0.0), inside


@pytest.fixture(scope="module")
def white_table():
    """A zero-thickness layer (with platelets and diffusers) over a white Lambertian base."""
    return tabulate(on_base(_material(t=0.0), (1.0, 1.0, 1.0)), jax.random.key(0), walks=WALKS, bounces=BOUNCES)


def test_zero_thickness_over_white_base_is_lambertian_shading(white_table):
    image = shade(white_table, size=SIZE, environment=0.0, light_radius_deg=0.0)
    assert image.shape == (SIZE, 2 * SIZE, 3)
    cosine, inside = _sphere_cosine(SIZE)
    sphere = image[:, :SIZE]
    np.testing.assert_allclose(sphere[inside], np.repeat(cosine[inside][:, None], 3, 1), rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(sphere[~inside], 0.0)  # the environment (0) behind the sphere
    patch = image[:, SIZE:]
    lit = patch[..., 1] > 0
    assert 0.1 < lit.mean() < 0.9  # the patch and the background both show
    np.testing.assert_allclose(patch[lit], math.cos(math.radians(75.0)), rtol=1e-4)
    np.testing.assert_array_equal(patch[~lit], 0.0)


def test_environment_adds_its_radiance_times_the_albedo(white_table):
    """A white Lambertian surface has albedo 1 from every direction: the environment adds its radiance.

    The albedo is the estimate's ``reflected`` energy; for this stack the walks
    choose the base with probability 1/2 and weight 2, so its standard error at
    256 walks is 1/16. The tolerance is 4 standard errors.
    """
    env = 0.1
    image = shade(white_table, size=SIZE, environment=env, light_radius_deg=0.0)
    cosine, inside = _sphere_cosine(SIZE)
    albedo = (image[:, :SIZE][inside] - cosine[inside][:, None]) / env
    np.testing.assert_allclose(albedo, 1.0, atol=4 / 16)
    np.testing.assert_allclose(albedo, np.broadcast_to(albedo[0], albedo.shape), rtol=1e-3)  # one offset (CRN)
    np.testing.assert_allclose(image[:, :SIZE][~inside], env)


def test_light_disc_changes_only_the_shading_near_the_terminator(white_table):
    point = shade(white_table, size=SIZE, environment=0.0, light_radius_deg=0.0)
    disc = shade(white_table, size=SIZE, environment=0.0, light_radius_deg=3.0)
    # averaging cos over a 3-degree disc changes a lit Lambertian pixel by at most 1 - cos(3 deg) relative,
    # plus the slope of cos over 3 degrees near the terminator
    np.testing.assert_allclose(disc, point, atol=math.radians(3.0) * 1.01)
    assert not np.array_equal(disc, point)


def test_render_shape_range_and_key():
    material = _material()  # untilted platelets: isotropic, the same table shape as white_table
    a = render(material, key=jax.random.key(1), size=SIZE, walks=WALKS, bounces=BOUNCES)
    assert a.shape == (SIZE, 2 * SIZE, 3)
    assert np.all(np.isfinite(a)) and a.min() >= 0.0 and a.max() <= 1.0
    assert a.max() > 0.5 and a.std() > 0.01  # not a blank picture
    b = render(material, key=jax.random.key(1), size=SIZE, walks=WALKS, bounces=BOUNCES)
    np.testing.assert_array_equal(a, b)
    c = render(material, key=jax.random.key(2), size=SIZE, walks=WALKS, bounces=BOUNCES)
    assert not np.array_equal(a, c)
    # the skin shows through a thin layer: a redder base gives a redder picture
    red = render(material, key=jax.random.key(1), size=SIZE, walks=WALKS, bounces=BOUNCES,
                 base_albedo=(0.9, 0.1, 0.1))
    assert red[..., 0].mean() - red[..., 2].mean() > a[..., 0].mean() - a[..., 2].mean() + 0.02


def test_linear_output_is_encoded_output_before_the_transfer_curve():
    import colour

    material = _material()
    kwargs = dict(key=jax.random.key(1), size=SIZE, walks=WALKS, bounces=BOUNCES)
    linear = render(material, encode=False, **kwargs)
    encoded = render(material, exposure=0.5, **kwargs)
    expected = colour.cctf_encoding(np.clip(0.5 * linear, 0.0, 1.0), function="sRGB")
    np.testing.assert_allclose(encoded, expected, atol=1e-5)


def _direction(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], np.float32)


def test_table_equals_simulate_at_grid_nodes():
    """At grid nodes the table is the estimator itself: same key, same walks, any azimuth of ``wi``.

    The material is tilted (anisotropic) and rough enough that the path
    regularisation changes nothing; ``wi`` is given out of the plane, which
    checks the table's azimuth conventions against :func:`simulate` on an
    arbitrary :class:`Query`.
    """
    material = on_base(_material(theta_p=30.0, phi_p=40.0, alpha_p=0.3, c_d=0.5, t=2.0))
    key = jax.random.key(3)
    table = tabulate(material, key, walks=32, bounces=8, n_theta=4, n_phi=8, n_phi_i=4)
    assert table.multiple.shape == (4, 4, 4, 8, 3)
    np.testing.assert_allclose(table.theta_deg, [0, 29, 58, 87])
    np.testing.assert_allclose(table.phi_i_deg, [180, 270, 360, 450])
    pairs = [((29, 270), (58, 45)), ((58, 0), (29, 180)), ((87, 180), (58, 315)), ((0, 0), (29, 90)),
             ((29, 90), (87, 225))]
    wi = np.stack([_direction(*p[0]) for p in pairs])
    wo = np.stack([_direction(*p[1]) for p in pairs])
    got = table.f(jnp.asarray(wi), jnp.asarray(wo))
    for k, pair in enumerate(pairs):  # one incidence per call: the same key gives the table's walks
        query = Query(jnp.asarray(wi[k:k + 1]), jnp.asarray(wo[None, k:k + 1]), jnp.zeros(1, jnp.int32),
                      jnp.zeros(1, jnp.int32))
        expected = simulate(material, query, key, walks=32, bounces=8).f[0]
        np.testing.assert_allclose(got[k], expected, rtol=2e-4, atol=1e-6, err_msg=f"(wi, wo) = {pair}")


def _synthetic(multiple, albedo=None, theta_max=90.0):
    n_t, n_a = multiple.shape[:2]
    if albedo is None:
        albedo = jnp.zeros((n_t, n_a, 3))
    return BSDFTable(material=on_base(_material()), multiple=jnp.asarray(multiple, jnp.float32),
                     albedo=jnp.asarray(albedo, jnp.float32), theta_max_deg=theta_max)


def test_interpolation_is_exact_for_a_multilinear_table():
    theta = np.linspace(0, 90, 4)
    # f = 1 + 2 theta_i / 90 + 3 theta_o / 90, constant in the azimuths
    values = 1.0 + 2.0 * theta[:, None, None, None] / 90 + 3.0 * theta[None, None, :, None] / 90
    table = _synthetic(np.broadcast_to(values[..., None], (4, 2, 4, 6, 3)))
    rng = np.random.default_rng(0)
    ti, to = rng.uniform(0, 89, 20), rng.uniform(0, 89, 20)
    pi, po = rng.uniform(-180, 360, 20), rng.uniform(-180, 360, 20)
    wi = np.stack([_direction(a, b) for a, b in zip(ti, pi)])
    wo = np.stack([_direction(a, b) for a, b in zip(to, po)])
    got = table.f_multiple(jnp.asarray(wi), jnp.asarray(wo))
    np.testing.assert_allclose(got[:, 1], 1.0 + 2.0 * ti / 90 + 3.0 * to / 90, rtol=1e-4)
    # beyond the last node values are held
    short = _synthetic(np.broadcast_to(values[..., None], (4, 2, 4, 6, 3)), theta_max=60.0)
    held = short.f_multiple(jnp.asarray(_direction(20.0, 0.0)), jnp.asarray(_direction(80.0, 0.0)))
    np.testing.assert_allclose(held[0], 1.0 + 2.0 * 20 / 60 + 3.0 * 90 / 90, rtol=1e-4)


def test_interpolation_wraps_around_in_azimuth():
    n_phi = 8  # nodes every 45 degrees of phi_o
    values = np.zeros((2, 1, 2, n_phi, 3))
    values[..., 0, :] = 1.0  # phi_o = 0
    values[..., n_phi - 1, :] = 3.0  # phi_o = 315
    table = _synthetic(values)
    wi = jnp.asarray(_direction(30.0, 180.0))  # isotropic table: wi at azimuth 180 reads phi_o as is
    for phi, expected in [(0.0, 1.0), (315.0, 3.0), (337.5, 2.0), (-22.5, 2.0), (22.5, 0.5), (360.0, 1.0)]:
        got = table.f_multiple(wi, jnp.asarray(_direction(45.0, phi)))
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6, err_msg=f"phi_o {phi}")
    # isotropic: only the difference of the azimuths counts
    turned = table.f_multiple(jnp.asarray(_direction(30.0, 180.0 + 70.0)), jnp.asarray(_direction(45.0, 337.5 + 70.0)))
    np.testing.assert_allclose(turned, 2.0, rtol=1e-5)


def test_directional_albedo_reads_the_albedo_table():
    albedo = np.zeros((3, 4, 3))
    albedo[:, :, 0] = np.arange(4)[None, :]  # azimuth nodes 180, 270, 0, 90
    albedo[:, :, 1] = np.arange(3)[:, None]  # theta nodes 0, 45, 90
    table = _synthetic(np.zeros((3, 4, 3, 4, 3)), albedo)
    got = table.directional_albedo(jnp.asarray(np.stack([_direction(45.0, 270.0), _direction(67.5, 45.0)])))
    np.testing.assert_allclose(got[0, :2], [1.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(got[1, :2], [2.5, 1.5], atol=1e-5)  # halfway between 0 and 90 degrees of azimuth


def test_despeckle_clamps_an_isolated_spike_and_keeps_smooth_values():
    theta = np.linspace(0.0, 1.0, 5)[:, None, None]
    phi = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)[None, :, None]
    smooth = (1.0 + 0.5 * theta + 0.2 * np.cos(phi)) * np.array([1.0, 0.8, 0.6])  # (5, 8, 3)
    np.testing.assert_allclose(_despeckle(jnp.asarray(smooth), 2.0), smooth, rtol=1e-6)
    spiky = smooth.copy()
    spiky[2, 0] *= 10.0  # at phi = 0: its neighbours wrap around to phi = 315 degrees
    spiky[4, 5] *= 10.0  # on the last theta row
    out = np.asarray(_despeckle(jnp.asarray(spiky), 2.0))
    np.testing.assert_allclose(out[2, 0] / smooth[2, 0], out[2, 0, 0] / smooth[2, 0, 0])  # colour kept
    assert 1.5 < out[2, 0, 0] / smooth[2, 0, 0] < 2.3 and 1.5 < out[4, 5, 0] / smooth[4, 5, 0] < 2.3
    keep = np.ones((5, 8), bool)
    keep[2, 0] = keep[4, 5] = False
    np.testing.assert_allclose(out[keep], smooth[keep], rtol=1e-6)


@pytest.mark.parametrize("bad", [(1.0, 2.0), (0.5, 0.5, 1.5), (0.5, float("nan"), 0.5), "skin"])
def test_bad_base_albedo_is_an_input_error(bad):
    with pytest.raises(InputError, match="base_albedo must be three numbers"):
        render(_material(), key=jax.random.key(0), base_albedo=bad)


@pytest.mark.parametrize("size", [0, 3, 2.5, True])
def test_bad_size_is_an_input_error(size):
    with pytest.raises(InputError, match="size must be a whole number"):
        render(_material(), key=jax.random.key(0), size=size)


# --- the command ---------------------------------------------------------------------------


@pytest.fixture()
def params(tmp_path):
    path = tmp_path / "params.json"
    layer = {"t": 1.0, "c_d": 0.9, "albedo_d": [0.99, 0.98, 0.95], "g1": 0.55, "g2": 0.09, "w_g": 1.0,
             "albedo_p": [0.75, 0.85, 0.99], "alpha_p": 0.13, "theta_p_deg": 0.0}
    path.write_text(json.dumps({"layers": [layer], "base": {"type": "black"}}))
    return path


def _run(argv, capsys):
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def test_command_writes_a_png_and_refuses_to_overwrite(params, tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "preview.png"
    small = ["--size", SIZE, "--walks", WALKS, "--bounces", BOUNCES]
    status, stdout, _ = _run(["render", params, "--out", out, *small], capsys)
    assert status == 0 and "wrote" in stdout
    with Image.open(out) as im:
        assert im.size == (2 * SIZE, SIZE) and im.mode == "RGB"
        first = np.asarray(im)
    before = out.read_bytes()
    status, _, err = _run(["render", params, "--out", out, *small, "--seed", 5], capsys)
    assert status == 2 and "already exists" in err and "--force" in err
    assert out.read_bytes() == before
    status, _, _ = _run(["render", params, "--out", out, *small, "--seed", 5, "--force"], capsys)
    assert status == 0
    with Image.open(out) as im:
        assert not np.array_equal(np.asarray(im), first)


@pytest.mark.parametrize("extra, message", [
    (["--base-albedo", "0.5,0.5"], "--base-albedo must be three numbers"),
    (["--base-albedo", "a,b,c"], "--base-albedo must be three numbers"),
    (["--base-albedo", "0.5,0.5,2"], "--base-albedo must be three numbers"),
    (["--size", "0"], "--size must be"),
    (["--thickness", "-1"], "--thickness must be"),
    (["--exposure", "0"], "--exposure must be"),
])
def test_command_bad_options(params, tmp_path, capsys, extra, message):
    out = tmp_path / "x.png"
    status, _, err = _run(["render", params, "--out", out, *extra], capsys)
    assert status == 2
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_command_bad_files(params, tmp_path, capsys):
    status, _, err = _run(["render", tmp_path / "missing.json", "--out", tmp_path / "x.png"], capsys)
    assert status == 2 and "missing.json: no such file" in err and len(err.strip().splitlines()) == 1
    status, _, err = _run(["render", params, "--out", tmp_path / "x.jpg"], capsys)
    assert status == 2 and "must be a .png" in err
    status, _, err = _run(["render", params, "--out", tmp_path / "no" / "x.png"], capsys)
    assert status == 2 and "does not exist" in err
    assert list(tmp_path.iterdir()) == [params]
