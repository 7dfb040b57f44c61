"""Tests for statmc.denoisers: the protocol, each adapter, OIDN determinism, lazy imports."""

import subprocess
import sys
import warnings

import numpy as np
import pytest

from _memory import assert_central_part, traced_peak
from statmc import denoisers as D
from statmc.analytic import apply_kernels
from statmc.errors import InputError
from statmc.toy import ToyRenderer


@pytest.fixture(scope="module")
def toy():
    r = ToyRenderer("mixed", width=32, height=32)
    st = r.render_uniform(16, seed=7)
    return r, st


# ----------------------------------------------------------------------------- imports
def test_import_statmc_does_not_import_torch_or_pyoidn():
    code = ("import sys, statmc, statmc.sure, statmc.denoisers; "
            "d = statmc.denoisers.oidn(); g = statmc.denoisers.gaussian(1.0); "
            "bad = [m for m in ('torch', 'pyoidn') if m in sys.modules]; "
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"imported at module level: {out.stdout.strip()}"


# ----------------------------------------------------------------------------- protocol
@pytest.mark.parametrize("name,bound", [("identity", {}), ("none", {}), ("gaussian", {"sigma": 1.5}),
                                        ("gem", "mean_var"), ("oidn", "features")])
def test_every_adapter_follows_the_protocol(toy, name, bound):
    r, st = toy
    if bound == "mean_var":
        bound = {"mean_var": st.mean_var}
    elif bound == "features":
        bound = {"albedo": st.albedo, "normal": st.normal}
    f = D.get(name, **bound)
    assert isinstance(f, D.Denoiser)
    x = st.mean.astype(np.float32)
    y = np.asarray(f(x))
    assert y.shape == x.shape and np.isfinite(y).all()
    assert np.array_equal(x, st.mean.astype(np.float32)), "input modified"


def test_denoisers_reduce_the_error_of_a_noisy_render(toy):
    r, st = toy
    mu = r.true_mean()
    x = st.mean.astype(np.float32)
    base = np.mean((x - mu) ** 2)
    for f in (D.gaussian(1.0), D.gem(st.mean_var), D.oidn(st.albedo, st.normal)):
        assert np.mean((f(x) - mu) ** 2) < 0.7 * base, repr(f)


# ----------------------------------------------------------------------------- identity / gaussian
def test_identity_returns_a_copy_and_unit_kernels():
    x = np.arange(24, dtype=np.float32).reshape(2, 4, 3)
    f = D.identity()
    y = f(x)
    assert np.array_equal(y, x) and y is not x
    assert np.array_equal(apply_kernels(f.kernels(x.shape), x), x)


@pytest.mark.parametrize("sigma,shape", [(0.7, (9, 11, 3)), (2.0, (7, 5, 3)), (1.0, (30, 20, 1))])
def test_gaussian_kernels_reproduce_the_filter_including_borders(sigma, shape):
    rng = np.random.default_rng(3)
    x = rng.random(shape)
    f = D.gaussian(sigma)
    K = f.kernels(shape)
    assert K.shape[:2] == shape[:2] and K.shape[2] == K.shape[3]
    np.testing.assert_allclose(apply_kernels(K, x), f(x), rtol=0, atol=1e-12)
    # border renormalisation: every pixel's in-image weights sum to one
    np.testing.assert_allclose(K.sum(axis=(2, 3)), 1.0, atol=1e-12)


def test_gaussian_kernels_are_zero_outside_the_image():
    K = D.gaussian(1.5).kernels((6, 6))
    r = K.shape[2] // 2
    assert np.all(K[0, 0, :r, :] == 0) and np.all(K[0, 0, :, :r] == 0)
    assert np.all(K[-1, -1, r + 1:, :] == 0)


def test_gaussian_with_absurd_sigma_stays_small():
    """GaussianDenoiser built the whole kernel at construction: σ = 1e6 took 137 MiB (and
    1e300 was refused as 'a kernel array', though the filter it calls takes it), and
    .kernels(shape) asked for an (H, W, 6e6, 6e6) array (MemoryError, 65.5 PiB).  The taps
    are now built for the image in .kernels, cut to the 2(max(H, W) − 1) + 1 that reach
    it: a few MiB whatever σ, and the kernels still reproduce the filter."""
    x = np.random.default_rng(4).random((16, 12, 3))
    D.gaussian(1.0).kernels(x.shape)                  # compile outside the measurement
    D.gaussian(1.0)(x)
    for sigma in (1e6, 1e8, 1e300):
        def build_and_apply(sigma):
            f = D.gaussian(sigma)
            return f, f.kernels(x.shape), f(x)
        (f, K, y), peak = traced_peak(build_and_apply, sigma)
        assert peak < 4 << 20, (sigma, peak)
        assert K.shape == (16, 12, 31, 31)
        np.testing.assert_allclose(apply_kernels(K, x), y, rtol=1e-12, atol=0)
        np.testing.assert_allclose(K.sum(axis=(2, 3)), 1.0, atol=1e-12)
    for bad, name in ((np.nan, "sigma"), (-1.0, "sigma"), ("2", "sigma")):
        with pytest.raises(InputError, match=f"`{name}` must be a finite number >= 0"):
            D.gaussian(bad)
    with pytest.raises(InputError, match="`truncate` must be a finite number > 0"):
        D.gaussian(1.0, truncate=0.0)


def test_gaussian_kernels_cut_to_the_image_equal_the_whole_ones(monkeypatch):
    """With the cut lowered to 2 taps, σ = 4 on 7×9 pixels keeps the 8 taps a side that
    reach the image: the kernels must be the whole kernels' central part, the rest of
    which is 0 (outside the image for every pixel)."""
    from statmc import filters
    shape = (7, 9, 2)
    whole = D.gaussian(4.0).kernels(shape)
    monkeypatch.setattr(filters, "_MAX_FULL_RADIUS", 2)
    cut = D.gaussian(4.0).kernels(shape)
    assert_central_part(cut, whole, (12, 8))


def test_gaussian_keeps_float32():
    x = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    assert D.gaussian(1.0)(x).dtype == np.float32


# ----------------------------------------------------------------------------- GEM
def test_gem_adapter_equals_reconstruct(toy):
    from statmc import gem

    r, st = toy
    x = st.mean.astype(np.float32)
    mv = st.mean_var.astype(np.float32)
    # The paper's rule uses γ, so a dropped `gamma` would show; the pooled default does not.
    paper = D.gem(st.mean_var, gamma=0.05, bias="paper")(x)
    np.testing.assert_array_equal(paper, gem.reconstruct(x, mv, gamma=0.05, bias="paper"))
    assert not np.array_equal(paper, gem.reconstruct(x, mv, gamma=0.3, bias="paper"))
    np.testing.assert_array_equal(D.gem(st.mean_var, gamma=0.3)(x), gem.reconstruct(x, mv))
    assert "bias='paper'" in repr(D.gem(st.mean_var, bias="paper"))
    with pytest.raises(InputError, match="`bias`"):
        D.gem(st.mean_var, bias="robust")


def test_gem_adapter_rejects_bad_variance_and_shape(toy):
    r, st = toy
    with pytest.raises(InputError, match="mean_var"):
        D.gem(-st.mean_var - 1.0)
    with pytest.raises(InputError, match="color"):
        D.gem(st.mean_var)(st.mean[:8])


# ----------------------------------------------------------------------------- OIDN
def test_oidn_is_deterministic(toy):
    r, st = toy
    x = st.mean.astype(np.float32)
    f = D.oidn(st.albedo, st.normal)
    y0 = f(x)
    for _ in range(5):
        assert np.array_equal(f(x), y0)
    # a second adapter (its own device and filter) gives the same bits
    g = D.oidn(st.albedo, st.normal)
    assert np.array_equal(g(x), y0)
    # ... and so does a different input in between (no state carried over)
    f(x * 1.5)
    assert np.array_equal(f(x), y0)


def test_oidn_matches_pyoidn_convenience_call(toy):
    import pyoidn

    r, st = toy
    x = st.mean.astype(np.float32)
    for kw in ({}, {"albedo": st.albedo}, {"albedo": st.albedo, "normal": st.normal}):
        ref = pyoidn.denoise(x, **kw, hdr=True, quality="high")
        np.testing.assert_array_equal(D.oidn(**kw)(x), ref)


def test_oidn_without_features_follows_the_image_shape():
    f = D.oidn()
    rng = np.random.default_rng(2)
    a = f(rng.random((16, 24, 3), dtype=np.float32))
    b = f(rng.random((20, 12, 3), dtype=np.float32))
    assert a.shape == (16, 24, 3) and b.shape == (20, 12, 3)
    f.close()
    f.close()  # idempotent
    assert f(rng.random((8, 8, 3), dtype=np.float32)).shape == (8, 8, 3)  # re-created on demand


def test_oidn_rejects_bad_inputs(toy):
    r, st = toy
    with pytest.raises(InputError, match="normal.*albedo"):
        D.oidn(normal=st.normal)
    with pytest.raises(InputError, match="albedo"):
        D.oidn(albedo=st.albedo + 2.0)
    with pytest.raises(InputError, match="albedo"):
        D.oidn(albedo=st.albedo[..., :2])
    with pytest.raises(InputError, match="quality"):
        D.oidn(quality="ultra")
    f = D.oidn(st.albedo)
    with pytest.raises(InputError, match="color"):
        f(st.mean[:16].astype(np.float32))
    with pytest.raises(InputError, match="color"):
        D.oidn()(np.zeros((4, 4, 2), np.float32))
    with pytest.raises(InputError, match="NaN"):
        D.oidn()(np.full((4, 4, 3), np.nan, np.float32))


# ----------------------------------------------------------------------------- torch
def _net(seed=0, cin=3):
    torch = pytest.importorskip("torch")
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Conv2d(cin, 8, 3, padding=1), torch.nn.Softplus(),
                               torch.nn.Conv2d(8, 3, 3, padding=1)).eval()


