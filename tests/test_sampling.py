"""Integer counts from a sampling map: exact budget, unbiased rounding, bad input."""

import numpy as np
import pytest
from hypothesis import example, given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats as sps

from statmc import InputError
from statmc.sampling import counts_from_density


@settings(max_examples=80, deadline=None)
@given(d=arrays(np.float64, st.tuples(st.integers(1, 9), st.integers(1, 9)),
                elements=st.floats(0, 1e6, allow_nan=False)),
       budget=st.integers(0, 5000), seed=st.integers(0, 2**31))
def test_budget_is_met_exactly_and_counts_bracket_target(d, budget, seed):
    c = counts_from_density(d, budget, rng=seed)
    assert c.dtype == np.int64 and c.shape == d.shape
    assert c.sum() == budget and c.min() >= 0
    if d.sum() > 0:
        t = d / d.sum() * budget
        assert np.all(c >= np.floor(t) - 1e-9) and np.all(c <= np.ceil(t) + 1e-9 + 1)


def test_rounding_is_unbiased():
    rng = np.random.default_rng(0)
    d = rng.uniform(0, 1, size=(6, 7))
    budget = 100
    t = d / d.sum() * budget
    reps = 4000
    acc = np.zeros_like(d)
    for s in range(reps):
        acc += counts_from_density(d, budget, rng=s)
    avg = acc / reps
    # each count is floor(t)+Bernoulli(frac); per-pixel z-scores of the average
    frac = t - np.floor(t)
    se = np.sqrt(np.maximum(frac * (1 - frac), 1e-12) / reps)
    z = ((avg - t) / se)[frac > 0.02]
    p = sps.kstest(z, "norm").pvalue
    assert p > 1e-3, f"rounding looks biased, KS p = {p:.2g}"


def test_min_count_and_uniform_for_zero_map():
    c = counts_from_density(np.zeros((4, 4)), 37, min_count=1, rng=0)
    assert c.sum() == 37 and c.min() >= 1
    with pytest.raises(InputError, match=r"`budget` must be at least `min_count` × pixels = 1 × "
                       r"16 = 16 samples; got 10\."):
        counts_from_density(np.ones((4, 4)), 10, min_count=1)


@pytest.mark.parametrize("d, match", [
    (np.full((2, 2), np.nan), "NaN"), (-np.ones((2, 2)), ">= 0"), (np.ones(3), "dimensions")])
def test_bad_density(d, match):
    with pytest.raises(InputError, match=match):
        counts_from_density(d, 10)


def test_negative_budget():
    with pytest.raises(InputError, match="budget"):
        counts_from_density(np.ones((2, 2)), -1)


def test_subnormal_density_does_not_overflow():
    # regression: rest / total overflowed to inf for a subnormal total (found by hypothesis)
    c = counts_from_density(np.array([[2.22507386e-313, 0.0]]), 1, rng=0)
    assert c.tolist() == [[1, 0]]


@settings(max_examples=60, deadline=None)
@given(d=arrays(np.float64, st.tuples(st.integers(1, 12), st.integers(1, 12)),
                elements=st.floats(0, 1e6, allow_nan=False)),
       budget=st.integers(0, 5000), min_count=st.integers(0, 3), seed=st.integers(0, 2**31))
def test_compiled_rounding_equals_numpy_reference(d, budget, min_count, seed):
    from statmc.sampling import _systematic_round, _systematic_round_reference
    rest = budget + min_count * d.size              # min_count always fits
    got = _systematic_round(d, rest - min_count * d.size, min_count, np.random.default_rng(seed))
    ref = _systematic_round_reference(d, rest - min_count * d.size, min_count,
                                      np.random.default_rng(seed))
    np.testing.assert_array_equal(got, ref)


def test_compiled_rounding_equals_reference_on_a_large_map():
    from statmc.sampling import _systematic_round, _systematic_round_reference
    rng = np.random.default_rng(5)
    d = rng.lognormal(0, 2, (300, 400)) * (rng.random((300, 400)) < 0.7)
    for budget in (1, 12345, 7 * d.size + 3):
        np.testing.assert_array_equal(_systematic_round(d, budget, 0, np.random.default_rng(1)),
                                      _systematic_round_reference(d, budget, 0,
                                                                  np.random.default_rng(1)))


def _extra_sample_pvalues(draw, t, reps):
    """Per-pixel exact binomial p-values of ``E[counts] = t`` for ``reps`` independent maps
    ``draw(seed)``: each count must be ``floor(t)`` or ``floor(t) + 1``, so the number of
    maps where pixel i got the extra sample is Binomial(reps, t_i − floor(t_i))."""
    base = np.floor(t)
    extra = np.zeros(t.shape, np.int64)
    for s in range(reps):
        e = draw(s) - base
        assert np.all((e == 0) | (e == 1)), "a count left {floor(t), floor(t) + 1}"
        extra += e.astype(np.int64)
    frac = (t - base).ravel()
    return np.array([sps.binomtest(int(k), reps, f).pvalue if 0 < f < 1 else float(k == 0)
                     for k, f in zip(extra.ravel(), frac)])


