"""The Python API under unusual but legal inputs, and bad ones (a notebook user's calls).

Each test pins a finding of the session-10 API audit: the input a user will pass, and
either the same result as the contiguous native float64 input or an :class:`InputError`
that names the parameter.  Behaviour that already worked is only tested where it guards a
real risk (non-contiguous or foreign-byte-order arrays handed to compiled kernels).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from _memory import traced_peak
from statmc import (analytic, combine, denoisers, filters, gem, metrics, progressive, sampling,
                    sure)
from statmc.errors import InputError
from statmc.stats import PixelStats

H, W, C = 7, 9, 3


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1, 1.0, (H, W, C))
    v = rng.uniform(1e-3, 1e-2, (H, W, C))
    n = rng.integers(2, 9, (H, W))
    k = rng.uniform(0.0, 1.0, (H, W, 5, 5))
    return x, v, n, k / k.sum(axis=(2, 3), keepdims=True)


def _calls():
    """(name, function, arguments): public functions whose arrays reach numba kernels."""
    x, v, n, k = _inputs()
    z = denoisers.gaussian(1.0)(x)
    return [
        ("filters.gaussian_filter", lambda a: filters.gaussian_filter(a, 1.5), [x]),
        ("filters.gaussian_spread", lambda a: filters.gaussian_spread(a, 1.5), [v]),
        ("filters.filter_bank", filters.filter_bank, [x, v]),
        ("gem.reconstruct", lambda a, b, c: gem.reconstruct(a, b, n=c, final=False), [x, v, n]),
        ("gem.sampling_map", lambda a, b, c: gem.sampling_map(a, b, c, 300, rng=1), [x, v, n]),
        ("gem.difference_variance", gem.difference_variance, [v]),
        ("sampling.counts_from_density",
         lambda a: sampling.counts_from_density(a, 300, rng=1), [v[..., 0]]),
        ("sure.sure", sure.sure, [k, x, v]),
        ("analytic.apply_kernels", analytic.apply_kernels, [k, x]),
        ("combine.combine", combine.combine, [x, z, k]),
        ("combine.statistical_weights",
         lambda a, b, c: combine.statistical_weights(a, b, c, 0.5 * c, 5), [x, z, v]),
        ("progressive.mixing_weights",
         lambda a, b, c: progressive.mixing_weights(a, b, c, (b - a) ** 2, 0.3 * c), [x, z, v]),
        ("progressive.confidence_gate",
         lambda a, b, c: progressive.confidence_gate(a, b, c, np.full(a.shape, 0.5)), [x, z, v]),
    ]


CALLS = _calls()


def _layouts(a):
    """Views and copies of ``a`` that hold the same numbers."""
    strided = np.zeros((2 * a.shape[0],) + a.shape[1:], a.dtype)
    strided[::2] = a
    readonly = a.copy()
    readonly.setflags(write=False)
    return {
        "big-endian": a.astype(a.dtype.newbyteorder(">")),
        "strided": strided[::2],
        "reversed": np.ascontiguousarray(a[..., ::-1])[..., ::-1],
        "fortran": np.asfortranarray(a),
        "readonly": readonly,
    }


def _assert_same(expected, got, where):
    if isinstance(expected, dict):
        assert expected.keys() == got.keys(), where
        for key in expected:
            _assert_same(expected[key], got[key], f"{where}[{key}]")
    elif isinstance(expected, (tuple, list)):
        assert len(expected) == len(got), where
        for i, (e, g) in enumerate(zip(expected, got)):
            _assert_same(e, g, f"{where}[{i}]")
    elif isinstance(expected, np.ndarray) or np.isscalar(expected):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected), err_msg=where)


@pytest.mark.parametrize("layout", ["big-endian", "strided", "reversed", "fortran", "readonly"])
@pytest.mark.parametrize("name,func,args", CALLS, ids=[c[0] for c in CALLS])
def test_array_layouts_give_the_contiguous_result(name, func, args, layout):
    """A big-endian array (``'>f8'``, as some file readers return) raised numba's
    TypingError in every function whose arrays reach a compiled kernel (filters, GEM,
    counts); the other layouts guard the same kernels against strided or read-only views.
    The caller's arrays are never written to."""
    expected = func(*args)
    for i, a in enumerate(args):
        other = _layouts(np.asarray(a))[layout]
        before = other.copy()
        got = func(*args[:i], other, *args[i + 1:])
        _assert_same(expected, got, f"{name} argument {i} {layout}")
        np.testing.assert_array_equal(other, before)


# The kernel modules whose inputs are normalised (statmc._kernel_inputs), and the calls
# that reach them only (GEM, progressive and sampling prepare their own inputs).
NORMALISED = ("statmc._combine_kernels", "statmc._analytic_kernels", "statmc._filter_kernels")
ONE_VARIANT = ["filters.gaussian_filter", "filters.gaussian_spread", "filters.filter_bank",
               "gem.reconstruct", "gem.difference_variance",
               "sure.sure", "analytic.apply_kernels", "combine.combine",
               "combine.statistical_weights"]


def _entry_kernels():
    """(module, name, dispatcher) of the compiled kernels that Python code calls, i.e. not
    only from other kernels (those are typed when their caller compiles)."""
    import importlib

    from numba.core.registry import CPUDispatcher
    out = []
    for mod_name in NORMALISED:
        mod = importlib.import_module(mod_name)
        disp = {n: d for n, d in vars(mod).items() if isinstance(d, CPUDispatcher)}
        nested = {n for d in disp.values() for n in d.py_func.__code__.co_names if n in disp}
        out += [(mod, n, d) for n, d in disp.items() if n not in nested]
    return out


def _same_kernel_types(got, ref, strided_ok):
    """``got`` and ``ref`` (kernel name, argument types) equal; with ``strided_ok`` an array
    may also be the read-only strided view of the same array (layout ``'A'``)."""
    from numba.core import types
    if len(got) != len(ref) or got[0] != ref[0]:
        return False
    return all(g == r or (strided_ok and isinstance(g, types.Array) and isinstance(r, types.Array)
                          and g == r.copy(layout="A", readonly=True)) for g, r in zip(got, ref))


@pytest.mark.parametrize("layout", ["big-endian", "strided", "reversed", "fortran", "readonly"])
@pytest.mark.parametrize("name,func,args", [c for c in CALLS if c[0] in ONE_VARIANT],
                         ids=[c[0] for c in CALLS if c[0] in ONE_VARIANT])
def test_array_layouts_reuse_the_compiled_kernels(name, func, args, layout, monkeypatch):
    """A read-only, foreign-byte-order or Fortran-ordered input reaches each kernel with the
    argument types of the contiguous call, so numba compiles nothing new: a read-only
    ``var_y`` compiled the statistical weights' kernels anew (30-60 s on a cold cache, for
    the same numbers), and likewise the combination, filter and kernel-apply kernels.  A
    strided one is copied, except the weights and kernels (up to 7 GiB at 1080p), which
    stay views, read through their strides: the kernels' one other layout."""
    seen = []
    for mod, kname, disp in _entry_kernels():
        def spy(*a, _d=disp, _n=kname, **kw):
            seen.append((_n,) + tuple(_d.typeof_pyval(x) for x in a) + tuple(
                (k, _d.typeof_pyval(v)) for k, v in sorted(kw.items())))
            return _d(*a, **kw)
        monkeypatch.setattr(mod, kname, spy)
    func(*args)
    contiguous = set(seen)
    assert contiguous, f"{name} reached none of the kernels watched"
    for i, a in enumerate(args):
        seen.clear()
        func(*args[:i], _layouts(np.asarray(a))[layout], *args[i + 1:])
        new = [g for g in set(seen) if not any(
            _same_kernel_types(g, r, layout in ("strided", "reversed")) for r in contiguous)]
        assert not new, f"{name} argument {i} {layout}: new kernel argument types {new}"


def test_big_endian_float32_counts_and_images():
    """``'>f4'`` images (OpenEXR-like float32 in foreign byte order) and ``'>i8'`` count
    maps into GEM: the result equals the native float32 / int64 one."""
    x, v, n, _ = _inputs(1)
    x32, v32 = x.astype(np.float32), v.astype(np.float32)
    expected = gem.reconstruct(x32, v32, n=n, final=False)
    got = gem.reconstruct(x32.astype(">f4"), v32.astype(">f4"), n=n.astype(">i8"), final=False)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)


# ----------------------------------------------------------------------- empty images
EMPTY = [(0, 4, 3), (4, 0, 3), (4, 4, 0)]


def _empty_calls(shape):
    x = np.ones(shape)
    v = np.full(shape, 0.01)
    hw = shape[:2]
    k = np.full(hw + (3, 3), 1 / 9)
    g = denoisers.gaussian(1.0)
    st = x[None].repeat(2, 0)
    return {
        "sure.sure": lambda: sure.sure(k, x, v),
        "sure.mc_sure": lambda: sure.mc_sure(g, x, v, rng=1),
        "sure.kernel_variance": lambda: sure.kernel_variance(k, v),
        "analytic.apply_kernels": lambda: analytic.apply_kernels(k, x),
        "analytic.kernel_bias_variance":
            lambda: analytic.kernel_bias_variance(k, x, np.full(hw, 4.0), np.full(hw, 2.0), x, v),
        "analytic.optimal_sample_map":
            lambda: analytic.optimal_sample_map(k, x, np.full(hw, 4.0), x, v, 10),
        "combine.combine_boosting": lambda: combine.combine_boosting(x, x, k),
        "combine.statistical_weights": lambda: combine.statistical_weights(x, x, v, v, 3),
        "combine.combine_denoised": lambda: combine.combine_denoised(x, v, g, size=3, rng=1),
        "combine.combine_bin_images": lambda: combine.combine_bin_images(st, st, size=3),
        "progressive.mixing_weights": lambda: progressive.mixing_weights(x, x, v, v, v),
        "progressive.confidence_gate": lambda: progressive.confidence_gate(x, x, v, v),
        "denoisers.gaussian": lambda: g(x),
    }


@pytest.mark.parametrize("shape", EMPTY, ids=str)
def test_empty_images_are_refused_by_name(shape):
    """An image without pixels or channels gave ZeroDivisionError, IndexError or "Mean of
    empty slice" NaNs; the statistical functions now refuse it naming the argument."""
    for name, call in _empty_calls(shape).items():
        with pytest.raises(InputError, match="non-empty") as info:
            call()
        assert "`" in str(info.value), name


@pytest.mark.parametrize("shape", EMPTY, ids=str)
def test_empty_images_through_plain_filters(shape):
    """Pure filters map an empty image to an empty image (C = 0 was a ZeroDivisionError),
    and a density without pixels takes a zero budget only."""
    a = np.ones(shape)
    assert filters.gaussian_filter(a, 2.0).shape == shape
    assert filters.gaussian_spread(a, 2.0).shape == shape
    assert gem.difference_variance(a).shape == (4,) + shape
    d = np.ones(shape[:2]) if shape[2] else np.ones((0, 3))
    if d.size == 0:
        assert sampling.counts_from_density(d, 0).shape == d.shape
        with pytest.raises(InputError, match=r"`density` must have pixels to place `budget`=5 samples in; got shape"):
            sampling.counts_from_density(d, 5)


