"""The iterative adaptive render loop, generic over renderers and samplers.

An initial uniform pass, then ``iterations`` passes whose per-pixel counts a *sampler*
chooses from the statistics so far, merged exactly into one :class:`PixelStats`.  The
budget of ``spp × H × W`` samples is met exactly (Rousselle et al. 2011, §6: 4 initial
samples per pixel, then 8 iterations of ``M(n − 4)/8`` samples each).  The alternative
``schedule="doubling"`` doubles the total budget at every pass instead, ``B_t = B_0 2^t``
(Salehi et al. 2022, §5.2: ``B_t = 2^(t+3)`` spp from an initial 8), so that one run
yields the whole error-against-budget curve.

A sampler is a callable ``sampler(stats, budget, rng) -> counts`` returning an ``(H, W)``
integer map that sums to ``budget``.  Named samplers live in :data:`SAMPLERS`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .errors import InputError, as_int, as_number, as_rng, as_whole
from .stats import PixelStats, check_stats

__all__ = ["adaptive_render", "AdaptiveResult", "SAMPLERS", "get_sampler", "pass_budgets"]


def _uniform_sampler(stats: PixelStats, budget: int, rng) -> np.ndarray:
    from .sampling import counts_from_density
    check_stats(stats)
    return counts_from_density(np.ones(stats.n.shape), budget, rng=rng)


def _gem_sampler(stats: PixelStats, budget: int, rng, *, gamma: float = 0.2) -> np.ndarray:
    from .gem import sampling_map
    check_stats(stats)
    return sampling_map(stats.mean, stats.mean_var, stats.n, budget, gamma=gamma, rng=rng)


def _expected_error_sampler(stats: PixelStats, budget: int, rng, **options) -> np.ndarray:
    from .analytic import expected_error_sampler
    return expected_error_sampler(stats, budget, rng, **options)


def _denoising_aware_sampler(stats: PixelStats, budget: int, rng, **options) -> np.ndarray:
    from .da_sampling import sampler
    return sampler(stats, budget, rng, **options)


SAMPLERS: dict[str, Callable] = {
    "uniform": _uniform_sampler,
    "gem": _gem_sampler,
    "expected-error": _expected_error_sampler,
    "denoising-aware": _denoising_aware_sampler,
}


def _sampler_options(fn: Callable) -> set[str] | None:
    """The keyword options the sampler ``fn`` takes: for the built-in ones, those of the
    functions they forward to; for a sampler a user registered in :data:`SAMPLERS`, its own
    (None, i.e. any, when it takes ``**options`` or has no signature)."""
    import inspect

    extra = set()
    if fn is _expected_error_sampler:
        from .analytic import expected_error_sampler
        fns, extra = [expected_error_sampler], {"gem_options"}     # PilotKernelSampler
    elif fn is _denoising_aware_sampler:
        from .da_sampling import denoising_aware_density, sampler
        fns = [sampler, denoising_aware_density]
    else:
        try:
            params = inspect.signature(fn).parameters.values()
        except (TypeError, ValueError):
            return None
        if any(p.kind == inspect.Parameter.VAR_KEYWORD for p in params):
            return None
        fns = [fn]
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    names = {p.name for f in fns for p in inspect.signature(f).parameters.values()
             if p.kind in kinds}
    return (names | extra) - {"stats", "budget", "rng", "extra_output"}


def get_sampler(name_or_callable, **options) -> Callable:
    """A sampler by name (:data:`SAMPLERS`) or a callable, with ``options`` bound.

    A named sampler's options are checked here: an unknown one is an
    :class:`~statmc.errors.InputError` (not a ``TypeError`` after the first render pass).
    """
    if not callable(name_or_callable) and name_or_callable in SAMPLERS and options:
        allowed = _sampler_options(SAMPLERS[name_or_callable])
        unknown = [] if allowed is None else sorted(set(options) - allowed)
        if unknown:
            raise InputError(f"unknown option(s) {unknown} for sampler {name_or_callable!r}; "
                             f"expected some of {sorted(allowed) or 'none'}.")
    if callable(name_or_callable):
        fn = name_or_callable
    elif name_or_callable == "expected-error" and isinstance(options.get("kernels"), str) \
            and options["kernels"] == "gem":
        # GEM kernels selected once from the pilot pass and then held fixed (Lemma A.1 of
        # Salehi 2022 needs kernels that do not see the new samples): a fresh, stateful
        # sampler per call, i.e. per render.
        from .analytic import PilotKernelSampler
        rest = {k: v for k, v in options.items() if k != "kernels"}
        return PilotKernelSampler("gem", **rest)
    else:
        try:
            fn = SAMPLERS[name_or_callable]
        except KeyError:
            raise InputError(f"unknown sampler {name_or_callable!r}; expected one of "
                             f"{sorted(SAMPLERS)}.") from None
    if options:
        return lambda stats, budget, rng: fn(stats, budget, rng, **options)
    return fn


@dataclass
class AdaptiveResult:
    """Statistics of all passes merged, and what each pass did."""

    stats: PixelStats
    counts: list[np.ndarray] = field(default_factory=list)
    seconds_render: float = 0.0
    seconds_sampler: float = 0.0

    @property
    def total_counts(self) -> np.ndarray:
        return self.stats.n


SCHEDULES = ("even", "doubling")


def pass_budgets(total: int, first: int, *, schedule: str = "even",
                 iterations: int | None = None) -> list[int]:
    """Sample totals of the adaptive passes after an initial pass of ``first`` samples.

    ``"even"``: ``total − first`` split over ``iterations`` passes (8 by default; sizes
    differ by at most one sample; Rousselle et al. 2011, §6).  ``"doubling"``: each pass
    brings the cumulative budget to twice its value, ``B_t = first · 2^t`` (Salehi et al.
    2022, §5.2), the last pass capped at ``total``; ``iterations``, if given, must equal
    the number of such passes.
    """
    if schedule not in SCHEDULES:
        raise InputError(f"`schedule` must be one of {SCHEDULES}; got {schedule!r}.")
    total = as_whole("total", total, what="number of samples")
    first = as_whole("first", first, what="number of samples")
    if iterations is not None:
        iterations = as_whole("iterations", iterations, what="number of passes")
    if first > total:
        raise InputError(f"`first`={first} samples exceed `total`={total}; the passes after "
                         "the initial one cannot take a negative budget.")
    rest = total - first
    if schedule == "even":
        it = 8 if iterations is None else iterations
        return [rest // it + (1 if k < rest % it else 0) for k in range(it)] if it else []
    if first <= 0:
        raise InputError(f"the doubling schedule needs an initial pass of > 0 samples; "
                         f"got {first}.")
    out, done = [], first
    while done < total:
        step = min(done, total - done)
        out.append(step)
        done += step
    if iterations is not None and iterations != len(out):
        raise InputError(f"`iterations`={iterations} does not match the doubling schedule, "
                         f"which needs {len(out)} passes from {first} to {total} samples; "
                         "leave `iterations` unset.")
    return out


def _takes_first_sample(renderer) -> bool:
    """Whether ``renderer.render`` accepts ``first_sample`` (continues sample sequences)."""
    import inspect
    try:
        return "first_sample" in inspect.signature(renderer.render).parameters
    except (TypeError, ValueError):
        return False


def adaptive_render(renderer, spp: float, *, sampler="gem", initial_spp: int = 4,
                    iterations: int | None = None, schedule: str = "even", seed: int = 0,
                    progress: bool = False, callback=None, **sampler_options) -> AdaptiveResult:
    """Render with an average of ``spp`` samples per pixel, placed adaptively.

    Parameters
    ----------
    renderer : object with ``height``, ``width`` and ``render(counts, *, seed, features)``
        If its ``render`` also takes ``first_sample`` (as
        :meth:`statmc.mitsuba_backend.MitsubaRenderer.render` does), every pass continues
        each pixel's sample sequence of ``seed``: the result then holds the same samples as
        one render of the final counts with ``seed``, so it shares the first samples of
        every pixel with a uniform render of that seed (common random numbers between
        samplers), and a change in one pass's counts changes only the pixels it moves.
        Otherwise every pass gets a seed of its own, derived from ``seed``.
    spp : float
        Average samples per pixel over all passes; the total is ``round(spp × H × W)``.
    sampler : str or callable
        ``"uniform"``, ``"gem"`` (Rousselle 2011), ``"expected-error"`` (Salehi 2022
        Lemma A.1 with a fixed Gaussian), ``"denoising-aware"`` (Firmino 2023; option
        ``denoiser="oidn"|"gem"|"gaussian"``) or any ``sampler(stats, budget, rng) -> counts``.
    initial_spp : int
        Samples per pixel of the first, uniform pass (4 in Rousselle 2011 §6).
    iterations : int, optional
        Adaptive passes after it (8 in Rousselle 2011 §6, the default for ``"even"``).
    schedule : {"even", "doubling"}
        ``"even"`` splits the budget after the initial pass evenly over ``iterations``
        passes; ``"doubling"`` doubles the cumulative budget at every pass (Salehi 2022
        §5.2), the last pass capped at ``spp`` — see :func:`pass_budgets`.
    callback : callable, optional
        Called as ``callback(k, stats, counts)`` after every pass.

    Returns
    -------
    AdaptiveResult
    """
    if not callable(getattr(renderer, "render", None)) or not all(
            isinstance(getattr(renderer, a, None), (int, np.integer)) for a in ("height", "width")):
        hint = (" (a scene name: build a renderer first, e.g. statmc.renderers.make_renderer)"
                if isinstance(renderer, str) else "")
        raise InputError(f"`renderer` must have integer `height`, `width` and a method "
                         f"render(counts, *, seed, features) -> PixelStats; got "
                         f"{type(renderer).__name__}{hint}.")
    h, w = renderer.height, renderer.width
    spp_value = as_number("spp", spp, lo=0.0)
    if spp_value * h * w > 2 ** 53:
        raise InputError(f"`spp` × H × W must be at most 2**53 samples (float64 counts them "
                         f"exactly); got {spp_value:g} × {h} × {w}.")
    total = int(round(spp_value * h * w))
    initial_spp = as_whole("initial_spp", initial_spp, what="number of samples per pixel")
    if iterations is not None:
        iterations = as_whole("iterations", iterations, what="number of passes")
    seed = as_int("seed", seed, lo=0)            # also a renderer seed: an int, not a Generator
    if schedule not in SCHEDULES:
        raise InputError(f"`schedule` must be one of {SCHEDULES}; got {schedule!r}.")
    given = iterations
    if iterations is None:
        iterations = 8
    if schedule == "doubling" and iterations:  # a flag here; the schedule sets the count
        iterations = 1 if total != initial_spp * h * w else 0
        if not iterations and given:
            pass_budgets(total, total, schedule=schedule, iterations=given)  # raises: 0 passes
    if iterations and initial_spp * h * w > total:
        raise InputError(f"`spp`={spp} is below the initial pass of {initial_spp} spp; "
                         "lower `initial_spp` or give more samples.")
    first = initial_spp if iterations else int(spp)
    if iterations and first < 2:
        raise InputError("adaptive sampling needs an initial pass of >= 2 spp to estimate variances.")
    pick = get_sampler(sampler, **sampler_options)
    rng = as_rng(seed, "seed")
    rest = total - first * h * w
    budgets = pass_budgets(total, first * h * w, schedule=schedule,
                           iterations=given if schedule == "doubling" else iterations) \
        if iterations else []
    t_render = t_sampler = 0.0
    counts = np.full((h, w), first, np.int64)
    if not iterations and rest:  # uniform remainder spread unbiasedly
        counts = counts + _uniform_sampler(PixelStats.empty(h, w), rest, rng)
    res = AdaptiveResult(stats=None)
    continues = _takes_first_sample(renderer)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, desc="adaptive render", unit="spl", unit_scale=True)
    for k in range(len(budgets) + 1):
        if k > 0:
            t0 = time.perf_counter()
            counts = np.asarray(pick(res.stats, budgets[k - 1], rng))
            t_sampler += time.perf_counter() - t0
            if counts.shape != (h, w) or counts.sum() != budgets[k - 1] or counts.min() < 0:
                raise InputError(f"sampler returned counts of shape {counts.shape} summing to "
                                 f"{counts.sum()}; expected ({h}, {w}) summing to {budgets[k - 1]}.")
        t0 = time.perf_counter()
        if continues:
            part = renderer.render(counts, seed=seed, features=(k == 0),
                                   first_sample=None if res.stats is None else res.stats.n)
        else:
            part = renderer.render(counts, seed=seed * 1_000_003 + 7919 * k, features=(k == 0))
        t_render += time.perf_counter() - t0
        if not isinstance(part, PixelStats) or part.shape[:2] != (h, w):
            what = (f"PixelStats of shape {part.shape}" if isinstance(part, PixelStats)
                    else type(part).__name__)
            raise InputError(f"`renderer.render` must return PixelStats of {h}x{w} pixels; "
                             f"got {what}.")
        res.stats = part if res.stats is None else res.stats.merge(part)
        res.counts.append(counts)
        if bar is not None:
            bar.update(int(counts.sum()))
        if callback is not None:
            callback(k, res.stats, counts)
    if bar is not None:
        bar.close()
    res.seconds_render, res.seconds_sampler = t_render, t_sampler
    return res
