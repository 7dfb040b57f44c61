# %% [markdown]
# # Verifying the theorems numerically
#
# Five claims of the papers behind `statmc`, each checked against a closed form, a
# generic solver or Monte Carlo, with the numbers on screen. The papers are in
# `../shared/papers/` of the project workspace; the same checks, with their statistical
# thresholds, are in `tests/` (named in each section). Everything runs on the CPU in
# well under a minute.
#
# 1. GEM's error-rate parameter γ against the measured rate of wrong stops (Rousselle et al. 2011, Eq. 1 and §4.3)
# 2. Back et al. 2020, Eq. 8 is the exact minimiser of Eq. 6
# 3. Firmino et al. 2022, Eq. 9's mixing α minimises the expected error of Eq. 8
# 4. SURE is unbiased (Firmino et al. 2022, Eq. 1)
# 5. Future renders: gamma moment matching (Salehi et al. 2022, Eq. 8 and 9) and the bias–variance decomposition of Lemma A.1 / Theorem 1

# %%
import numpy as np
import matplotlib.pyplot as plt
from scipy import optimize, stats as sps

from statmc import analytic, combine, denoisers, gem, progressive, sure
from statmc.sure import kernel_variance
from statmc.toy import ToyRenderer

plt.rcParams["figure.dpi"] = 80


def t_interval(values, level=0.999):
    """Mean and two-sided t confidence interval of i.i.d. values."""
    v = np.asarray(values, float)
    lo, hi = sps.t.interval(level, v.size - 1, loc=v.mean(), scale=sps.sem(v))
    return v.mean(), lo, hi

# %% [markdown]
# ## 1. GEM: γ is the rate of wrong stops on constant noisy images
#
# Rousselle, Knaus & Zwicker 2011 (`rousselle2011-greedy-error-minimization.md`),
# Eq. 1 and §4.3: the scale selector stops at the finer of two Gaussians when
# `S = ρ z(γ) (r_c² + r_f²)/(r_c² − r_f²) Σ (c − f)² + Σ (Var[c] − Var[f]) > 0`, with the
# hand-fitted weight `z(γ) = −log(1 − (1.9 γ)^(1/√2))` meant to make γ the rate of wrong
# stops on a constant image (where the bias is zero, so every stop is wrong).
#
# We measure it as `tests/test_gem.py::test_gamma_sets_the_error_rate_on_constant_images`
# does: constant 128×128 images with Gaussian noise, n = 32 samples per pixel, one
# channel, the pair σ = 1 → 2 (the paper's Fig. 4 setting), raw stop decisions (no
# post-processing), 8 independent images per γ. `docs/gem.md` has the full γ × n table.

# %%
rng = np.random.default_rng(1)
n, size, reps = 32, 128, 8
gammas = [0.05, 0.1, 0.15, 0.2, 0.25, 0.3]
rows = []
for g in gammas:
    rates = []
    for _ in range(reps):
        x = rng.normal(size=(n, size, size, 1))            # truth 0, sample sd 1
        mean, mean_var = x.mean(0), x.var(0, ddof=1) / n   # variance of the MEAN
        out = gem.select(mean, mean_var, gamma=g, n=np.full((size, size), n),
                         sigmas=(0.0, 1.0, 2.0), final=False, postprocess=False)
        rates.append(out["stop_raw"][1].mean())            # pair sigma 1 -> 2
    rows.append((g, gem.error_rate_weight(g), *t_interval(rates)))

print(" gamma   z(gamma)  wrong-stop rate  99.9% t interval")
for g, z, m, lo, hi in rows:
    print(f"{g:6.2f}  {z:8.3f}  {m:15.3f}  [{lo:.3f}, {hi:.3f}]")

r = np.array(rows)
fig, ax = plt.subplots(figsize=(4.2, 3.6))
ax.plot([0, 0.35], [0, 0.35], "k:", label="rate = γ")
ax.errorbar(r[:, 0], r[:, 2], yerr=[r[:, 2] - r[:, 3], r[:, 4] - r[:, 2]], fmt="o-",
            label="measured (99.9% CI)")
