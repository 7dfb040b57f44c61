"""Size of the β shrinkage of ``progressive.mixing_weights`` under a normal null, by Monte Carlo.

The shrinkage (docs/progressive.md, "Shrinkage"; our rule, not in Firmino et al. 2022/2023)
keeps β (factor ``(1 − z² se²/b²)₊ > 0``) where ``|b| > z·se``, ``b`` the smoothed
numerator of Eq. 10 and ``se = min(se_model, se_spread)``.  Under the null ``y = μ``
(unbiased denoiser) β should survive in ``P(|N(0,1)| > z) = 4.55 %`` of the points at
``z = 2``.  Fields as in tests/test_progressive.py::_h0_field: ``x = μ + σ·N(0,1)`` (one
normal draw shared by the channels, scaled per channel: perfectly correlated colour noise),
``σ̂² = σ² χ²_{n−1}/(n − 1)`` independent of ``x``, ``y = μ``, ``D = 0``, SURE ``(y − x)² − σ̂²``.

For each setting: the rate of ``|b| > z·se`` with se = the rule's minimum, the model alone,
the spread alone, the spread corrected for its (1 − Σk²) bias, and the exact standard
error (oracle ``√Var[b]``, from the normal model with the true σ²).  Points are taken on a
grid ``4·smooth`` pixels apart (kernel overlap ≈ exp(−4) = 1.8 %: nearly independent), so
the counts are binomial; 95 % Wilson intervals.  Also: the mean factor over all points
(how much of β leaks on average) and the z that gives the nominal rate for the min rule.

Run: ``nice -n 10 .venv/bin/python bench/analysis_shrink_size.py [--points 100000]``
"""

import argparse
import math
import os
import time

import numpy as np
from scipy import stats as sst

from statmc import progressive as pg
from statmc.filters import gaussian_kernel_1d


def wilson(k, m, level=0.95):
    q = sst.norm.ppf(0.5 + level / 2)
    p = k / m
    c = (p + q * q / (2 * m)) / (1 + q * q / m)
    h = q * math.sqrt(p * (1 - p) / m + q * q / (4 * m * m)) / (1 + q * q / m)
    return c - h, c + h


def null_field(rng, h, n, channels, smooth, relative_eps):
    shape1 = (h, h, 1)
    mu = np.full(shape1, 0.7) * np.linspace(1.0, 0.6, channels)
    sigma2 = np.full(shape1, 0.01) * np.linspace(1.0, 0.5, channels)
    x = mu + np.sqrt(sigma2) * rng.standard_normal(shape1)
    s2_hat = sigma2 * rng.chisquare(n - 1, shape1) / (n - 1)
    y = mu
    sure = (y - x) ** 2 - s2_hat
    _, info = pg.mixing_weights(x, y, s2_hat, sure, np.zeros_like(x), smooth=smooth,
                                relative_eps=relative_eps, n=np.full((h, h), n),
                                extra_output=True)
    step = int(round(4 * smooth))
    pick = (slice(step, -step, step), slice(step, -step, step), 0)
    se = np.minimum(info["se_model"], info["se_spread"])
    b = (info["bias_z"] * se)[pick].ravel()
    # oracle: Var[Σ_c w_c e_c] = 2(1 + 1/(n−1)) (Σ_c w_c σ_c²)² per point, times Σ k²
    w = 1.0 if relative_eps is None else 1.0 / (y * y + relative_eps)
    g = gaussian_kernel_1d(smooth)
    k2 = float((g * g).sum()) ** 2
    var_e = 2 * (1 + 1 / (n - 1)) * float(((w * sigma2).sum(axis=2)).ravel()[0]) ** 2
    oracle = math.sqrt(k2 * var_e)
    return (b, info["se_model"][pick].ravel(), info["se_spread"][pick].ravel(),
            info["shrink"][pick].ravel(), oracle, k2)


def run(setting, points, z, seed):
    n, channels, smooth, relative_eps = setting
    h = 512
    rng = np.random.default_rng(seed)
    bs, sms, sss, lams = [], [], [], []
    while sum(map(len, bs)) < points:
        b, sm, ss, lam, oracle, k2 = null_field(rng, h, n, channels, smooth, relative_eps)
        bs.append(b), sms.append(sm), sss.append(ss), lams.append(lam)
    b, sm, ss, lam = (np.concatenate(a) for a in (bs, sms, sss, lams))
    m = b.size
    rules = {"min (used)": np.minimum(sm, ss), "model": sm, "spread": ss,
             "min, spread/(1-Σk²)": np.minimum(sm, ss / math.sqrt(1 - k2)),
             "oracle √Var[b]": np.full(m, oracle)}
    out = {}
    for name, se in rules.items():
        k = int(np.sum(np.abs(b) > z * se))
        out[name] = (k / m, *wilson(k, m))
    zmin = np.abs(b) / np.minimum(sm, ss)
    z_nominal = float(np.quantile(zmin, 1 - 2 * sst.norm.sf(z)))
    return m, out, float(lam.mean()), float((lam > 0.5).mean()), z_nominal


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--z", type=float, default=pg.DEFAULT_SHRINK)
    ap.add_argument("--quick", action="store_true", help="only the default setting")
    a = ap.parse_args()
    nominal = 2 * sst.norm.sf(a.z)
    print(f"z = {a.z}: nominal two-sided rate {100 * nominal:.2f} %   "
          f"(load average {os.getloadavg()[0]:.2f})")
    # (n, channels, smooth, relative_eps); the first is the library default
    settings = [(64, 3, pg.DEFAULT_SMOOTH, pg.DEFAULT_RELATIVE_EPS),
                (4, 3, pg.DEFAULT_SMOOTH, pg.DEFAULT_RELATIVE_EPS),
                (16, 3, pg.DEFAULT_SMOOTH, pg.DEFAULT_RELATIVE_EPS),
                (1024, 3, pg.DEFAULT_SMOOTH, pg.DEFAULT_RELATIVE_EPS),
                (64, 1, pg.DEFAULT_SMOOTH, pg.DEFAULT_RELATIVE_EPS),
                (64, 1, 3.0, None),                      # the unit tests' setting
                (64, 3, 2.0, pg.DEFAULT_RELATIVE_EPS),
                (64, 3, 8.0, pg.DEFAULT_RELATIVE_EPS)]
    if a.quick:
        settings = settings[:1]
    for i, s in enumerate(settings):
        t0 = time.perf_counter()
        m, out, lam_mean, lam_half, z_nom = run(s, a.points, a.z, seed=1000 + i)
        print(f"\nn = {s[0]}, channels = {s[1]}, smooth = {s[2]}, relative_eps = {s[3]}: "
              f"{m} points ({time.perf_counter() - t0:.0f} s)")
        for name, (p, lo, hi) in out.items():
            flag = "" if lo <= nominal <= hi else ("  > nominal" if lo > nominal else "  < nominal")
            print(f"  {name:22s} {100 * p:6.3f} %  [{100 * lo:.3f}, {100 * hi:.3f}]{flag}")
        print(f"  mean factor {lam_mean:.4f}; factor > 0.5 at {100 * lam_half:.3f} %; "
              f"z for the nominal rate with the min rule: {z_nom:.3f}")


if __name__ == "__main__":
    main()