# ----------------------------------------------------------------------- huge counts
def test_huge_integer_counts_stay_exact():
    """Counts went through float64: 2**62 + 1 became 2**62, ``total_samples`` wrapped to a
    negative int64 sum, and 2**63 - 1 (or 1e300 as float) cast to a negative count."""
    x, v, _, _ = _inputs(2)
    n = np.full((H, W), 2 ** 62 + 1, np.int64)
    for st in (PixelStats(n, x, v), PixelStats.from_mean_var(x, v, n),
               PixelStats.from_sums(n, x, v + x * x)):
        np.testing.assert_array_equal(st.n, n)
        assert st.total_samples == H * W * (2 ** 62 + 1)
    top = PixelStats(np.full((H, W), 2 ** 63 - 1, np.int64), x, v)
    assert top.n.min() == 2 ** 63 - 1 and top.total_samples == H * W * (2 ** 63 - 1)


@pytest.mark.parametrize("n", [np.full((H, W), 2 ** 64 - 1, np.uint64), np.full((H, W), 1e300),
                               np.full((H, W), 2.0 ** 63)], ids=["uint64", "1e300", "2**63"])
def test_counts_beyond_int64_are_refused(n):
    x, v, _, _ = _inputs(2)
    with pytest.raises(InputError, match=r"`n` must fit in int64"):
        PixelStats(n, x, v)


def test_merge_refuses_overflowing_counts():
    """The merged count overflowed to a negative int64, reported as "`n` must be >= 0";
    then the refusal named no parameter ("cannot merge: the summed sample counts overflow
    int64 ..."): it names `other`, what was expected and the counts given."""
    x, v, _, _ = _inputs(2)
    big = PixelStats(np.full((H, W), 2 ** 62, np.int64), x, v)
    with pytest.raises(InputError, match=r"^`other` must add to the sample counts `n` without "
                                         r"overflowing int64 \(a merged count < 2\*\*63\); got "
                                         rf"{H * W} pixels .*largest `n`: {2 ** 62} here and "
                                         rf"{2 ** 62} in `other`"):
        big.merge(big)
    with pytest.raises(InputError, match=r"^`other` must be a statmc.PixelStats to merge; "
                                         r"got ndarray"):
        big.merge(x)
    with pytest.raises(InputError, match=r"^`other` must have the shape .*\(7, 9, 3\); "
                                         r"cannot merge \(7, 8, 3\)"):
        big.merge(PixelStats(np.ones((H, W - 1)), x[:, 1:], v[:, 1:]))