ax.set_xlabel("γ"); ax.set_ylabel("rate of wrong stops"); ax.legend()
ax.set_title("GEM error-rate calibration, n = 32")
plt.show()

# %% [markdown]
# The fitted `z(γ)` does what the paper says only roughly: the rate tracks γ within a few
# hundredths for γ = 0.1 … 0.3 (10–15 % high), and is about 60 % of γ at γ = 0.05.
# The test accepts the paper's accuracy, ±0.05.

# %% [markdown]
# ## 2. Back et al. 2020: Eq. 8 is the exact minimiser of Eq. 6
#
# Back, Hua, Hachisuka & Moon 2020 (`back2020-deep-combiner.md`). For an independent
# estimate `y` and a correlated one `z` (e.g. a denoised image or a common-random-number
# render), Eq. 6 is the least-squares energy of pixel c over its window,
#
# `J_c = ½ w_c (y_c − β_c)² + Σ_i w_i (y_i − β_i)² + Σ_i w_i ((z_c − z_i) − (β_c − β_i))²`,
#
# and Eq. 8 its closed-form minimiser
# `β̂_c = (w_c y_c + Σ_i w_i (y_i + z_c − z_i)) / (w_c + Σ_i w_i)`. Eq. 7 prints the
# gradients with sign/factor slips (an erratum the tests pin), so we check Eq. 8 directly:
# `statmc.combine.combine` against `numpy.linalg.lstsq` on the stacked weighted
# residuals, for every pixel of random inputs, borders included (taps outside the image
# are dropped). As in `tests/test_combine.py::test_eq8_and_eq14_are_the_least_squares_minimisers`.

# %%
def lstsq_beta_c(y, z, w, py, px):
    """Minimise Eq. 6 of pixel (py, px) with a generic least-squares solver."""
    H, W, C = y.shape
    k = w.shape[-1]
    r = k // 2
    taps = [(dy, dx) for dy in range(k) for dx in range(k) if (dy, dx) != (r, r)
            and 0 <= py + dy - r < H and 0 <= px + dx - r < W]
    out = np.empty(C)
    for c in range(C):
        rows, rhs = [], []
        s = np.sqrt(w[py, px, r, r] / 2)                   # ½ w_c (y_c − β_c)²
        rows.append(np.eye(1 + len(taps))[0] * s); rhs.append(s * y[py, px, c])
        for j, (dy, dx) in enumerate(taps, start=1):
            qy, qx = py + dy - r, px + dx - r
            s = np.sqrt(w[py, px, dy, dx])
            e = np.zeros(1 + len(taps)); e[j] = s          # w_i (y_i − β_i)²
            rows.append(e); rhs.append(s * y[qy, qx, c])
            e = np.zeros(1 + len(taps)); e[0], e[j] = s, -s  # w_i ((z_c−z_i) − (β_c−β_i))²
            rows.append(e); rhs.append(s * (z[py, px, c] - z[qy, qx, c]))
        out[c] = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0][0]
    return out


rng = np.random.default_rng(2)
H, W, C = 9, 11, 3
worst = 0.0
for k in (3, 5, 7):
    y, z = rng.normal(size=(H, W, C)), rng.normal(size=(H, W, C))
    w = rng.uniform(0.05, 2.0, size=(H, W, k, k))
    eq8 = combine.combine(y, z, w)
    ref = np.array([[lstsq_beta_c(y, z, w, i, j) for j in range(W)] for i in range(H)])
    err = np.abs(eq8 - ref).max()
    worst = max(worst, err)
    print(f"k = {k}: max |Eq. 8 − lstsq| over all {H * W * C} pixel-channels = {err:.2e}")