def test_torch_module_converts_layouts_at_the_boundary():
    torch = pytest.importorskip("torch")
    x = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    ident = D.torch_module(torch.nn.Identity())
    y = ident(x)
    assert y.dtype == np.float32 and np.array_equal(y, x)
    net = _net()
    ref = net(torch.from_numpy(x.transpose(2, 0, 1)[None].copy()))[0].detach().numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(D.torch_module(net)(x), ref, rtol=1e-6, atol=1e-7)


def test_torch_module_concatenates_bound_features():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(1)
    x = rng.random((6, 6, 3)).astype(np.float32)
    alb = rng.random((6, 6, 3)).astype(np.float32)
    nrm = rng.uniform(-1, 1, (6, 6, 3)).astype(np.float32)
    net = _net(cin=9)
    inp = np.concatenate([x, alb, nrm], axis=2).transpose(2, 0, 1)[None].copy()
    ref = net(torch.from_numpy(inp))[0].detach().numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(D.torch_module(net, albedo=alb, normal=nrm)(x), ref, rtol=1e-6, atol=1e-7)
    with pytest.raises(InputError, match="color"):
        D.torch_module(net, albedo=alb, normal=nrm)(x[:4])


def test_torch_jvp_matches_finite_differences():
    pytest.importorskip("torch")
    rng = np.random.default_rng(2)
    x = rng.random((8, 9, 3)).astype(np.float32)
    v = rng.standard_normal(x.shape).astype(np.float32)
    f = D.torch_module(_net())
    y, jv = f.jvp(x, v)
    np.testing.assert_array_equal(y, f(x))
    h = 1e-2
    fd = (f((x + h * v).astype(np.float64).astype(np.float32)).astype(np.float64)
          - f((x - h * v).astype(np.float32))) / (2 * h)
    np.testing.assert_allclose(jv, fd, rtol=0, atol=2e-3 * np.abs(jv).max())


