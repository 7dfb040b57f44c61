"""The adaptive render loop: exact budgets, sampler contract, pictures."""

import numpy as np
import pytest

from statmc import InputError
from statmc.adaptive import adaptive_render
from statmc.pipeline import reconstruct_stats, render_with_sampler
from statmc.plots import write_convergence_plot, write_map_png
from statmc.toy import ToyRenderer


@pytest.fixture(scope="module")
def toy():
    return ToyRenderer("mixed", width=24, height=20)


@pytest.mark.parametrize("sampler", ["uniform", "gem", "expected-error"])
@pytest.mark.parametrize("spp", [5, 12.5])
def test_budget_is_met_exactly_and_passes_merge(toy, sampler, spp):
    res = adaptive_render(toy, spp, sampler=sampler, seed=3)
    total = int(round(spp * toy.height * toy.width))
    assert res.stats.n.sum() == total
    assert len(res.counts) == 9 and np.all(res.counts[0] == 4)
    np.testing.assert_array_equal(sum(res.counts), res.stats.n)
    budgets = [c.sum() for c in res.counts[1:]]
    assert max(budgets) - min(budgets) <= 1  # the rest is split evenly over the iterations


def test_adaptive_samplers_move_samples(toy):
    n = adaptive_render(toy, 16, sampler="gem", seed=1).stats.n
    assert n.min() >= 4 and n.max() > 3 * 16  # concentrated somewhere, never below the first pass


def test_same_seed_same_result(toy):
    a = adaptive_render(toy, 8, sampler="gem", seed=7).stats
    b = adaptive_render(toy, 8, sampler="gem", seed=7).stats
    np.testing.assert_array_equal(a.n, b.n)
    np.testing.assert_array_equal(a.mean, b.mean)


def test_bad_sampler_and_budgets(toy):
    with pytest.raises(InputError, match="unknown sampler"):
        adaptive_render(toy, 8, sampler="nope")
    with pytest.raises(InputError, match="sampler returned"):
        adaptive_render(toy, 8, sampler=lambda stats, budget, rng: np.zeros(stats.n.shape, int))
    with pytest.raises(InputError, match="initial pass"):
        adaptive_render(toy, 2, sampler="gem", initial_spp=4)
    with pytest.raises(InputError, match=">= 2 spp"):
        adaptive_render(toy, 8, sampler="gem", initial_spp=1)
    with pytest.raises(InputError, match="sample map"):
        render_with_sampler(toy, 8, sampler="gem", counts=np.ones((20, 24), int))


def test_reconstructions(toy):
    st = toy.render_uniform(16, seed=0)
    truth = toy.true_mean()
    raw, _ = reconstruct_stats(st, "none")
    gem, maps = reconstruct_stats(st, "gem")
    gau, _ = reconstruct_stats(st, "gaussian", sigma=1.0)
    mse = lambda x: float(np.mean((x - truth) ** 2))  # noqa: E731
    assert mse(gem) < mse(raw) and mse(gau) < mse(raw)
    assert maps["scale"].shape == (20, 24) and maps["sigma"].max() > 0
    with pytest.raises(InputError, match="unknown reconstruction"):
        reconstruct_stats(st, "magic")


def test_pictures_are_written_atomically(tmp_path):
    write_map_png(tmp_path / "m.png", np.arange(12.0).reshape(3, 4), label="spp", log=True)
    write_convergence_plot(tmp_path / "c.png", {"a": ([4, 16], [1.0, 0.25])})
    for f in ("m.png", "c.png"):
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(InputError, match="differ in shape"):
        write_convergence_plot(tmp_path / "bad.png", {"a": ([4, 16], [1.0])})
    with pytest.raises(InputError, match="NaN"):
        write_map_png(tmp_path / "bad.png", np.full((2, 2), np.nan))
    assert not (tmp_path / "bad.png").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".statmc-")]