# %% [markdown]
# A picture of the same fact for one pixel: with the neighbours' `β_i` at their optimum
# for a given `β_c` (`β_i = ½(y_i − z_c + z_i + β_c)`, from `∂J_c/∂β_i = 0`), `J_c` is a
# parabola in `β_c` whose bottom is Eq. 8.

# %%
py, px, c = 4, 5, 0
r = k // 2
yc, zc, wc = y[py, px, c], z[py, px, c], w[py, px, r, r]
nb = [(dy, dx) for dy in range(k) for dx in range(k) if (dy, dx) != (r, r)]
yi = np.array([y[py + dy - r, px + dx - r, c] for dy, dx in nb])
zi = np.array([z[py + dy - r, px + dx - r, c] for dy, dx in nb])
wi = np.array([w[py, px, dy, dx] for dy, dx in nb])


def J(bc):
    bi = 0.5 * (yi - zc + zi + bc)
    return 0.5 * wc * (yc - bc) ** 2 + np.sum(wi * (yi - bi) ** 2) \
        + np.sum(wi * ((zc - zi) - (bc - bi)) ** 2)


b8 = eq8[py, px, c]
grid = np.linspace(b8 - 1.5, b8 + 1.5, 201)
fig, ax = plt.subplots(figsize=(4.2, 3.2))
ax.plot(grid, [J(b) for b in grid])
ax.axvline(b8, color="C1", ls="--", label=f"Eq. 8: {b8:.4f}")
ax.set_xlabel("β_c"); ax.set_ylabel("min over β_i of J_c"); ax.legend()
plt.show()
print("numeric minimiser:", optimize.minimize_scalar(J).x, " Eq. 8:", b8)

# %% [markdown]
# ## 3. Firmino et al. 2022: the mixing α of Eq. 9 minimises the expected error
#
# Firmino, Frisvad & Jensen 2022 (`firmino2022-progressive-denoising.md`). Progressive
# denoising outputs `z = x + α (f(x) − x)`. By Stein's lemma its expected squared error
# is Eq. 8, `E[(z − μ)²] = (1 − α)² σ² + α² E[(f − μ)²] + 2 α (1 − α) (D − σ²)` with
# `D = σ² ∂f/∂x` (the divergence term), minimised by Eq. 9,
# `α = (σ² − D) / (σ² − 2D + E[(f − μ)²])` clipped to [0, 1].
#
# Check on the toy renderer, whose per-pixel moments are exact: `f` is a Gaussian filter
# (σ = 1.5 px), `x` the mean of 8 samples, so `σ² = true_var/8`, `D = K_cc σ²` and
# `E[(f − μ)²] = bias² + Σ K² σ²` are exact. We compare (a) the literal Eq. 9 of
# `statmc.progressive.mixing_weights` with a bounded scalar minimiser of Eq. 8 per pixel,
# and (b) Eq. 8 with Monte Carlo over 200 independent renders.
# (`tests/test_progressive.py::test_eq9_minimises_eq8_linear_denoiser_exact_moments`)

# %%
toy = ToyRenderer("mixed", width=48, height=48)
mu, var1 = toy.true_mean(), toy.true_var()       # truth; variance of ONE sample
spp = 8
s2 = var1 / spp                                  # variance of the mean
f = denoisers.gaussian(1.5)
K = f.kernels(mu.shape)
r = K.shape[2] // 2
bias = analytic.apply_kernels(K, mu) - mu
mse_f = bias ** 2 + kernel_variance(K, s2)       # E[(f − μ)²], exact
D = K[:, :, r, r][..., None] * s2                # divergence term, exact
RAW = dict(smooth=0, relative_eps=None, shrink=0, per_channel=True)  # the literal Eq. 9
alpha = progressive.mixing_weights(mu, mu, s2, mse_f, D, **RAW)

pick = np.random.default_rng(3).choice(alpha.size, 200, replace=False)
diffs = []
for i in pick:
    p = np.unravel_index(i, alpha.shape)
    a_num = optimize.minimize_scalar(lambda a: float(progressive.mix_error(a, s2[p], mse_f[p], D[p])),
                                     bounds=(0, 1), method="bounded",
                                     options={"xatol": 1e-12}).x
    diffs.append(abs(alpha[p] - a_num))