def test_torch_module_rejects_bad_output_shape():
    torch = pytest.importorskip("torch")
    f = D.torch_module(torch.nn.Conv2d(3, 2, 1))
    with pytest.raises(InputError, match="module"):
        f(np.zeros((4, 4, 3), np.float32))


# ----------------------------------------------------------------------------- get / as_denoiser
def test_get_by_name_and_errors():
    assert isinstance(D.get("none"), D.IdentityDenoiser)
    assert isinstance(D.get("Gaussian", sigma=2.0), D.GaussianDenoiser)
    with pytest.raises(InputError, match="name"):
        D.get("bm3d")
    with pytest.raises(InputError, match="unexpected sigmaa"):
        D.get("gaussian", sigmaa=2.0)
    with pytest.raises(InputError, match="needs mean_var"):
        D.get("gem")
    with pytest.raises(InputError, match="sigma"):
        D.get("gaussian", sigma=-1.0)


def test_as_denoiser():
    torch = pytest.importorskip("torch")

    def f(c):
        return c

    assert D.as_denoiser(f) is f
    assert isinstance(D.as_denoiser("gaussian", sigma=1.0), D.GaussianDenoiser)
    assert isinstance(D.as_denoiser(torch.nn.Identity()), D.TorchDenoiser)
    with pytest.raises(InputError, match="callable"):
        D.as_denoiser(3.0)
    with pytest.raises(InputError, match="bound"):
        D.as_denoiser(f, sigma=1.0)