def test_doubling_schedule_doubles_the_budget(toy):
    """Salehi 2022 §5.2: B_t = 8·2^t spp; the callback sees every cumulative budget."""
    hw = toy.height * toy.width
    seen = []
    res = adaptive_render(toy, 64, sampler="gem", initial_spp=8, schedule="doubling", seed=2,
                          callback=lambda k, st, c: seen.append(int(st.n.sum()) // hw))
    assert seen == [8, 16, 32, 64] and len(res.counts) == 4
    np.testing.assert_array_equal(sum(res.counts), res.stats.n)
    assert res.counts[-1].sum() == 32 * hw and res.stats.n.min() >= 8
    # a budget that is no power-of-two multiple: the last pass is capped
    res = adaptive_render(toy, 20, sampler="uniform", initial_spp=8, schedule="doubling")
    assert [int(c.sum()) // hw for c in res.counts] == [8, 8, 4] and res.stats.n.sum() == 20 * hw
    # the uniform sampler on doubling passes is the uniform render
    assert np.all(res.stats.n == 20)
    # even schedule unchanged
    assert [len(adaptive_render(toy, 8, sampler="uniform", schedule="even").counts)] == [9]


def test_doubling_schedule_errors(toy):
    with pytest.raises(InputError, match="schedule"):
        adaptive_render(toy, 16, sampler="gem", schedule="triple")
    with pytest.raises(InputError, match="doubling schedule, which needs 2 passes"):
        adaptive_render(toy, 32, sampler="gem", initial_spp=8, schedule="doubling", iterations=3)
    with pytest.raises(InputError, match="initial pass"):
        adaptive_render(toy, 4, sampler="gem", initial_spp=8, schedule="doubling")
    with pytest.raises(InputError, match="needs 0 passes"):
        adaptive_render(toy, 8, sampler="gem", initial_spp=8, schedule="doubling", iterations=2)


def test_expected_error_with_gem_pilot_kernels_holds_them_fixed():
    """get_sampler('expected-error', kernels='gem') is a fresh PilotKernelSampler per render:
    the kernels come from the first (pilot) pass and do not change afterwards."""
    from statmc.adaptive import get_sampler
    from statmc.analytic import PilotKernelSampler
    a = get_sampler("expected-error", kernels="gem")
    b = get_sampler("expected-error", kernels="gem")
    assert isinstance(a, PilotKernelSampler) and a is not b
    seen = []
    r = ToyRenderer("mixed", width=16, height=16)
    res = adaptive_render(r, 8, sampler=a, seed=3,
                          callback=lambda k, stats, counts: seen.append(a.kernels.copy()
                                                                        if a.kernels is not None else None))
    assert int(res.stats.n.sum()) == 8 * 16 * 16
    later = [k for k in seen[1:] if k is not None]
    assert later and all(np.array_equal(later[0], k) for k in later)


def test_even_schedule_splits_a_remainder_exactly():
    """Rousselle 2011 §6: N = M(n − 4)/8 samples per iteration.  When 8 does not divide
    the rest, the first ``rest % 8`` passes take one sample more: closed form, for
    several totals, initial passes and iteration counts (the budgets of the other tests
    divide evenly, which hid a dropped remainder)."""
    from statmc.adaptive import pass_budgets
    for total, first, it in ((2405, 1920, 8), (1000, 3, 8), (17, 10, 3), (9, 9, 4), (100, 0, 7)):
        rest = total - first
        got = pass_budgets(total, first, iterations=it)
        want = [rest // it + 1] * (rest % it) + [rest // it] * (it - rest % it)
        assert got == want and sum(got) == rest, (total, first, it, got)
    assert pass_budgets(50, 10) == [5] * 8                      # 8 iterations by default
    assert pass_budgets(50, 10, iterations=0) == []


@pytest.mark.parametrize("sampler", ["uniform", "gem"])
def test_budget_with_a_remainder_is_met_exactly(toy, sampler):
    """spp = 5.01 on 24×20: total round(2404.8) = 2405, rest 485 = 8·60 + 5 over the 8
    passes; the loop's total and every pass's budget are exact."""
    res = adaptive_render(toy, 5.01, sampler=sampler, seed=4)
    assert int(res.stats.n.sum()) == 2405
    assert [int(c.sum()) for c in res.counts] == [4 * 480] + [61] * 5 + [60] * 3
    np.testing.assert_array_equal(sum(res.counts), res.stats.n)


def test_no_iterations_spreads_the_fractional_remainder():
    """``iterations=0``: one uniform pass of int(spp) spp plus the remainder
    round(spp·M) − int(spp)·M spread uniformly (every pixel 4 or 5 at 4.25 spp)."""
    r = ToyRenderer("mixed", width=24, height=20)
    res = adaptive_render(r, 4.25, sampler="uniform", iterations=0, seed=5)
    n = res.stats.n
    assert int(n.sum()) == round(4.25 * 480) and len(res.counts) == 1
    assert n.min() == 4 and n.max() == 5 and int((n == 5).sum()) == 120


@pytest.mark.parametrize("spp", [1e30, 2.0 ** 50])
def test_a_budget_beyond_float_precision_is_named_by_spp(spp):
    # before: "`budget` must be a whole number <= 9007199254740992; got 3.2e+33", naming an
    # internal variable the caller never passed
    r = ToyRenderer("mixed", width=16, height=16)
    with pytest.raises(InputError, match=r"`spp` × H × W must be at most 2\*\*53 samples "
                       r"\(float64 counts them exactly\); got .* × 16 × 16"):
        adaptive_render(r, spp, sampler="uniform")