print(f"Eq. 9 vs numeric minimiser of Eq. 8 over 200 pixels: max |Δα| = {max(diffs):.1e}")
print(f"α: {np.mean(alpha == 0):.0%} of entries at 0, {np.mean(alpha == 1):.0%} at 1, "
      f"the rest interior")

# %%
R = 200
alphas = np.linspace(0, 1, 11)
mc = np.zeros((R, alphas.size)); mc_eq9 = np.zeros(R)
for s in range(R):
    x = toy.render_uniform(spp, seed=s, features=False).mean
    fx = analytic.apply_kernels(K, x)
    mc[s] = [np.mean((x + a * (fx - x) - mu) ** 2) for a in alphas]
    mc_eq9[s] = np.mean((x + alpha * (fx - x) - mu) ** 2)
closed = [progressive.mix_error(a, s2, mse_f, D).mean() for a in alphas]
closed_eq9 = progressive.mix_error(alpha, s2, mse_f, D).mean()

fig, ax = plt.subplots(figsize=(4.6, 3.4))
ax.plot(alphas, closed, "-", label="Eq. 8 (closed form), one α for all pixels")
ax.errorbar(alphas, mc.mean(0), yerr=3 * mc.std(0, ddof=1) / np.sqrt(R), fmt="o",
            ms=3, label="Monte Carlo, 200 renders (±3 se)")
ax.axhline(closed_eq9, color="C2", ls="--", label="per-pixel α of Eq. 9")
ax.set_xlabel("α"); ax.set_ylabel("MSE"); ax.set_yscale("log"); ax.legend(fontsize=8)
plt.show()
best = int(np.argmin(closed))
zstat = (mc_eq9.mean() - closed_eq9) / (mc_eq9.std(ddof=1) / np.sqrt(R))
print(f"MSE: x alone {closed[0]:.3e}, f(x) alone {closed[-1]:.3e}, "
      f"best single α = {alphas[best]:.1f}: {closed[best]:.3e}, per-pixel Eq. 9: {closed_eq9:.3e}")
print(f"Monte Carlo of the Eq. 9 mix: {mc_eq9.mean():.3e} (z = {zstat:+.2f} against Eq. 8)")

# %% [markdown]
# Eq. 8 and Monte Carlo agree for every α, and the per-pixel α of Eq. 9 beats every
# single global α. In practice σ², D and `E[(f − μ)²]` are not known: `statmc`
# estimates them (variance of the mean from the samples, MC-SURE for black-box
# denoisers), smooths the terms and gates α with a Student-t test (Eq. 12–18); the
# minimisation property shown here holds for the exact moments only.

# %% [markdown]
# ## 4. SURE is unbiased
#
# Firmino et al. 2022, Eq. 1 (Stein's unbiased risk estimate): for a denoiser `f` and
# noisy `x` with variance of the mean σ², `SURE = (f(x) − x)² + 2 σ² ∂f/∂x − σ²` has
# expectation `E[(f(x) − μ)²]`, without knowing μ. Stein's lemma needs Gaussian noise in
# general, but for a *linear* filter it holds for any noise law, so we test it on the
# full "mixed" toy scene (exponential, uniform, Gaussian noise and fireflies) with the
# render's own *estimated* variance of the mean, over 300 independent 8-spp renders.
# A power check: the same test applied to the estimate without the divergence term
# (a classic mistake) must fail. (`tests/test_sure.py::test_sure_is_unbiased_for_a_gaussian_filter_on_toy_renders`)