# ----------------------------------------------------------------------- tone mapping
@pytest.mark.parametrize("name", ["aces", "reinhard"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tonemap_saturates_for_huge_radiance(name, dtype):
    """ACES of float32 radiance above ~1.8e19 was inf/inf = NaN (x² overflowed), and so
    was Reinhard where ``exposure · x`` overflowed; the curve is 1 and its slope 0 there."""
    from statmc.da_sampling import tonemap, tonemap_derivative

    big = np.finfo(dtype).max
    x = np.array([big, big / 1e10, 1e19, 0.5], dtype)
    for exposure in (1.0, 1e10):
        t = tonemap(x, name, exposure=exposure)
        d = tonemap_derivative(x, name, exposure=exposure)
        assert t.dtype == dtype and np.isfinite(t).all() and np.isfinite(d).all()
        np.testing.assert_array_equal(t[:2], 1.0)
        np.testing.assert_array_less(d[:3], 1e-18)
    e = 0.5 * 1.0
    want = e / (1 + e) if name == "reinhard" else e * (2.51 * e + 0.03) / (e * (2.43 * e + 0.59) + 0.14)
    assert tonemap(x, name)[3] == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tonemap_with_a_tiny_exposure_is_quiet_and_unchanged(dtype):
    """The ACES cap 8/exposure (6c9d1ab) passed beyond float32's range for an exposure
    below ~2.4e-38 and np.minimum warned 'overflow encountered in cast' on a float32 image;
    the values must stay those of the curve (clamped to 1 from e·x = 7.24)."""
    from statmc.da_sampling import tonemap, tonemap_derivative

    x = np.array([0.0, 1.0, 1e30, np.finfo(dtype).max], dtype)
    for exposure in (1e-38, 1e-300):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            t = tonemap(x, exposure=exposure)
            d = tonemap_derivative(x, exposure=exposure)
        y = np.minimum(x.astype(np.float64) * exposure, 8.0)     # the curve is 1 from 7.24
        want = np.minimum(y * (2.51 * y + 0.03) / (y * (2.43 * y + 0.59) + 0.14), 1.0)
        np.testing.assert_allclose(t, want.astype(dtype), rtol=1e-6, atol=0)
        assert t.dtype == dtype and np.isfinite(d).all() and (d >= 0).all()


@pytest.mark.parametrize("name", ["aces", "reinhard"])
def test_tonemap_with_a_huge_exposure_keeps_zero_at_zero(name):
    """An exposure beyond float32's range became inf in a float32 image's arithmetic, so
    T(0·inf) was NaN where the image is 0 (and everywhere for ACES: its cap 8/inf = 0
    times inf), its derivative NaN likewise.  The curve of e·x is computed as in float64
    there: 0 stays 0, any positive pixel saturates (or not: 1e-39·1e39 = 1), the slope
    at 0 (e·T'(0), beyond float32) is inf, and nothing warns."""
    from statmc.da_sampling import tonemap, tonemap_derivative

    x = np.array([0.0, 1e-45, 1e-39, 3e-39, 1.0, -1.0, 3e38], np.float32)
    for exposure in (1e39, 1e300, np.finfo(np.float64).max):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            t = tonemap(x, name, exposure=exposure)
            d = tonemap_derivative(x, name, exposure=exposure)
            t64 = tonemap(x.astype(np.float64), name, exposure=exposure)
            d64 = tonemap_derivative(x.astype(np.float64), name, exposure=exposure)
        assert t.dtype == d.dtype == np.float32
        assert not np.isnan(t).any() and not np.isnan(d).any()
        assert t[0] == t[5] == 0.0 and t[6] == 1.0 and d[5] == d[6] == 0.0
        np.testing.assert_array_equal(t, t64.astype(np.float32))
        with np.errstate(over="ignore"):
            np.testing.assert_array_equal(d, d64.astype(np.float32))
        assert d[0] == np.inf or exposure == 1e39        # e·T'(0) > 3.4e38 (not 0.2e39)


def test_tonemap_derivative_where_its_intermediates_overflow():
    """In float32 the ACES slope was (e·N)/den², and e·N overflowed to inf for e > ~1e36
    where the slope itself is finite (e = 1e37, e·x = 5: 9.5e34); Reinhard's e/(1 + e·x)²
    squared first, and 0 came out where the slope is 1e-20 (e = 1e20, x = 1)."""
    from statmc.da_sampling import tonemap_derivative

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        aces = tonemap_derivative(np.array([5e-37], np.float32), "aces", exposure=1e37)
        reinhard = tonemap_derivative(np.array([1.0], np.float32), "reinhard", exposure=1e20)
    y, (a, b, c, d, e) = 5.0, (2.51, 0.03, 2.43, 0.59, 0.14)
    num, den = y * (a * y + b), y * (c * y + d) + e
    want = 1e37 * ((2 * a * y + b) * den - num * (2 * c * y + d)) / den ** 2
    assert float(aces[0]) == pytest.approx(want, rel=1e-5)
    assert float(reinhard[0]) == pytest.approx(1e-20, rel=1e-6)


# ----------------------------------------------------------------------- adaptive loop
@pytest.fixture(scope="module")
def toy():
    from statmc.toy import ToyRenderer
    return ToyRenderer("edges", width=10, height=8)


@pytest.mark.parametrize("kwargs,match", [
    (dict(spp=float("nan")), "`spp` must be a finite number"),       # was int(round(nan))'s ValueError
    (dict(spp="8"), "`spp` must be a finite number"),                # was str.__round__ TypeError
    (dict(spp=8, initial_spp=2.5), "`initial_spp` must be a whole"),  # silently rendered 2 spp
    (dict(spp=8, iterations=2.5), "`iterations` must be a whole"),   # was range(2.5) TypeError
    (dict(spp=8, seed=None), "`seed` must be a non-negative integer"),  # was None * int TypeError
    (dict(spp=8, seed=np.random.default_rng(1)), "`seed` must be a non-negative integer"),
    (dict(spp=8, sampler="gem", gama=0.3), r"unknown option\(s\) \['gama'\] for sampler 'gem'"),
])
def test_adaptive_render_refuses_bad_arguments_before_rendering(toy, kwargs, match):
    """Each of these was a TypeError/ValueError from deep inside (the misspelt sampler
    option only after the first pass had been rendered), or silently wrong."""
    from statmc.adaptive import adaptive_render
    with pytest.raises(InputError, match=match):
        adaptive_render(toy, **kwargs)


def test_initial_spp_given_as_whole_float_renders_it(toy):
    """``initial_spp=4.0`` (whole-valued float) is accepted and renders 4 spp first."""
    from statmc.adaptive import adaptive_render
    res = adaptive_render(toy, 6, initial_spp=4.0, iterations=1, sampler="uniform")
    assert res.counts[0].dtype.kind == "i" and np.all(res.counts[0] == 4)
    assert res.stats.total_samples == 6 * toy.height * toy.width


def test_sampler_options_are_checked_by_name():
    from statmc.adaptive import get_sampler
    get_sampler("gem", gamma=0.3)
    get_sampler("expected-error", kernels="gem", gem_options={"gamma": 0.3}, sigma=1.0)
    get_sampler("denoising-aware", denoiser="gaussian", k=2, variant="variance")
    get_sampler(lambda stats, budget, rng, **kw: None, anything=1)      # a callable: its own
    for name in ("uniform", "expected-error", "denoising-aware"):
        with pytest.raises(InputError, match=rf"unknown option\(s\) \['nope'\] for sampler '{name}'"):
            get_sampler(name, nope=1)


def test_sampler_options_of_a_registered_sampler_are_its_own(monkeypatch):
    """SAMPLERS is public and da_sampling.sampler's docstring says to register samplers in
    it; 1a57dd7 checked every name outside the built-in four against the uniform sampler,
    so a user's registered sampler refused its own option ("unknown option(s) ['power'] for
    sampler 'capped'; expected some of none"), and one registered over "gem" was checked
    against GEM's gamma."""
    from statmc.adaptive import SAMPLERS, get_sampler
    x, v, n, _ = _inputs(21)
    stats = PixelStats.from_mean_var(x, v * n[..., None], n)

    def capped(stats, budget, rng, *, power=1.0):
        return sampling.counts_from_density(stats.mean_var.mean(axis=2) ** power, budget, rng=rng)

    monkeypatch.setitem(SAMPLERS, "capped", capped)
    assert get_sampler("capped", power=0.5)(stats, 100, 1).sum() == 100
    with pytest.raises(InputError, match=r"unknown option\(s\) \['pwr'\] for sampler 'capped'"):
        get_sampler("capped", pwr=0.5)
    monkeypatch.setitem(SAMPLERS, "gem", lambda stats, budget, rng, **kw: capped(stats, budget,
                                                                                  rng, **kw))
    assert get_sampler("gem", power=0.5)(stats, 100, 1).sum() == 100


@pytest.mark.parametrize("args,kwargs,match", [
    ((4, 10), {}, "`first`=10 samples exceed `total`=4"),     # gave [0, 0, -1, -1, ...]
    ((-1, 2), {}, "`total` must be a whole number"),
    ((10.5, 4), {}, "`total` must be a whole number"),         # gave float budgets
    ((10, 4), {"iterations": -1}, "`iterations` must be a whole"),
])
def test_pass_budgets_refuses_negative_and_fractional_budgets(args, kwargs, match):
    from statmc.adaptive import pass_budgets
    with pytest.raises(InputError, match=match):
        pass_budgets(*args, **kwargs)


# ----------------------------------------------------------------------- keyword edges
@pytest.mark.parametrize("gamma", [None, "0.2"])
def test_gem_gamma_must_be_a_number(gamma):
    """``gamma=None`` was float(None)'s TypeError; the string "0.2" was silently parsed."""
    x, v, _, _ = _inputs(3)
    with pytest.raises(InputError, match="`gamma` must be in"):
        gem.reconstruct(x, v, gamma=gamma)


def test_confidence_gate_refuses_a_vanishing_sigma_s():
    """``sigma_s=1e-40`` passed the ``> 0`` check and gave an all-NaN gate (σ_s is below
    float32's range in the default single-precision work).  1e-6 still works."""
    x, v, _, _ = _inputs(3)
    y = denoisers.gaussian(1.0)(x)
    alpha = np.full(x.shape, 0.5)
    assert np.isfinite(progressive.confidence_gate(x, y, v, alpha, sigma_s=1e-6)).all()
    with pytest.raises(InputError, match=r"`sigma_s` must be >= 1e-06; got 1e-40"):
        progressive.confidence_gate(x, y, v, alpha, sigma_s=1e-40)


# ----------------------------------------------------------------------- metrics
def test_relmse_of_huge_values_is_not_nan():
    """relMSE of float64 values beyond ~1e154 was inf/inf = NaN (both squares overflow);
    it is scale-free there, so 1e200·x against 1e200·r gives the eps-free relMSE."""
    from statmc.metrics import relmse
    x, _, _, _ = _inputs(4)
    r = 1.01 * x
    want = relmse(x, r, eps=0.0)
    assert relmse(1e200 * x, 1e200 * r) == pytest.approx(want, rel=1e-12)
    assert relmse(1e300 * x, -1e300 * r) == pytest.approx(relmse(x, -r, eps=0.0), rel=1e-12)
    assert relmse(1e250 * x, np.zeros_like(x)) == np.inf     # the true value overflows


def test_ssim_works_in_units_of_data_range():
    """SSIM of HDR values with a matching ``data_range`` beyond ~1e154 was NaN (the squares
    and C1 = (k1 L)² overflowed); it is invariant to scaling x, ref and L together.  Values
    too large for the given range are refused instead of returning NaN."""
    from statmc.metrics import one_minus_ssim
    x, _, _, _ = _inputs(4)
    r = 1.01 * x
    want = one_minus_ssim(x, r)
    assert one_minus_ssim(1e200 * x, 1e200 * r, data_range=1e200) == pytest.approx(want, rel=1e-9)
    with pytest.raises(InputError, match="too large for SSIM at `data_range`=1.0"):
        one_minus_ssim(1e200 * x, 1e200 * r)


# ----------------------------------------------------------------------- array-likes
def test_unconvertible_array_likes_are_input_errors():
    """A ragged list was NumPy's bare ValueError, and a torch tensor that requires grad
    torch's RuntimeError; both now name the argument."""
    torch = pytest.importorskip("torch")
    with pytest.raises(InputError, match="`image` must be an array of real numbers.*list"):
        filters.gaussian_filter([[1.0, 2.0], [3.0]], 1.0)
    x, v, _, _ = _inputs(5)
    with pytest.raises(InputError, match="`mean` must be an array of real numbers.*detach"):
        gem.reconstruct(torch.tensor(x, requires_grad=True), v)


def test_masked_arrays_with_masked_entries_are_refused():
    """The mask was dropped silently: relMSE used the values under it."""
    from statmc.metrics import relmse
    x, _, _, _ = _inputs(5)
    masked = np.ma.masked_array(x, mask=x > 0.5)
    with pytest.raises(InputError, match="`x` is a masked array with .* masked entries"):
        relmse(masked, x)
    assert relmse(np.ma.masked_array(x), x) == 0.0          # nothing masked: fine


def test_grey_image_refusal_says_how_to_add_the_channel_axis():
    x, v, _, _ = _inputs(5)
    with pytest.raises(InputError, match=r"got shape \(7, 9\)\. For a grey image add a "
                                         r"channel axis: `x\[\.\.\., None\]`"):
        sure.mc_sure(denoisers.gaussian(1.0), x[..., 0], v[..., 0])


def test_combine_bias_variance_ignores_outside_taps_and_refuses_nan_inside():
    """A NaN weight on a tap outside the image (documented as never read, and ignored by
    ``combine``) made that pixel's bias and variance NaN; a NaN inside the image gave NaN
    silently where ``combine`` raises."""
    x, v, _, k = _inputs(6)
    outside = k.copy()
    outside[0, 0, 0, 0] = np.nan                    # tap (-2, -2) of the corner pixel
    clean = k.copy()
    clean[0, 0, 0, 0] = 0.0
    for got, want in zip(combine.combine_bias_variance(outside, v, v, z_bias=x),
                         combine.combine_bias_variance(clean, v, v, z_bias=x)):
        np.testing.assert_array_equal(got, want)
    inside = k.copy()
    inside[3, 4, 2, 2] = np.nan
    with pytest.raises(InputError, match=r"`weights` must be finite .* \(row 3, column 4\)"):
        combine.combine_bias_variance(inside, v, v)
    # finite weights whose absolute sum overflows are finite all the same (session-10
    # review: they were refused as "must be finite")
    huge = k.copy()
    huge[3, 4, :, :] = 1e308
    with np.errstate(all="ignore"):
        bias, var = combine.combine_bias_variance(huge, v, v)
    assert bias.shape == var.shape == x.shape


@pytest.mark.parametrize("bounds", [None, 1.0, (0.0, 1.0, 2.0)])
def test_sample_future_bounds_must_be_a_pair(bounds):
    """``bounds=None`` was "'NoneType' object is not iterable" (TypeError)."""
    x, v, n, _ = _inputs(7)
    with pytest.raises(InputError, match="`bounds` must be \\(low, high\\)"):
        analytic.sample_future(x, n, n, x, v, dist="clipped_normal", bounds=bounds, rng=1)


@pytest.mark.parametrize("kwargs,match", [
    (dict(max_iter=0), "`max_iter` must be a whole number of iterations >= 1"),
    (dict(max_iter=-1), "`max_iter` must be a whole"),
    (dict(rtol=-1.0), "`rtol` must be >= 0"),
    (dict(rtol=float("nan")), "`rtol` must be a finite number"),
])
def test_optimal_sample_map_checks_its_solver_options(kwargs, match):
    """``max_iter <= 0`` returned the starting map as if solved, and a negative or NaN
    ``rtol`` silently ran to ``max_iter``."""
    x, v, n, k = _inputs(7)
    with pytest.raises(InputError, match=match):
        analytic.optimal_sample_map(k, x, n, x, v, 100, **kwargs)


def test_unknown_progressive_options_are_refused():
    """``progressive_options={'nope': 1}`` was a TypeError from progressive_denoise with
    ``output='progressive'`` and silently unused otherwise."""
    from statmc.da_sampling import denoising_aware_density
    x, v, _, _ = _inputs(8)
    st = PixelStats.from_mean_var(x, 8 * v, np.full((H, W), 8))
    for output in ("progressive", "denoised"):
        with pytest.raises(InputError, match=r"unknown `progressive_options` \['nope'\]"):
            denoising_aware_density(st, denoisers.gaussian(1.0), output=output,
                                    progressive_options={"nope": 1}, rng=1)


def test_budgets_beyond_float64_integers_are_refused():
    """Counts are placed through float64 targets: a budget of 2**56 + 12345 came back 6
    samples off (the sum must equal the budget) and 2**63 overflowed (OverflowError in
    counts_from_density, numba's SystemError in gem.sampling_map).  2**53 is exact."""
    x, v, n, _ = _inputs(8)
    d = v[..., 0]
    assert int(sampling.counts_from_density(d, 2 ** 53, rng=1).sum(dtype=object)) == 2 ** 53
    for budget in (2 ** 53 + 1, 2 ** 56 + 12345, 2 ** 63):
        with pytest.raises(InputError, match=r"`budget` must be a whole .*<= 9007199254740992"):
            sampling.counts_from_density(d, budget, rng=1)
        with pytest.raises(InputError, match=r"`budget` must be a whole .*<= 9007199254740992"):
            gem.sampling_map(x, v, n, budget, rng=1)


def test_estimate_mse_takes_float16_and_big_endian_banks():
    """gem.estimate_mse handed its arrays to the kernel as given: float16 raised numba's
    NotImplementedError and '>f8'/'>f4' its TypingError."""
    x, v, _, _ = _inputs(9)
    sig = [0.0, 1.0, 2.0]
    vals, vars_ = filters.filter_bank(x, v, sig)
    r2 = np.array([filters.kernel_moment2(s) for s in sig])
    scales = np.random.default_rng(9).integers(0, 3, (H, W))
    want = gem.estimate_mse(vals, vars_, r2, scales)
    got = gem.estimate_mse(vals.astype(">f8"), vars_.astype(">f8"), r2, scales.astype(">i8"))
    np.testing.assert_array_equal(got, want)
    half = gem.estimate_mse(vals.astype(np.float16), vars_.astype(np.float16), r2, scales)
    want32 = gem.estimate_mse(vals.astype(np.float16).astype(np.float32),
                              vars_.astype(np.float16).astype(np.float32), r2, scales)
    assert half.dtype == np.float32
    np.testing.assert_array_equal(half, want32)


@pytest.mark.parametrize("n,w,match", [
    (2.5, [0.25, 0.5, 0.25], "`n` must be a non-negative integer"),    # was IndexError
    (-1, [0.25, 0.5, 0.25], "`n` must be a non-negative integer"),     # was an empty array
    (5, [0.5, 0.5], "`w` must be a centred kernel of odd length"),    # was IndexError
])
def test_border_scale_checks_its_arguments(n, w, match):
    with pytest.raises(InputError, match=match):
        filters.border_scale(n, w)


def test_denoising_aware_map_takes_a_whole_float_budget():
    """``budget=100.0`` (spp·H·W computed in floating point) was refused by
    denoising_aware_map ("must be a non-negative integer") while counts_from_density,
    gem.sampling_map and the other samplers accept whole floats."""
    from statmc.da_sampling import denoising_aware_map
    x, v, _, _ = _inputs(10)
    st = PixelStats.from_mean_var(x, 8 * v, np.full((H, W), 8))
    g = denoisers.gaussian(1.0)
    np.testing.assert_array_equal(denoising_aware_map(st, g, 100.0, rng=1),
                                  denoising_aware_map(st, g, 100, rng=1))
    with pytest.raises(InputError, match="`budget` must be a whole number of samples >= 0"):
        denoising_aware_map(st, g, 100.5, rng=1)


def test_counts_from_density_near_the_float64_maximum():
    """A density whose sum overflows (entries near 1.8e308, each finite) raised the
    kernel's ZeroDivisionError; the map is scale-free, so it equals the rescaled one."""
    d = np.array([[1e308, 1e308], [1e300, 0.0]])
    np.testing.assert_array_equal(sampling.counts_from_density(d, 101, rng=3),
                                  sampling.counts_from_density(d / 1e308, 101, rng=3))


def test_gaussian_wider_than_the_image():
    """The kernel was built and run at full length whatever the image: σ = 1e6 took 41 s
    on a 64×64 image and σ = 1e9 asked for a 45 GiB kernel (MemoryError).  Taps beyond the
    image only meet zero padding, so the result must equal the dense reference, the
    per-channel image mean in the limit, and the spread must keep the total."""
    x, v, _, _ = _inputs(11)
    got = filters.filter_bank(x, v, [2000.0])                 # 6000 taps a side > 4096
    want = filters.filter_bank_reference(x, v, [2000.0])
    np.testing.assert_allclose(got[0], want[0], rtol=1e-12)
    np.testing.assert_allclose(got[1], want[1], rtol=1e-12)
    flat = filters.gaussian_filter(x, 1e9)
    np.testing.assert_allclose(flat, np.broadcast_to(x.mean(axis=(0, 1)), x.shape), rtol=1e-12)
    assert filters.gaussian_spread(v, 1e9).sum() == pytest.approx(v.sum(), rel=1e-12)


def test_cut_gaussian_equals_the_full_one_where_its_taps_reach(monkeypatch):
    """The cut kernel of fdd1b65 must be exact where taps reach the image, not only in the
    near-flat limit (σ = 2000 on 7×9 pixels varies its weights by 1e-5): with the cut
    lowered to 2 taps, σ = 4 (12 taps a side, cut to 8 on this image) must give the dense
    reference's values and variances, the uncut filter and spread, and keep the spread
    the adjoint of the filter."""
    x, v, _, _ = _inputs(20)
    for s in (0.5, 4.0, 4096 / 3):           # up to 4096 taps a side: the kernel, bit for bit
        np.testing.assert_array_equal(filters._taps(s, 3.0, max(H, W)),
                                      filters.gaussian_kernel_1d(s))
    sig = [0.0, 4.0, 6.5]
    full = (filters.filter_bank(x, v, sig), filters.gaussian_filter(x, 4.0),
            filters.gaussian_spread(v, 4.0))
    monkeypatch.setattr(filters, "_MAX_FULL_RADIUS", 2)
    assert len(filters._taps(4.0, 3.0, max(H, W))) == 2 * (max(H, W) - 1) + 1   # cut
    got = filters.filter_bank(x, v, sig)
    want = filters.filter_bank_reference(x, v, sig)
    for g, w, f in zip(got, want, full[0]):
        np.testing.assert_allclose(g, w, rtol=1e-12)
        np.testing.assert_allclose(g, f, rtol=1e-12)
    np.testing.assert_allclose(filters.gaussian_filter(x, 4.0), full[1], rtol=1e-12)
    spread = filters.gaussian_spread(v, 4.0)
    np.testing.assert_allclose(spread, full[2], rtol=1e-12)
    assert np.sum(spread * x) == pytest.approx(np.sum(v * filters.gaussian_filter(x, 4.0)),
                                               rel=1e-12)


def _gem_calls_at(sig, x, v, n):
    """Every GEM path that builds a kernel of the scales ``sig``: the selection (both
    bias modes: pair covariances, stopping-map filters and their centre taps), the
    difference variances, the post-processing alone and the exposed filter."""
    pooled = gem.select(x, v, sigmas=sig)
    paper = gem.select(x, v, sigmas=sig, bias="paper", final=False, n=n)
    return {"pooled": pooled, "paper": paper,
            "recon": gem.reconstruct(x, v, sigmas=sig, bias="paper", n=n),
            "dv": gem.difference_variance(v, sig),
            "post": gem.postprocess_stop_maps(paper["stop_raw"], sig, final=True),
            "sf": gem.SelectedFilter(pooled["scales"], sig)(v)}


def test_gem_with_absurd_scales_stays_small():
    """F10: only the bank's filter cut kernels longer than the image; the kernel moments,
    the stopping-map filters' centre taps, the pair covariances and the difference
    variances built the whole kernel, so gem.reconstruct(sigmas=(0, 1, 1e8)) on 64×64
    ran 68 s into a MemoryError (13.7 GiB resident) and σ = 1e6 allocated ~275 MiB
    here (137 MiB in kernel_moment2 alone).  Now a few MiB whatever σ."""
    x, v, n, _ = _inputs(12)
    _gem_calls_at([0.0, 1.0, 3.0], x, v, n)              # compile outside the measurement
    for big in (1e6, 1e8, 1e150):
        sig = [0.0, 1.0, big]
        out, peak = traced_peak(lambda: (_gem_calls_at(sig, x, v, n),
                                         filters.kernel_moment2(big))[0])
        assert peak < 4 << 20, (big, peak)
        for key in ("recon", "dv", "sf"):
            assert np.all(np.isfinite(out[key])), key
    with pytest.raises(InputError, match=r"`sigmas` must give finite, strictly increasing "
                                         r"kernel second moments.*1e\+300"):
        gem.reconstruct(x, v, sigmas=[0.0, 1.0, 1e300])   # r² = inf: was a NaN bias factor


def test_gem_scales_that_are_the_pixel_filter_are_named():
    """σ = 0.02 (exp(−1/(2σ²)) underflows: the pixel filter again, r² = 0) was refused as
    "`r2_coarse` must exceed `r2_fine` >= 0; got array([0. , 0.99...]) and array([0., 0.])",
    two arrays the caller never passed; σ = 0.03 (r² ~ 1e-240) works."""
    x, v, _, _ = _inputs(18)
    with pytest.raises(InputError, match=r"^`sigmas` must give finite, strictly increasing "
                                         r"kernel second moments .*got sigmas \[0.0, 0.02, 1.0\]"):
        gem.reconstruct(x, v, sigmas=(0, 0.02, 1))
    assert np.isfinite(gem.reconstruct(x, v, sigmas=(0, 0.03, 1))).all()


def test_gem_on_cut_kernels_equals_gem_on_whole_ones(monkeypatch):
    """Every GEM kernel comes from filters._taps, cut where it cannot reach the image:
    with the cut lowered to 2 taps (σ = 4 and 6.5 on 7×9 pixels are cut to 8 a side, the
    map filters of 2σ too), selection, stopping maps, estimated MSE, difference
    variances, post-processing and the exposed filter must be those of the whole
    kernels: the cut kernel's centre tap and border scales must go together."""
    x, v, n, _ = _inputs(21)
    sig = [0.0, 1.0, 4.0, 6.5]
    full = _gem_calls_at(sig, x, v, n)
    monkeypatch.setattr(filters, "_MAX_FULL_RADIUS", 2)
    assert len(filters._taps(4.0, 3.0, max(H, W))) == 2 * (max(H, W) - 1) + 1   # cut
    cut = _gem_calls_at(sig, x, v, n)
    for mode in ("pooled", "paper"):
        for key in ("scales", "stop_raw", "stop"):
            np.testing.assert_array_equal(cut[mode][key], full[mode][key], err_msg=key)
        for key in ("image", "values", "variances", "est_mse", "r2"):
            np.testing.assert_allclose(cut[mode][key], full[mode][key], rtol=1e-12, err_msg=key)
    np.testing.assert_array_equal(cut["post"], full["post"])
    for key in ("recon", "dv", "sf"):
        np.testing.assert_allclose(cut[key], full[key], rtol=1e-12, err_msg=key)
    np.testing.assert_allclose(cut["dv"], gem._difference_variance_reference(v, sig), rtol=1e-12)
    info = gem.select(x, v, sigmas=sig, final=False, n=n)
    np.testing.assert_array_equal(
        gem.postprocess_stop_maps(info["stop_raw"], sig, final=False),
        gem._postprocess_reference(info["stop_raw"], sig, False, 3.0))
    np.testing.assert_allclose(cut["sf"], gem.SelectedFilter(full["pooled"]["scales"], sig)
                               .reference(v), rtol=1e-12)


def test_gem_map_scale_that_overflows_is_named():
    """map_scale · σ beyond float64 was refused as "`sigma` must be a finite number >= 0;
    got inf." (a parameter the caller never passed)."""
    x, v, n, _ = _inputs(13)
    for call in (lambda: gem.reconstruct(x, v, map_scale=1e308),
                 lambda: gem.select(x, v, final=False, map_scale=1e307, sigmas=[0.0, 1.0, 100.0]),
                 lambda: gem.postprocess_stop_maps(np.ones((2, H, W)), [0.0, 1.0, 1e300],
                                                   final=True, map_scale=1e10)):
        with pytest.raises(InputError, match=r"^`map_scale` times the coarsest scale must be "
                                             r"a finite σ .*; got map_scale"):
            call()


def test_gem_sampler_rounds_beyond_the_budget():
    """Rounds past the budget hand out nothing, but the kernel looped over them all:
    rounds=10**15 would run for days and 2**70 was numba's TypingError ('Int value is too
    large'); batch=2**63 its SystemError.  Rounds now stop at the budget (the same counts)
    and batch is a whole number up to 2**53, as the budget."""
    x, v, n, _ = _inputs(14)
    seen = []
    real = gem._allocate_rounds_fast

    def spy(rel, nn, budget, batch, rounds):
        seen.append(rounds)
        assert rounds <= budget, "the kernel would loop over every round"
        return real(rel, nn, budget, batch, rounds)

    import unittest.mock
    with unittest.mock.patch.object(gem, "_allocate_rounds_fast", spy):
        big = gem.sampling_map(x, v, n, 50, rounds=10 ** 15, rng=4)
    assert seen == [50]
    np.testing.assert_array_equal(big, gem.sampling_map(x, v, n, 50, rounds=50, rng=4))
    np.testing.assert_array_equal(gem.sampling_map(x, v, n, 50, rounds=2 ** 70, rng=4), big)
    assert gem.sampling_map(x, v, n, 0, rounds=2 ** 70, rng=4).sum() == 0
    with pytest.raises(InputError, match=r"`batch` must be a whole number <= 9007199254740992; "
                                         r"got 9223372036854775808"):
        gem.sampling_map(x, v, n, 50, batch=2 ** 63, rng=4)
    assert gem.sampling_map(x, v, n, 50, batch=2 ** 53, rng=4).sum() == 50


def _bank3(seed=15):
    x, v, _, _ = _inputs(seed)
    sig = [0.0, 1.0, 2.0]
    vals, vars_ = filters.filter_bank(x, v, sig)
    return x, v, vals, vars_, [filters.kernel_moment2(s) for s in sig]


@pytest.mark.parametrize("call,match", [
    # estimate_mse read r2 unchecked: two moments for three scales had the kernel read a
    # bias factor past the array's end (whatever memory held), four were silently cut
    (lambda x, v, a, b, r: gem.estimate_mse(a, b, r[:2], np.zeros((H, W), int)),
     r"`r2` must hold one second moment per scale, shape \(3,\)"),
    (lambda x, v, a, b, r: gem.estimate_mse(a, b, r + [9.0], np.zeros((H, W), int)),
     r"`r2` must hold one second moment per scale"),
    # fractional and boolean scale indices were cast to intp (0.5 -> 0)
    (lambda x, v, a, b, r: gem.estimate_mse(a, b, r, np.full((H, W), 0.5)),
     r"`scales` must be an \(H, W\) integer array"),
    (lambda x, v, a, b, r: gem.estimate_mse(a, b, r, np.ones((H, W), bool)),
     r"`scales` must be an \(H, W\) integer array"),
    # NaN values came out as a NaN MSE
    (lambda x, v, a, b, r: gem.estimate_mse(a * np.nan, b, r, np.ones((H, W), int)),
     r"`values` holds \d+ NaN"),
    # a NaN weight made every decision 'go on', a negative one turned the bias around
    (lambda x, v, a, b, r: gem.selector(a, b, r, weight=np.nan), r"`weight` holds 1 NaN"),
    (lambda x, v, a, b, r: gem.selector(a, b, r, weight=-1.0), r"`weight` must be >= 0"),
    (lambda x, v, a, b, r: gem.selector(a, np.inf * b, r), r"`variances` holds 0 NaN"),
    (lambda x, v, a, b, r: gem.pooled_selector(a, b, np.full((2, H, W), np.nan), r),
     r"`diff_variances` holds"),
    # bias_factor(0, inf) warned and gave NaN; bias_factor(nan, 1) NaN quietly
    (lambda x, v, a, b, r: gem.bias_factor(0.0, np.inf), r"`r2_coarse` must exceed .*finite"),
    (lambda x, v, a, b, r: gem.bias_factor(np.nan, 1.0), r"`r2_coarse` must exceed .*finite"),
    # a NaN stopping map was a 'go on' everywhere; a string NumPy's ValueError
    (lambda x, v, a, b, r: gem.postprocess_stop_maps(np.full((1, H, W), np.nan), [0, 1],
                                                     final=True), r"`stop` holds"),
    (lambda x, v, a, b, r: gem.postprocess_stop_maps("x", [0, 1], final=True),
     r"`stop` must be a real numeric array"),
    # sigmas that are not numbers: NumPy's ValueError / TypeError, naming nothing
    (lambda x, v, a, b, r: filters.filter_bank(x, v, "abc"), r"`sigmas` must be a real numeric"),
    (lambda x, v, a, b, r: filters.filter_bank(x, v, [[0, 1], [2]]), r"`sigmas` must be an array"),
    (lambda x, v, a, b, r: gem.reconstruct(x, v, sigmas=[0, 1 + 2j]), r"`sigmas` must be a real"),
    (lambda x, v, a, b, r: gem.difference_variance(v, {0: 1}), r"`sigmas` must be a real"),
    # σ = 0 skipped the truncate check (a negative truncate was accepted there only)
    (lambda x, v, a, b, r: filters.gaussian_filter(x, 0.0, truncate=-1), r"`truncate` must be"),
    (lambda x, v, a, b, r: filters.gaussian_spread(v, 0.0, truncate=0), r"`truncate` must be"),
], ids=["r2-short", "r2-long", "scales-float", "scales-bool", "values-nan", "weight-nan",
        "weight-negative", "variances-inf", "diff-variances-nan", "bias-factor-inf",
        "bias-factor-nan", "stop-nan", "stop-str", "bank-sigmas-str", "bank-sigmas-ragged",
        "gem-sigmas-complex", "dv-sigmas-dict", "filter-truncate", "spread-truncate"])
def test_gem_helpers_refuse_what_they_misread(call, match):
    with pytest.raises(InputError, match=match):
        call(*_bank3())


def test_estimate_mse_of_an_empty_image():
    """An image of 0 rows raised NumPy's 'zero-size array to reduction operation minimum',
    one of 0 channels ZeroDivisionError (in estimate_mse and a SelectedFilter's call)."""
    x, v, a, b, r = _bank3()
    out = gem.estimate_mse(a[:, :0], b[:, :0], r, np.zeros((0, W), int))
    assert out.shape == (0, W, C)
    out = gem.estimate_mse(a[..., :0], b[..., :0], r, np.zeros((H, W), int))
    assert out.shape == (H, W, 0)
    for k in (0, 1):
        f = gem.SelectedFilter(np.full((H, W), k), [0.0, 1.0])
        assert f(x[..., :0]).shape == (H, W, 0)


@pytest.mark.parametrize("kwargs,match", [
    (dict(eps="0.1"), r"`eps` must be a finite number > 0; got '0.1'"),       # was read
    (dict(eps=True), r"`eps` must be a finite number > 0; got True"),         # was 1.0
    (dict(eps=[0.1, 0.2]), r"`eps` must be a finite number > 0"),            # TypeError
    (dict(var_prior="2"), r"`var_prior` must be a finite number >= 0"),       # was read
    (dict(var_prior_sigma=np.array([1.0, 2.0])), r"`var_prior_sigma` must be a finite"),
])
def test_gem_sampler_numbers_are_numbers(kwargs, match):
    """sampling_map read eps, var_prior and var_prior_sigma with float(): a string was
    parsed, True was 1 and a list or a 2-element array raised TypeError."""
    x, v, n, _ = _inputs(16)
    with pytest.raises(InputError, match=match):
        gem.sampling_map(x, v, n, 100, rng=0, **kwargs)
    np.testing.assert_array_equal(gem.sampling_map(x, v, n, 100, rng=0, eps=np.array(1e-3)),
                                  gem.sampling_map(x, v, n, 100, rng=0))


def test_huge_truncate_drops_only_zero_taps():
    """Past 4096 taps a side the kernel also loses its taps beyond 40σ, exactly 0 in
    float64 (σ = 0.1 with truncate = 1e5: 10000 taps a side, 4 of them non-zero): the bank
    must be the dense reference's (built from the whole 20001-tap kernel) and the one of a
    cut at 40σ, and GEM's second moment the whole kernel's."""
    x, v, _, _ = _inputs(17)
    assert len(filters._taps(0.1, 1e5, max(H, W))) == 9
    got = filters.filter_bank(x, v, [0.0, 0.1, 0.7], truncate=1e5)
    want = filters.filter_bank_reference(x, v, [0.0, 0.1, 0.7], truncate=1e5)
    for g, w, c in zip(got, want, filters.filter_bank(x, v, [0.0, 0.1, 0.7], truncate=40.0)):
        np.testing.assert_allclose(g, w, rtol=1e-12)
        np.testing.assert_array_equal(g, c)
    w = filters.gaussian_kernel_1d(0.7, truncate=1e4)
    k = np.arange(len(w)) - len(w) // 2
    assert filters.kernel_moment2(0.7, truncate=1e4) == pytest.approx(float(np.sum(w * k * k)),
                                                                      rel=1e-15)


def test_all_metrics_takes_one_name_as_a_string():
    """``include="relmse"`` was iterated letter by letter: "unknown metric(s) ['r', 'e',
    'l', 'm', 's', 'e']"."""
    from statmc.metrics import all_metrics, relmse
    x, _, _, _ = _inputs(12)
    assert all_metrics(x, 1.1 * x, include="relmse") == {"relmse": relmse(x, 1.1 * x)}


def test_images_beyond_float32_are_refused_before_the_denoiser():
    """Denoisers are called on float32 images: an x of 1e150 became Inf on the way and was
    reported (after a RuntimeWarning) as "`color` holds 240 Inf values; replace them",
    about an array the caller never passed."""
    x, v, _, _ = _inputs(13)
    g = denoisers.gaussian(1.0)
    for call in (lambda: sure.mc_sure(g, 1e150 * x, 1e300 * v, rng=1),
                 lambda: sure.output_variance(g, 1e150 * x, 1e300 * v, rng=1)):
        with pytest.raises(InputError, match=r"`x` holds values up to .* beyond float32's range"):
            call()


def test_denoiser_objects_where_kernels_are_needed_are_named():
    """sure.sure(gem_denoiser, ...) and apply_kernels(gaussian_denoiser, ...) said
    "`kernels` must be a numeric array; got dtype object"; now they name what was given
    and what to pass instead."""
    x, v, _, _ = _inputs(14)
    with pytest.raises(InputError, match="got GEMDenoiser. For any other denoiser use mc_sure"):
        sure.sure(denoisers.gem(v), x, v)
    with pytest.raises(InputError, match=r"got GaussianDenoiser \(for a kernel denoiser pass "
                                         r"its `kernels\(shape\)`\)"):
        analytic.apply_kernels(denoisers.gaussian(1.0), x)
    with pytest.raises(InputError, match=r"got GaussianDenoiser \(for a kernel denoiser"):
        combine.filter_covariance(denoisers.gaussian(1.0), v, size=5)


def test_from_sums_refuses_sums_without_samples():
    """Nonzero sums where ``n = 0`` were taken as a mean of ``sum_x / 1`` and an M2 > 0: an
    empty pixel with a value and a variance."""
    x, v, _, _ = _inputs(15)
    n = np.full((H, W), 4)
    n[2, 3] = 0
    with pytest.raises(InputError, match=r"must be 0 where `n` = 0 .* in 1 pixels"):
        PixelStats.from_sums(n, 4 * x, 4 * (v + x * x))
    s1, s2 = 4 * x, 4 * (v + x * x)
    s1[2, 3] = s2[2, 3] = 0.0
    assert PixelStats.from_sums(n, s1, s2).n[2, 3] == 0


def test_adaptive_render_names_a_wrong_renderer():
    """A scene name instead of a renderer, or a render() that returns an array, were
    AttributeErrors from deep inside ('str' object has no attribute 'height'; 'ndarray'
    object has no attribute 'mean_var' after the first pass)."""
    from statmc.adaptive import adaptive_render

    class ArrayRenderer:
        height, width = 4, 5

        def render(self, counts, *, seed=0, features=True):
            return np.zeros((4, 5, 3))

    with pytest.raises(InputError, match="got str .*make_renderer"):
        adaptive_render("cornell-box", 8)
    with pytest.raises(InputError, match="`renderer.render` must return PixelStats of 4x5 "
                                         "pixels; got ndarray"):
        adaptive_render(ArrayRenderer(), 8)


@pytest.mark.parametrize("name", ["uniform", "gem", "expected-error"])
def test_samplers_name_an_array_passed_as_stats(name):
    """An image passed where PixelStats are expected failed as "'ndarray' object has no
    attribute 'n'" or, for the expected-error sampler, "'builtin_function_or_method' object
    has no attribute 'shape'" (an ndarray's ``mean`` is a method)."""
    from statmc.adaptive import get_sampler
    x, _, _, _ = _inputs(16)
    with pytest.raises(InputError, match="`stats` must be a statmc.PixelStats; got ndarray"):
        get_sampler(name)(x, 100, np.random.default_rng(1))


@pytest.mark.parametrize("sigma", ["1", None, True])
def test_filter_sigma_must_be_a_number(sigma):
    """sigma="1" was parsed silently (denoisers.get("gaussian", sigma="1") worked), True
    read as 1 and None was float()'s TypeError; a 0-d array still works."""
    x, _, _, _ = _inputs(17)
    with pytest.raises(InputError, match="`sigma` must be a finite number >= 0"):
        filters.gaussian_filter(x, sigma)
    np.testing.assert_array_equal(filters.gaussian_filter(x, np.array(2.0)),
                                  filters.gaussian_filter(x, 2.0))


def test_zero_dimensional_arrays_are_numbers():
    """A 0-d array (``np.array(2.0)``, e.g. from ``np.asarray(value)``) was refused as
    "must be a finite number; got array(2.)" by every as_number / as_int / as_whole check."""
    x, v, n, _ = _inputs(18)
    y = denoisers.gaussian(1.0)(x)
    alpha = np.full(x.shape, 0.5)
    np.testing.assert_array_equal(
        progressive.confidence_gate(x, y, v, alpha, sigma_s=np.array(2.0)),
        progressive.confidence_gate(x, y, v, alpha, sigma_s=2.0))
    np.testing.assert_array_equal(gem.sampling_map(x, v, n, np.array(300), rng=1),
                                  gem.sampling_map(x, v, n, 300, rng=1))
    np.testing.assert_array_equal(sure.mc_sure(denoisers.gaussian(1.0), x, v, k=np.array(2), rng=1),
                                  sure.mc_sure(denoisers.gaussian(1.0), x, v, k=2, rng=1))
    from statmc.da_sampling import denoising_aware_density, tonemap
    np.testing.assert_array_equal(tonemap(x, exposure=np.array(2.0)), tonemap(x, exposure=2.0))
    np.testing.assert_array_equal(
        progressive.confidence_gate(x, y, v, alpha, window=np.array(5), sigma_s=2.0),
        progressive.confidence_gate(x, y, v, alpha, window=5, sigma_s=2.0))
    stats = PixelStats.from_mean_var(x, v * n[..., None], n)
    gauss = denoisers.gaussian(1.0)
    np.testing.assert_array_equal(
        denoising_aware_density(stats, gauss, eps=np.array(1e-3), k=np.array(2), rng=1),
        denoising_aware_density(stats, gauss, eps=1e-3, k=2, rng=1))


def test_gem_gamma_as_zero_dimensional_array():
    """The gamma type check (64937b9) refused a 0-d array (``isinstance(np.array(0.2),
    numbers.Real)`` is False) that float(gamma) had read as 0.2 before: '`gamma` must be in
    (0, 0.5263) ...; got array(0.2)'."""
    x, v, _, _ = _inputs(19)
    assert gem.error_rate_weight(np.array(0.2)) == gem.error_rate_weight(0.2)
    np.testing.assert_array_equal(gem.reconstruct(x, v, gamma=np.array(0.3)),
                                  gem.reconstruct(x, v, gamma=0.3))


@pytest.mark.parametrize("layout", ["big-endian", "strided", "reversed", "fortran", "readonly"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_confidence_gate_layouts_reuse_the_compiled_kernels(layout, dtype, monkeypatch):
    """Any input of :func:`progressive.confidence_gate` (x, y, mean_var, alpha) in another
    layout reaches the gate's kernels with the argument types of the contiguous call: a
    read-only one compiled ``_prepare`` and ``_gate_bands`` anew (8-15 s on a cold cache)
    for the same numbers."""
    from statmc import _progressive_kernels as pk
    from numba.core.registry import CPUDispatcher

    seen = []
    for kname, disp in vars(pk).items():
        if isinstance(disp, CPUDispatcher) and kname in ("_prepare", "_gate_bands"):
            def spy(*a, _d=disp, _n=kname):
                seen.append((_n,) + tuple(_d.typeof_pyval(q) for q in a))
                return _d(*a)
            monkeypatch.setattr(pk, kname, spy)
    rng = np.random.default_rng(3)
    x = rng.random((9, 7, 3)).astype(dtype)
    args = [x, (x + 0.1 * rng.standard_normal(x.shape)).astype(dtype),
            np.full(x.shape, 1e-3, dtype), rng.random(x.shape).astype(dtype)]
    expected = progressive.confidence_gate(*args)
    contiguous = set(seen)
    assert {s[0] for s in contiguous} == {"_prepare", "_gate_bands"}
    for i, a in enumerate(args):
        seen.clear()
        got = progressive.confidence_gate(*args[:i], _layouts(a)[layout], *args[i + 1:])
        np.testing.assert_array_equal(got, expected)
        assert got.dtype == expected.dtype
        new = set(seen) - contiguous
        assert not new, f"argument {i} {layout}: new kernel argument types {new}"


def test_neighbour_products_of_slab_views_reuse_the_compiled_kernel():
    """``combine``'s denoiser moments hand ``add_neighbour_products_sum`` strided slabs
    ``jv[:, s0:s1]`` (layout ``'A'``) beside stacked contiguous ones, and each mix of
    layouts compiled the parallel kernel once more (1.5-3 s on a cold cache); now the
    inputs reach it in one type, with the same sums to the bit."""
    from statmc import _stencil_kernels as sk

    kernel = getattr(sk, "_add_neighbour_products_sum", sk.add_neighbour_products_sum)
    rng = np.random.default_rng(5)
    full = rng.standard_normal((3, 14, 6, 3))
    use = np.array([True, False, True])
    R = 1
    c = np.ascontiguousarray(full[:, 2:12])
    ref = np.zeros((10, 6, 3, 3, 3))
    sk.add_neighbour_products_sum(ref, c, c, R, use)
    n_sigs = len(kernel.signatures)
    slab = full[:, 2:12]
    frozen = c.copy()
    frozen.flags.writeable = False
    for a, b in [(slab, slab), (c, slab), (frozen, c), (c.astype(">f8"), slab)]:
        got = np.zeros_like(ref)
        sk.add_neighbour_products_sum(got, a, b, R, use)
        np.testing.assert_array_equal(got, ref)
        assert len(kernel.signatures) == n_sigs, kernel.signatures[n_sigs:]


@pytest.mark.parametrize("scene, why", [
    ("nonexistent.xml", "which is neither a built-in scene nor an existing file"),
    ("toy:nope", "which is not one of the toy scenes"), ("", "an empty name"),
    (3, "of type int")])
def test_make_renderer_names_its_scene_parameter_and_lists_the_scenes(scene, why):
    # before: "scene 'nonexistent.xml' is neither a file nor a built-in scene (...)", "unknown
    # toy scene 'toy:nope'; expected one of ...": no parameter named, and the first did not
    # say a file was expected
    from statmc.renderers import list_scenes, make_renderer
    known = ", ".join(sorted(list_scenes()))
    with pytest.raises(InputError) as e:
        make_renderer(scene, width=8, height=8)
    assert str(e.value) == (f"`scene` must be a built-in scene name ({known}) or the path of an "
                            f"existing Mitsuba XML file; got {scene!r}, {why}.")


def test_make_renderer_takes_a_path_object(tmp_path):
    # before: "`scene` must be a scene name or a Mitsuba XML path; got PosixPath(...)" for a
    # pathlib.Path, which MitsubaRenderer itself takes
    import pathlib
    from statmc.renderers import make_renderer
    with pytest.raises(InputError, match=r"got 'nope.xml', which is neither"):
        make_renderer(pathlib.Path("nope.xml"))


def test_pipeline_messages_name_the_library_parameters_not_cli_flags():
    # before: render_bins(r, 6, 4) said "--spp 6 must be a multiple of --bins 4 (...)" and
    # render_with_sampler(counts=..., sampler="gem") "... cannot be combined with --sampler
    # gem": flags of the command line, which a library caller never typed
    from statmc.pipeline import render_bins, render_with_sampler
    from statmc.toy import ToyRenderer
    r = ToyRenderer("edges", width=16, height=12)
    with pytest.raises(InputError) as e:
        render_bins(r, 6, 4)
    assert str(e.value) == ("`spp` must be a multiple of `bins` (every bin gets the same number "
                            "of samples); got spp=6, bins=4.")
    with pytest.raises(InputError) as e:
        render_with_sampler(r, 8, sampler="gem", counts=np.full((12, 16), 8))
    assert str(e.value).startswith("`counts` (a sample map) fixes the sample counts, which an "
                                   "adaptive `sampler` chooses; got counts with sampler='gem'")
    assert "--" not in str(e.value)


@pytest.mark.parametrize("call, needle", [
    (lambda x: metrics.relmse(x, x, "a"),
     r"`eps` must be a finite number >= 0; got 'a'"),
    (lambda x: metrics.smape(x, x, None),
     r"`eps` must be a finite number >= 0; got None"),
    (lambda x: metrics.logloss(x, x, sigma="a"),
     r"`sigma` must be a positive number of pixels; got 'a'"),
    (lambda x: metrics.one_minus_ssim(x, x, sigma=None),
     r"`sigma` must be a positive number of pixels; got None"),
    (lambda x: metrics.ssim_map(x, x, k1=np.nan),
     r"`k1` must be a constant >= 0 \(0.01 in Wang et al. 2004\); got nan"),
    (lambda x: metrics.ssim_map(x, x, k2="0.03"),
     r"`k2` must be a constant >= 0 .*; got '0.03'"),
    (lambda x: metrics.flip(x, x, ppd="67"),
     r"`ppd` must be a positive number of pixels per degree; got '67'"),
    (lambda x: metrics.mse(x, x, per_pixel="yes"),
     r"`per_pixel` must be True or False; got 'yes'"),
    (lambda x: metrics.flip(x, x, per_pixel=1),
     r"`per_pixel` must be True or False; got 1"),
    (lambda x: metrics.all_metrics(x, x, include=["psnr"]),
     r"`include` must name metrics from \['relmse', .*\]; got unknown \['psnr'\]"),
])
def test_metric_options_of_the_wrong_type_are_named(call, needle):
    # before: eps='a' was float()'s "ValueError: could not convert string to float", sigma='a'
    # numpy's "TypeError: ufunc 'isfinite' not supported", k1=nan "`x` and `ref` are too
    # large for SSIM ... whose square overflows" (about the images), per_pixel='yes' taken as
    # True, and an unknown metric named no parameter
    x, _, _, _ = _inputs(14)
    with pytest.raises(InputError, match=needle):
        call(x)


@pytest.mark.parametrize("where, needle", [
    ("mean", r"`mean` holds 1 NaN and 0 Inf values"),
    ("n", r"`n` holds 1 NaN and 0 Inf values"),
])
def test_from_mean_var_names_a_nan_where_it_is(where, needle):
    # before: a NaN in `mean` (or `n`) was reported as "`sample_var` must give statistics
    # within float64; got 1 pixels where M2 = sample_var · (n − 1) ... overflows"
    x, v, n, _ = _inputs(15)
    args = {"mean": x.copy(), "sample_var": v, "n": n.astype(float)}
    args[where][(1, 2) if where == "n" else (1, 2, 0)] = np.nan
    with pytest.raises(InputError, match=needle):
        PixelStats.from_mean_var(**args)


@pytest.mark.parametrize("flag, value", [("covariance", None), ("covariance", "no"),
                                         ("extra_output", 1)])
def test_denoising_aware_density_flags_must_be_booleans(flag, value):
    # before: covariance=None ran as False and covariance="no" as True, silently
    from statmc.da_sampling import denoising_aware_density
    x, v, n, _ = _inputs(16)
    stats = PixelStats.from_mean_var(x, v * n[..., None], n)
    with pytest.raises(InputError, match=rf"`{flag}` must be True or False; got {value!r}"):
        denoising_aware_density(stats, denoisers.gaussian(1.0), **{flag: value})


def test_mitsuba_render_refuses_2_to_the_31_samples_and_non_boolean_flags():
    # before: render(counts) with 2**40 samples per pixel (and no first_sample, whose sum
    # with counts had the 2**31 bound) was not refused and ran for hours; progress="no"
    # showed the progress bar and features="no" rendered the features
    pytest.importorskip("mitsuba")
    from statmc.mitsuba_backend import MitsubaRenderer
    r = MitsubaRenderer("cornell-box", width=4, height=3)
    for spp in (2 ** 31, 2 ** 40):
        with pytest.raises(InputError, match=rf"`counts` must stay below 2\*\*31 samples per "
                                             rf"pixel; got max {spp}\."):
            r.render(np.full((3, 4), spp))
    with pytest.raises(InputError, match=r"`first_sample \+ counts` must stay below 2\*\*31 "
                                         r"samples per pixel; got max 2147483648\."):
        r.render(np.full((3, 4), 2), first_sample=np.full((3, 4), 2 ** 31 - 2))
    for flag in ("progress", "features", "cross"):
        with pytest.raises(InputError, match=rf"`{flag}` must be True or False; got 'no'"):
            r.render(np.full((3, 4), 1), **{flag: "no"})
    with pytest.raises(InputError, match=r"`features` must be True or False; got None"):
        r.render_crn(2, features=None)


def _pipeline_case(name):
    from statmc import pipeline as pl
    from statmc.toy import ToyRenderer
    r = ToyRenderer("edges", width=8, height=6)
    s = r.render(np.full((6, 8), 4), seed=1)
    return {
        "stats-array": (lambda: pl.reconstruct_stats(s.mean),
                        r"`stats` must be a statmc.PixelStats; got ndarray"),
        "method": (lambda: pl.reconstruct_stats(s, "nope"), r"`method` must be one of \('none', "
                   r"'gem', .*\); got 'nope', an unknown reconstruction"),
        "gem_bias": (lambda: pl.reconstruct_stats(s, "gem", gem_bias="nope"),
                     r"`gem_bias` must be one of \('paper', 'pooled'\) or None \(pooled\); got "
                     r"'nope'"),
        "bin-method": (lambda: pl.reconstruct_bins([s, s], "nope"), r"`method` must be one of "
                       r"\('gem\+bins', 'oidn\+bins'\); got 'nope', an unknown bin"),
        "renderer": (lambda: pl.render_with_sampler(None, 8),
                     r"`renderer` must be a renderer .*; got NoneType"),
        "bins-renderer": (lambda: pl.render_bins(None, 8, 2),
                          r"`renderer` must be a renderer .*; got NoneType"),
        "sampler": (lambda: pl.render_with_sampler(r, 8, sampler="nope"), r"`sampler` must be one "
                    r"of \['denoising-aware', .*\]; got 'nope', an unknown sampler"),
        "unused-denoiser": (lambda: pl.render_with_sampler(r, 8, denoiser="oidn"),
                            r"`denoiser` is the denoiser of the 'denoising-aware' and "
                            r"'expected-error' samplers; sampler='uniform' does not use it"),
        "ee-denoiser": (lambda: pl.render_with_sampler(r, 8, sampler="expected-error",
                                                       denoiser="oidn"),
                        r"`denoiser` must be a kernel denoiser, 'gem' or 'gaussian' .*; got "
                        r"'oidn'"),
        "bins-None": (lambda: pl.merge_bins(None),
                      r"`bins` must be a list of at least 2 PixelStats; got NoneType"),
        "bins-items": (lambda: pl.merge_bins([s.mean, s]), r"`bins` must be a list of at least 2 "
                       r"PixelStats; got 2 item\(s\): ndarray, PixelStats"),
    }[name]


@pytest.mark.parametrize("case", ["stats-array", "method", "gem_bias", "bin-method", "renderer",
                                  "bins-renderer", "sampler", "unused-denoiser", "ee-denoiser",
                                  "bins-None", "bins-items"])
def test_pipeline_refuses_bad_input_by_parameter_name(case):
    # before: reconstruct_stats(ndarray) was "AttributeError: 'builtin_function_or_method'
    # object has no attribute 'astype'", a None renderer "'NoneType' object has no attribute
    # 'height'", merge_bins(None) "'NoneType' object is not iterable", gem_bias='nope' was
    # named `bias`, a denoiser given with sampler='uniform' was silently ignored, and unknown
    # names said "unknown reconstruction 'nope'; expected one of ..." (no parameter)
    call, needle = _pipeline_case(case)
    with pytest.raises(InputError, match=needle):
        call()


def test_mitsuba_renderer_words_a_missing_scene_as_make_renderer_does():
    # before: "`scene` 'nope.xml' is neither a built-in scene (...) nor an existing Mitsuba
    # XML file" — the one scene message not in the "must be ...; got ..." form
    pytest.importorskip("mitsuba")
    from statmc.mitsuba_backend import MitsubaRenderer
    with pytest.raises(InputError, match=r"^`scene` must be a built-in Mitsuba scene name "
                       r"\(cornell-box, glass-caustic, glossy-spheres, textured-dof\) or the path "
                       r"of an existing Mitsuba XML file; got 'nope.xml', which is neither\.$"):
        MitsubaRenderer("nope.xml")


# Every public function wrapped by _threads.serial_when_small, called with all of its
# array arguments by name (the wrapper once took its first argument by position only:
# "missing 1 required positional argument: 'first'").
def _by_name_calls():
    rng = np.random.default_rng(5)
    x = rng.random((12, 10, 3))
    v = np.full_like(x, 0.01)
    n = np.full(x.shape[:2], 4)
    return [
        ("gem.reconstruct", gem.reconstruct, (x, v), dict(mean=x, mean_var=v)),
        ("gem.select", gem.select, (x, v), dict(mean=x, mean_var=v)),
        ("gem.selected_filter", gem.selected_filter, (x, v), dict(mean=x, mean_var=v)),
        ("gem.sampling_map", gem.sampling_map, (x, v, n, 600),
         dict(mean=x, mean_var=v, n=n, budget=600)),
        ("filters.gaussian_filter", filters.gaussian_filter, (x, 1.5), dict(image=x, sigma=1.5)),
        ("filters.gaussian_spread", filters.gaussian_spread, (v, 1.5), dict(amount=v, sigma=1.5)),
        ("filters.filter_bank", filters.filter_bank, (x, v), dict(mean=x, mean_var=v)),
    ]


def _arrays_of(result):
    """The arrays of a result: itself, the items of a tuple, the values of a dict or of
    an object's attributes, in a fixed order."""
    if isinstance(result, np.ndarray):
        return [result]
    if isinstance(result, tuple):
        return [a for r in result for a in _arrays_of(r)]
    if isinstance(result, dict):
        return [a for k in sorted(result) for a in _arrays_of(result[k])]
    if hasattr(result, "__dict__"):
        return _arrays_of(vars(result))
    return [np.asarray(result)]


@pytest.mark.parametrize("name, func, args, kwargs", _by_name_calls(),
                         ids=[c[0] for c in _by_name_calls()])
def test_array_arguments_can_be_passed_by_name(name, func, args, kwargs):
    by_position = _arrays_of(func(*args))
    by_name = _arrays_of(func(**kwargs))
    assert len(by_name) == len(by_position) > 0
    for a, b in zip(by_position, by_name):
        np.testing.assert_array_equal(a, b)


def test_combination_messages_name_the_argument_given():
    """Found in session 15's QA: complex weights lost their imaginary part with only a
    ComplexWarning; ``combine_denoised`` called its image `x` (the parameter is `y`);
    ``var=None`` raised "'NoneType' object is not iterable"."""
    rng = np.random.default_rng(3)
    H, W, C, k = 6, 5, 3, 3
    y = rng.random((H, W, C))
    z = y + 0.01
    v = np.full((H, W, C), 0.01)
    w = np.full((H, W, k, k), 1.0 / k**2)
    with pytest.raises(InputError, match=r"`weights` must be a real numeric array; got dtype complex128"):
        combine.combine(y, z, w + 1j)
    with pytest.raises(InputError, match=r"`weights` must be a real numeric array"):
        combine.combine_bias_variance(w + 0j, v, v)
    blur = lambda c: c                                   # noqa: E731 - a stand-in denoiser
    with pytest.raises(InputError, match=r"`mean_var` must have the shape of `y` \(6, 5, 3\)"):
        combine.combine_denoised(y, v[:5], blur)
    with pytest.raises(InputError, match=r"`var` must be 'smooth', 'raw', 'max' or a sequence"):
        combine.combine_denoised(y, v, blur, var=None)


def test_ssim_with_zero_constants_is_the_universal_quality_index():
    """``k1 = k2 = 0`` (Wang and Bovik's universal quality index, 2002) is a valid call: for
    ``x = a · ref`` every window's index is ``(2a / (1 + a²))²`` (luminance and contrast-
    structure terms are each ``2a / (1 + a²)``); refused by 82f3544, restored in session 15.
    A window constant in both images is 0/0 there, and the message says so."""
    rng = np.random.default_rng(8)
    ref = rng.uniform(0.2, 1.0, (16, 18, 3))
    for a in (1.0, 2.0, 0.3):
        s = metrics.ssim_map(a * ref, ref, k1=0, k2=0)
        np.testing.assert_allclose(s, (2 * a / (1 + a * a)) ** 2, rtol=1e-9)
    with pytest.raises(InputError, match=r"SSIM with `k1` and `k2` = 0 is 0/0 in a window"):
        metrics.ssim_map(np.ones((8, 8, 1)), np.ones((8, 8, 1)), k1=0, k2=0)
    with pytest.raises(InputError, match=r"`k1` must be a constant >= 0"):
        metrics.ssim_map(ref, ref, k1=-0.01)


# ---------------------------------------------------------------- session 16, helper C
def _small(seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1, 1.0, (7, 9, 3))
    v = rng.uniform(1e-3, 1e-2, (7, 9, 3))
    n = rng.integers(2, 9, (7, 9)).astype(float)
    k = rng.uniform(0.0, 1.0, (7, 9, 5, 5))
    return x, v, n, k / k.sum(axis=(2, 3), keepdims=True)


@pytest.mark.parametrize("bad", ["no", None, 1, "False"])
def test_true_false_options_refuse_non_bools(bad):
    """``return_grad``, ``return_info`` (analytic) and ``extra_output`` (sure, combine),
    ``return_denoised`` (combine_bins) took any truthy value: ``"no"`` returned the tuple,
    None the bare value.  Now "`name` must be True or False", as the rest of the library."""
    x, v, n, k = _small()
    s = np.full(n.shape, 4.0)
    f = denoisers.gaussian(1.0)
    ys = np.stack([x, 1.05 * x])
    small = dict(size=5, probes=2, stencil=3, smooth=1, patch=1, rng=1)
    calls = {
        "return_grad": lambda: analytic.expected_kernel_loss(k, x, n, s, x, v, return_grad=bad),
        "return_info": lambda: analytic.optimal_sample_map(k, x, n, x, v, 100.0, max_iter=5,
                                                           return_info=bad),
        "extra_output": lambda: sure.sure(k, x, v, extra_output=bad),
        "extra_output ": lambda: sure.mc_sure(f, x, v, k=1, rng=1, extra_output=bad),
        "extra_output  ": lambda: sure.output_variance(f, x, v, k=1, rng=1, extra_output=bad),
        "extra_output   ": lambda: combine.denoiser_moments(f, x, v, size=3, probes=1, rng=1,
                                                            extra_output=bad),
        "extra_output    ": lambda: combine.combine_denoised(x, v, f, extra_output=bad, **small),
        "extra_output     ": lambda: combine.combine_bins(ys, v, f, extra_output=bad, **small),
        "return_denoised": lambda: combine.combine_bins(ys, v, f, return_denoised=bad, **small),
    }
    for name, call in calls.items():
        with pytest.raises(InputError, match=rf"`{name.strip()}` must be True or False"):
            call()


def test_mix_sigma_too_wide_for_the_image_is_an_input_error():
    """``combine_denoised(..., mix_sigma=1e30)`` raised SciPy's "Maximum allowed size
    exceeded" from the Gaussian pool (1e9 asked for 64 GB of taps); beyond 4x the image's
    longer side the pool is the whole image's, so such a σ is refused, naming
    ``mix="global"``.  The bound never refuses the default 16, even on tiny images."""
    x, v, _, _ = _small()
    f = denoisers.gaussian(1.0)
    ys = np.stack([x, 1.05 * x])
    small = dict(size=5, probes=2, stencil=3, smooth=1, patch=1, rng=1)
    for big in (1e30, 1e9, 37.0):
        with pytest.raises(InputError, match=r"`mix_sigma` must be at most 36 pixels for a "
                                             r"7x9 image.*mix='global'"):
            combine.combine_denoised(x, v, f, mix_sigma=big, **small)
        with pytest.raises(InputError, match=r"`mix_sigma` must be at most 36 pixels"):
            combine.combine_bins(ys, v, f, mix_sigma=big, **small)
    out = combine.combine_denoised(x, v, f, mix_sigma=36.0, **small)   # the limit itself
    assert np.isfinite(out).all()
    tiny = x[:2, :2]                                 # 4 x 2 = 8 < the default 16: allowed
    assert np.isfinite(combine.combine_denoised(tiny, v[:2, :2], f, **small)).all()


@pytest.mark.parametrize("mix", ["global", None])
def test_mix_sigma_bound_only_applies_to_the_local_mix(mix):
    """``mix_sigma`` only sizes the Gaussian of ``mix="local"``; with ``mix="global"`` or
    None it is not used, and a wide one was refused with "pass mix='global'" even when
    mix='global' was given.  The output equals the one with the default σ."""
    x, v, _, _ = _small()
    f = denoisers.gaussian(1.0)
    ys = np.stack([x, 1.05 * x])
    small = dict(size=5, probes=2, stencil=3, smooth=1, patch=1, rng=1, mix=mix)
    ref = combine.combine_denoised(x, v, f, **small)
    np.testing.assert_array_equal(combine.combine_denoised(x, v, f, mix_sigma=1e30, **small), ref)
    ref_b = combine.combine_bins(ys, v, f, **small)
    np.testing.assert_array_equal(combine.combine_bins(ys, v, f, mix_sigma=1e30, **small), ref_b)
    with pytest.raises(InputError, match="`mix_sigma`"):       # still a positive number
        combine.combine_denoised(x, v, f, mix_sigma=0.0, **small)


def test_combine_boosting_names_weights_when_they_are_not_finite():
    """A NaN weight inside the image made ``combine_boosting`` report "`kernels` holds 1
    NaN" (the name inside apply_kernels); ``combine`` names `weights`, and so does it now."""
    x, _, _, _ = _small()
    z = denoisers.gaussian(1.0)(x)
    w = combine.gaussian_weights(7, 9, 1, 5, 1.0).copy()
    w[3, 4, 0, 2, 2] = np.nan
    for func in (combine.combine, combine.combine_boosting):
        with pytest.raises(InputError, match=r"`weights` must be finite .* \(row 3, column 4\)"):
            func(x, z, w)
    w[3, 1] = 0.0         # and a zero W_c before it in the row: both counted, it named first
    for func in (combine.combine, combine.combine_boosting):
        with pytest.raises(InputError, match=r"2 pixel\(s\) fail, the first at \(row 3, column 1\) "
                                             r"with W_c = 0"):
            func(x, z, w)


@pytest.mark.parametrize("name,bad", [("sigma", "2"), ("sigma", True), ("prior_dof", "1"),
                                      ("prior_dof", True), ("sigma", np.nan)])
def test_pooled_sample_variance_refuses_strings_and_bools(name, bad):
    """``sigma="2"`` and ``prior_dof=True`` were read by ``float()`` as 2.0 and 1.0."""
    _, v, n, _ = _small()
    with pytest.raises(InputError, match=rf"`{name}` must be a finite number"):
        analytic.pooled_sample_variance(v, n, **{name: bad})


@pytest.mark.parametrize("feature,shape", [("albedo", (7, 9)), ("albedo", (7, 9, 1)),
                                           ("normal", (7, 9, 4)), ("depth", (7, 9, 3))])
def test_feature_buffers_of_the_wrong_channel_count_are_refused(feature, shape):
    """PixelStats took an ``(H, W)`` or ``(H, W, 1)`` albedo: ``nn.pixel_features`` then
    failed with NumPy's concatenate error, or built two planes too few for the network."""
    x, v, n, _ = _small()
    st = PixelStats.from_mean_var(x, v, n)
    with pytest.raises(InputError, match=rf"feature `{feature}` must be an \(H, W"):
        st.with_features(**{feature: np.ones(shape)})
    assert st.with_features(depth=np.ones((7, 9, 1))).depth.shape == (7, 9, 1)   # still fine


def _overflowing_calls():
    """(id, call, message pattern): finite input near the top of float64's range whose
    result left it.  Each returned Inf or NaN without an error before session 17."""
    x, v, n, k = _small(21)
    ys = np.stack([x, 0.5 * x, 0.8 * x])
    return [
        ("gamma_parameters", lambda: analytic.gamma_parameters(1e300 * x, v, 4.0),
         r"`x_g`, `var_g` and `s` must give a gamma shape .* within float64's range"),
        ("future_moments", lambda: analytic.future_moments(1e308 * x, n, 4.0, x, v),
         r"the future moments left float64's range .*`x_t` up to [\d.]+e\+307"),
        ("sample_future", lambda: analytic.sample_future(1e200 * x, n, 4.0, 1e200 * x, v, rng=1),
         r"the future render left float64's range .*`x_g` up to [\d.]+e\+\d+"),
        ("sample_future_unshared",
         lambda: analytic.sample_future(x, n, 4.0, 1e200 * x, v, rng=1, shared_stream=False),
         r"`x_g`, `var_g` and `s` must give a gamma shape s·x_g²/var_g below 1\.8e308"),
        ("kernel_bias_variance", lambda: analytic.kernel_bias_variance(k * 1e160, x, n, 4.0, x, v),
         r"the bias and variance left float64's range .*`kernels` up to"),
        ("expected_kernel_loss", lambda: analytic.expected_kernel_loss(k, 1e200 * x, n, 4.0, x, v),
         r"the expected MSE left float64's range .*`x_t` up to [\d.]+e\+\d+.*expected squared errors"),
        ("expected_kernel_loss_grad",
         lambda: analytic.expected_kernel_loss(k, x, n, 4.0, 1e160 * x, v, return_grad=True),
         r"the expected MSE or its gradient left float64's range"),
        ("expected_kernel_loss_mrse",
         lambda: analytic.expected_kernel_loss(k, 1e200 * x, n, 4.0, 1e200 * x, v, loss="mrse"),
         r"the expected MRSE left float64's range .*for loss='mrse' also x_g² \+ eps"),
        ("optimal_sample_map", lambda: analytic.optimal_sample_map(k, x, n, 1e200 * x, v, 100),
         r"the expected MSE at uniform sampling left float64's range .*`x_g` up to [\d.]+e\+\d+"),
        ("sure", lambda: sure.sure(k, 1e200 * x, v),
         r"the SURE map left float64's range .*`x` up to [\d.]+e\+\d+.*expected the squared residuals"),
        ("filter_covariance", lambda: combine.filter_covariance(k * 1e160, v),
         r"the covariance stencil left float64's range .*`kernels` up to"),
        ("buffer_moments", lambda: combine.buffer_moments(1e200 * ys, ys, size=3),
         r"the moment var_y left float64's range .*`ys` up to [\d.]+e\+\d+"),
        ("buffer_moments_z", lambda: combine.buffer_moments(ys, -1e160 * ys, size=3),
         r"the moment cov_z left float64's range .*`zs` up to [\d.]+e\+1[56]\d"),
    ]


@pytest.mark.parametrize("call,match", [c[1:] for c in _overflowing_calls()],
                         ids=[c[0] for c in _overflowing_calls()])
def test_results_beyond_float64_are_refused_not_returned_as_inf(call, match):
    """Session-16 fuzz (helper C): finite input near the top of the float range made these
    functions return Inf or NaN silently.  Now an InputError names the inputs with their
    largest magnitudes and the range expected."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # and quietly: no overflow RuntimeWarning
        with pytest.raises(InputError, match=match):
            call()


def test_pooled_sample_variance_names_sample_var_when_its_weighting_overflows():
    """With sample variances near 1e308, (n − 1)·sample_var overflowed and the Gaussian
    filter refused its own argument: "`image` holds 0 NaN and 95 Inf values", a name the
    caller never gave."""
    _, v, n, _ = _small(22)
    with pytest.raises(InputError, match=r"the weighted sample variance \(n − 1\)·sample_var "
                                         r"left float64's range .*`sample_var` up to 1e\+308"):
        analytic.pooled_sample_variance(1e308 * v / v.max(), n)


def test_denoiser_moments_near_the_top_of_float64_are_exactly_scaled_or_refused():
    """``denoiser_moments`` took its finite-difference step from the RMS of the ±σ probes,
    whose sum overflowed for ``mean_var`` near 1e307: the step was 0 and every stencil NaN,
    silently.  Now the RMS is exact (scaled mean), so the stencils at ``mean_var = 2**1020``
    are those at ``2**-8`` times exactly ``2**1028`` (every step of the computation is a
    power-of-two scaling), and stencils that do leave float64 are an InputError."""
    rng = np.random.default_rng(5)
    x = rng.random((16, 16, 3))
    den = denoisers.gaussian(1.0)

    def moments(mv):
        with warnings.catch_warnings():
            warnings.simplefilter("error")      # no overflow RuntimeWarning on the way
            return combine.denoiser_moments(den, x, np.full_like(x, mv), probes=4, rng=3)

    z0, cz0, cyz0 = moments(2.0 ** -8)
    z1, cz1, cyz1 = moments(2.0 ** 1020)
    assert np.array_equal(z0, z1)
    assert np.array_equal(np.ldexp(cz0, 1028), cz1) and np.isfinite(cz1).all()
    assert np.array_equal(np.ldexp(cyz0, 1028), cyz1)
    with pytest.raises(InputError, match=r"the stencil cov_.* left float64's range .*"
                                         r"`mean_var` up to 1e\+308"):
        moments(1e308)


def test_buffer_moments_of_large_but_representable_bins_are_exactly_scaled():
    """95015d6 refused bins above VALUE_LIMIT (1e140), although ce3409f returned their
    moments finite up to about 1e154.  The moments are now checked, not the inputs: bins
    scaled by 2**480 (about 3e144) give the moments times exactly 2**960."""
    rng = np.random.default_rng(8)
    ys, zs = rng.random((4, 9, 10, 3)), rng.random((4, 9, 10, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        small = combine.buffer_moments(ys, zs, size=3)
        big = combine.buffer_moments(np.ldexp(ys, 480), np.ldexp(zs, 480), size=3)
    for a, b in zip(small, big):
        assert np.isfinite(b).all() and np.array_equal(np.ldexp(a, 960), b)