def test_rounding_is_unbiased_per_pixel_with_min_count_and_zero_density():
    """E[counts] = min_count + (budget − N·min_count)·d/Σd in every pixel: exact binomial
    test per pixel, Bonferroni over the pixels (valid under the dependence between pixels
    that systematic rounding creates).  Zero-density pixels get exactly min_count.  Power:
    the same test rejects systematic rounding with its offset drawn from U(0, 0.9)
    instead of U(0, 1) (a mild bias towards the early pixels of each stratum)."""
    from statmc.sampling import _systematic_round_reference
    rng = np.random.default_rng(31)
    d = rng.lognormal(0.0, 1.0, (6, 8)) * (rng.random((6, 8)) < 0.8)
    min_count, rest, reps, alpha = 2, 157, 3000, 1e-3
    budget = min_count * d.size + rest
    t = min_count + rest * d / d.sum()
    def draw(s):
        return counts_from_density(d, budget, min_count=min_count, rng=s)

    p = _extra_sample_pvalues(draw, t, reps)
    assert p.min() > alpha / p.size, f"biased: min p = {p.min():.3g}, pixels {np.argsort(p)[:5]}"
    for s in range(20):
        assert np.all(draw(s)[d == 0] == min_count)

    class Skewed:                                         # offset u ~ U(0, 0.9): biased
        def __init__(self, s):
            self.g = np.random.default_rng(s)

        def uniform(self):
            return 0.9 * self.g.uniform()

    p_alt = _extra_sample_pvalues(
        lambda s: _systematic_round_reference(d, rest, min_count, Skewed(s)), t, reps)
    assert p_alt.min() < alpha / p_alt.size, f"no power: min p = {p_alt.min():.3g}"


def test_points_on_stratum_boundaries_fall_in_half_open_intervals():
    """Pixel i owns the points in [cum_{i-1}, cum_i) (np.searchsorted side="right" in the
    reference); a point exactly on a boundary (u = 0 with fractional parts 1/2) goes to
    the next pixel with a non-empty interval, in the kernel as in the reference.  Catches
    an off-by-one `<=` in the compiled sweep that a continuous random u never hits."""
    from statmc.sampling import _systematic_round, _systematic_round_reference

    class Fixed:
        def __init__(self, u):
            self.u = u

        def uniform(self):
            return self.u

    d = np.array([[1.0, 1.0, 0.0, 1.0, 1.0]])              # targets 1/2, 1/2, 0, 1/2, 1/2
    for u, want in ((0.0, [1, 0, 0, 1, 0]), (0.5, [0, 1, 0, 0, 1]), (0.25, [1, 0, 0, 1, 0])):
        got = _systematic_round(d, 2, 0, Fixed(u))
        np.testing.assert_array_equal(got, [want], err_msg=f"u = {u}")
        np.testing.assert_array_equal(_systematic_round_reference(d, 2, 0, Fixed(u)), [want])


@pytest.mark.parametrize("kw, shown", [
    ({"budget": 10.5}, "10.5"), ({"budget": "10"}, "'10'"), ({"budget": np.inf}, "inf"),
    ({"budget": None}, "None"), ({"budget": True}, "True"), ({"budget": -1}, "-1"),
    ({"min_count": 0.5}, "0.5"), ({"min_count": "1"}, "'1'"), ({"min_count": -2}, "-2")])
def test_budget_and_min_count_must_be_whole_numbers(kw, shown):
    """A fractional budget was truncated silently (10.5 -> 10 samples, so the map no longer
    met the budget the caller asked for; min_count=0.5 became 0), a string '10' was
    accepted, inf was an OverflowError and None a TypeError.  Whole floats (12.0) and
    NumPy integers still work."""
    args = {"budget": 12, "min_count": 1, **kw}
    name = next(iter(kw))
    with pytest.raises(InputError, match=rf"`{name}` must be a whole number of samples >= 0; "
                                         rf"got {shown}"):
        counts_from_density(np.ones((2, 2)), args["budget"], min_count=args["min_count"], rng=0)
    for b in (12.0, np.float64(12.0), np.int32(12)):
        assert counts_from_density(np.ones((2, 2)), b, min_count=np.int64(1), rng=0).sum() == 12


@settings(max_examples=60, deadline=None)
@example(seed=0, h=1, w=2, dtype=np.float64, mags=[1.79e308], budget=7, min_count=0)  # sum = inf
@given(seed=st.integers(0, 2 ** 31), h=st.integers(1, 12), w=st.integers(1, 12),
       dtype=st.sampled_from([np.float32, np.float64]),
       mags=st.lists(st.sampled_from([0.0, 5e-324, 1e-300, 1e-20, 1.0, 1e15, 1e300, 1.79e308]),
                     min_size=1, max_size=3),
       budget=st.sampled_from([0, 1, 7, 1000, 2 ** 40, 2 ** 53]), min_count=st.integers(0, 2))
def test_budget_is_met_exactly_on_any_magnitudes(seed, h, w, dtype, mags, budget, min_count):
    # Any mix of magnitudes (subnormal to near float64's maximum, float32 maps where they
    # fit), one-row/one-column maps, budgets from 0 to 2**53: the counts are int64, >=
    # min_count, sum to the budget exactly, and pixels of density 0 get min_count only
    # (unless the whole map is 0: then it is uniform).
    rng = np.random.default_rng(seed)
    d = rng.choice(np.asarray(mags, np.float64), size=(h, w)) * rng.uniform(0.5, 1.0, size=(h, w))
    if dtype == np.float32:
        d = np.minimum(d, 3e38).astype(np.float32)
    budget = max(budget, min_count * h * w)
    c = counts_from_density(d, budget, min_count=min_count, rng=seed)
    assert c.dtype == np.int64 and c.shape == (h, w)
    assert int(c.sum()) == budget and c.min() >= min_count
    if d.any():
        assert (c[d == 0] == min_count).all()