# %%
toy32 = ToyRenderer("mixed", width=32, height=32)
mu32 = toy32.true_mean()
K32 = denoisers.gaussian(1.5).kernels(mu32.shape)
rows = []
for s in range(300):
    st = toy32.render_uniform(8, seed=s, features=False)
    est, info = sure.sure(K32, st.mean, st.mean_var, extra_output=True)
    true_mse = np.mean((info["denoised"] - mu32) ** 2)
    no_div = np.mean((info["denoised"] - st.mean) ** 2 - st.mean_var)
    rows.append((est.mean(), true_mse, no_div))
rows = np.array(rows)
for name, col in (("SURE", 0), ("without divergence", 2)):
    d = rows[:, col] - rows[:, 1]
    zstat = d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))
    print(f"{name:>20}: mean {rows[:, col].mean():.4e} vs true MSE {rows[:, 1].mean():.4e}, "
          f"z = {zstat:+.2f}, two-sided p = {2 * sps.norm.sf(abs(zstat)):.2g}")

fig, ax = plt.subplots(figsize=(4.8, 3.2))
for name, col in (("SURE", 0), ("without divergence", 2)):
    d = rows[:, col] - rows[:, 1]
    ax.hist(d, bins=40, alpha=0.6, label=f"{name}: mean {d.mean():+.1e}")
ax.axvline(0, color="k", ls=":")
ax.set_xlabel("estimate − true MSE (per render)"); ax.set_ylabel("renders"); ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# Per render SURE scatters around the true MSE (it is an estimate from one noisy image;
# the fireflies make the scatter large), but its mean over renders is the true MSE;
# dropping the divergence term biases it downwards by `2 Σ K_cc σ²`.

# %% [markdown]
# ## 5. Future renders: gamma moment matching and the bias–variance decomposition
#
# Salehi et al. 2022 (`salehi2022-analytic-distributions.md`). Adding `s` samples to a
# pixel rendered with `s̄` samples (current mean `x_t`, true mean `x_g`, per-sample
# variance `V`) gives the future mean `Y = (s̄ x_t + s Ȳ_s)/(s̄ + s)` with Eq. 6 mean
# `(s̄ x_t + s x_g)/(s̄ + s)` and variance `s V/(s̄ + s)²` (the factor of Eq. 19; Eq. 15
# prints `s/(s̄ + s)`, an erratum). Eq. 8/9 draw synthetic future renders by modelling
# `Ȳ_s` as gamma with shape `α = x_g² s/V` and rate `β = x_g s/V`, exact when one sample
# is gamma (a mean of `s` i.i.d. gammas is gamma). First the pixel of the paper's Fig. 5
# (`x_g = 0.38`, `V = 0.9`, `x_t = 0.78`, `s̄ = 16`), as in `tests/test_analytic.py`.

# %%
x_g, V, x_t, s_bar = 0.38, 0.9, 0.78, 16.0
px = lambda v: np.full((1, 1, 1), v)  # noqa: E731
n_rep = 20000
print("   s   E[Y] Eq.6   MC mean    Var[Y] Eq.19  MC var    z(var)")
for s in (1, 4, 16, 64):
    m, v = analytic.future_moments(px(x_t), s_bar, s, px(x_g), px(V))
    ys = analytic.sample_future(np.full((1, n_rep, 1), x_t), np.full((1, n_rep), s_bar),
                                np.full((1, n_rep), float(s)), np.full((1, n_rep, 1), x_g),
                                np.full((1, n_rep, 1), V), rng=100 + s).ravel()
    # standard error of the sample variance from the gamma's excess kurtosis 6/α (Eq. 9's α)
    se_var = v.item() * np.sqrt(2 / (n_rep - 1) + 6 / analytic.gamma_parameters(x_g, V, s)[0] / n_rep)
    print(f"{s:4d}  {m.item():9.4f}  {ys.mean():9.4f}  {v.item():12.5f}  {ys.var(ddof=1):8.5f}"
          f"  {(ys.var(ddof=1) - v.item()) / se_var:+6.2f}")