def test_docstring_examples():
    import doctest

    result = doctest.testmod(D, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 3 and result.failed == 0


# --------------------------------------------------------------- properties on any image
from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2 ** 31), h=st.integers(1, 12), w=st.integers(1, 12), c=st.integers(1, 3),
       dtype=st.sampled_from([np.float32, np.float64]), scale=st.sampled_from([0.0, 1e-20, 1.0, 1e15]),
       sigma=st.sampled_from([0.3, 1.0, 2.5, 40.0]), zero_frac=st.sampled_from([0.0, 0.3, 1.0]))
def test_gaussian_and_gem_denoisers_average_within_the_input_range_on_any_image(seed, h, w, c,
                                                                               dtype, scale,
                                                                               sigma, zero_frac):
    # The Gaussian's kernels are >= 0, 0 outside the image and sum to 1 (border
    # renormalised), and apply_kernels with them is the filter; so are GEM's scales:
    # outputs keep shape and dtype and lie within each channel's input range, and the
    # GEM variance bound is >= 0 (0 where every variance is 0).
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(h, w, c)) * scale * rng.gamma(0.5, 1, size=(h, w, 1))).astype(dtype)
    v = (rng.gamma(0.3, 1, size=(h, w, c)) * (scale ** 2 + 1e-30)).astype(dtype)
    v[rng.uniform(size=(h, w)) < zero_frac] = 0
    lo, hi = x.min(axis=(0, 1)), x.max(axis=(0, 1))
    g = D.gaussian(sigma)
    K = g.kernels(x.shape)
    # rounding of a k-term sum (and of the border scale's taps sum), k taps a side
    slack = (8 + 2 * K.shape[-1]) * np.finfo(dtype).eps * np.abs(x).max(axis=(0, 1))
    assert K.min() >= 0
    np.testing.assert_allclose(K.sum(axis=(2, 3)), 1.0, rtol=1e-12)
    for f in (g, D.gem(v), D.identity()):
        y = f(x)
        assert y.shape == x.shape and y.dtype == x.dtype and np.isfinite(y).all(), f
        assert (y >= lo - slack).all() and (y <= hi + slack).all(), f
    np.testing.assert_allclose(apply_kernels(K, x.astype(np.float64)), g(x.astype(np.float64)),
                               rtol=1e-9, atol=1e-12 * float(np.abs(x).max(initial=0)))
    var, img = D.gem(v).output_variance(x)
    assert var.shape == x.shape and np.isfinite(var).all() and var.min() >= 0
    if not v.any():
        assert not var.any()


def test_gem_denoiser_on_float32_color_whose_variance_exceeds_float32():
    # Regression (found by a magnitude sweep): GEMDenoiser cast its finite float64
    # `mean_var` to the colour's float32, which overflowed to inf past 3.4e38 (a 1e19
    # pixel with standard deviation 3e19) and was refused as "`mean_var` holds Inf
    # values". The reconstruction now runs in float64 there; float32 out, as documented.
    x = np.full((2, 3, 1), 1e19, np.float32)
    x[0, 0] = 3e19
    v = np.full((2, 3, 1), 1e39)
    f = D.gem(v)
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # no overflow in a cast either
        y = f(x)
        var, img = f.output_variance(x)
    assert y.dtype == np.float32
    np.testing.assert_array_equal(y, f(x.astype(np.float64)).astype(np.float32))
    assert np.isfinite(var).all() and var.min() > 0
    np.testing.assert_array_equal(img, f(x.astype(np.float64)))


def test_gem_denoiser_final_must_be_a_bool():
    """``GEMDenoiser(mean_var, final="no")`` ran as ``final=True`` (``bool("no")``); the
    option is checked as gem's own functions check it (session 15)."""
    v = np.full((6, 7, 3), 0.01)
    with pytest.raises(InputError, match=r"`final` must be True or False; got 'no'"):
        D.GEMDenoiser(v, final="no")
    assert D.GEMDenoiser(v, final=np.False_).final is False