rng = np.random.default_rng(13)
a1, b1 = analytic.gamma_parameters(x_g, V, 1)
fig, axes = plt.subplots(1, 3, figsize=(9, 2.8))
for ax, s in zip(axes, (1, 3, 16)):
    draws = rng.gamma(a1, 1 / b1, size=(20000, s)).mean(axis=1)   # mean of s one-sample gammas
    a, b = analytic.gamma_parameters(x_g, V, s)
    p = sps.kstest(draws, sps.gamma(a, scale=1 / b).cdf).pvalue
    grid = np.linspace(1e-3, np.quantile(draws, 0.995), 300)
    ax.hist(draws, bins=80, range=(0, grid[-1]), density=True, alpha=0.5)
    ax.plot(grid, sps.gamma(a, scale=1 / b).pdf(grid), "C1", label="Eq. 9 gamma")
    ax.plot(grid, sps.norm(x_g, np.sqrt(V / s)).pdf(grid), "C2:", label="normal")
    ax.set_title(f"s = {s}: KS p = {p:.2f}", fontsize=9)
axes[0].set_ylim(0, 4); axes[0].legend(fontsize=7)
plt.show()

# %% [markdown]
# Eq. 6 and Eq. 19 match the simulated means and variances. The z column tests the
# variance with the standard error implied by the gamma's excess kurtosis `6/α`; with
# four tests at a family-wise 0.1 %, |z| up to 3.5 is no evidence against the formula.
# The histograms compare the mean of `s` one-sample gammas with Eq. 9's gamma law (KS
# test) and with the moment-matched normal, which is far off at small `s`.

# %% [markdown]
# Lemma A.1 / Theorem 1: for kernels `K` that are *fixed* with respect to the new samples,
# `E[(K Y − x_g)²] = (K E[Y] − x_g)² + Σ K² Var[Y]` per pixel — the expected error of the
# future denoised image in closed form (`statmc.analytic.expected_kernel_loss`), for any
# law of the samples with those two moments. We check it on the toy renderer with *real*
# samples (exponential noise, fireflies): the kernels are GEM's scale selection on a
# 4-spp pilot render (`statmc.analytic.gem_kernels`, then frozen), the future adds
# `s = 12` spp, and Monte Carlo averages the true MSE over 300 independent continuations.

# %%
toy = ToyRenderer("mixed", width=48, height=48)
x_g, var_g = toy.true_mean(), toy.true_var()
pilot = toy.render_uniform(4, seed=1)
Kg = analytic.gem_kernels(pilot.mean, pilot.mean_var, n=pilot.n)   # frozen from here on
s_new = np.full(pilot.n.shape, 12.0)
closed = analytic.expected_kernel_loss(Kg, pilot.mean, pilot.n.astype(float), s_new, x_g, var_g)
bias, var = analytic.kernel_bias_variance(Kg, pilot.mean, pilot.n.astype(float), s_new, x_g, var_g)
mc = []
for s in range(300):
    future = pilot.merge(toy.render_uniform(12, seed=1000 + s, features=False))
    mc.append(np.mean((analytic.apply_kernels(Kg, future.mean) - x_g) ** 2))
m, lo, hi = t_interval(mc)
print(f"closed form (Lemma A.1): {closed:.5f} = bias² {np.mean(bias ** 2):.5f} + variance {np.mean(var):.5f}")
print(f"Monte Carlo, 300 futures: {m:.5f}, 99.9% interval [{lo:.5f}, {hi:.5f}]")
print(f"with Eq. 15's printed variance factor s/(s̄+s): {np.mean(bias ** 2 + var * 16):.5f} (rejected)")

# %% [markdown]
# ## Summary
#
# All five claims hold numerically on these inputs: γ tracks the wrong-stop rate only
# approximately (the paper's fit), Eq. 8 equals the solver to rounding, Eq. 9 equals the
# numeric minimiser and Eq. 8 matches Monte Carlo, SURE's mean equals the true MSE, and
# the gamma law and Lemma A.1 match simulation. The tests in `tests/` run the same checks
# with fixed seeds and stated p-value thresholds.
