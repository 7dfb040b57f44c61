# %% [markdown]
# # Learned weights in the statistical kernels
#
# The product's third use: small networks whose outputs — per-pixel kernel weights,
# mixing parameters, sampling logits — plug into `statmc`'s statistical kernels. They
# live in `statmc.nn` (the `nn/` folder, PyTorch CPU; docs/nn.md), which also holds the
# differentiable twins of the kernels they feed, the one input builder
# (`pixel_features`, from a `PixelStats`) and a small training helper. Two of its
# networks are used here:
#
# 1. a **kernel-predicting network** (`statmc.nn.KernelNet`): a 5×5 softmax kernel per pixel (the classical
#    counterpart is GEM's per-pixel choice among Gaussian kernels, Rousselle et al.
#    2011). Its kernels are exported as an `(H, W, 5, 5)` array and used by
#    `statmc.analytic.apply_kernels` and by Salehi et al. 2022's closed-form expected
#    loss of a future render (Lemma A.1, `statmc.analytic.expected_kernel_loss`);
# 2. a **mixing network** for progressive denoising (`statmc.nn.MixNet`; Firmino et al.
#    2022, §4.3, learn α with a network): its α goes into `statmc.progressive.progressive_denoise(...,
#    alpha=...)`, through the same Student-t gate as the classical α of Eq. 9.
#
# Both train for **a few dozen steps** on the analytic toy renderer (`statmc.toy`), whose
# exact per-pixel truth serves as the target, on the CPU in seconds. That is far too
# little training, on far too little data (one procedural scene), to say anything about
# learned versus classical methods in general: what this notebook shows is the plumbing
# — shapes, conventions, where the outputs plug in — and honest numbers for these tiny
# networks, including on a scene they never saw.

# %%
import time

import numpy as np
import matplotlib.pyplot as plt
import torch

from statmc import analytic, gem, metrics, progressive
from statmc import nn as snn
from statmc.toy import ToyRenderer

torch.set_num_threads(2)
plt.rcParams["figure.dpi"] = 80
t_start = time.perf_counter()

H = W = 64
train_scene = ToyRenderer("mixed", width=W, height=H)
truth = train_scene.true_mean()
SPP = 8
to_tensor = snn.image_to_tensor      # (H, W, C) numpy -> (1, C, H, W) tensor: statmc is channel-last, torch is not

# %% [markdown]
# ## 1. A kernel-predicting network
#
# `statmc.nn.KernelNet`: three convolutions map the 12 input planes of
# `statmc.nn.pixel_features` (log radiance, log relative variance of the mean, albedo,
# normal) to 25 logits per pixel; a softmax turns them into a normalised 5×5 kernel.
# `KernelNet.denoise` applies them with `statmc.nn.apply_kernels`, the differentiable
# twin of `statmc.analytic.apply_kernels` (same convention: `out[y, x] = Σ K[y, x, dy, dx] ·
# img[y + dy − 2, x + dx − 2]`, taps outside the image dropped; tests/test_nn.py checks
# the two agree). The loss is relMSE (`statmc.nn.relmse_loss`, ε = 0.01) against the
# toy's exact truth; `statmc.nn.train` runs Adam, and every step sees a fresh 8-spp
# render (new seed).

# %%
knet = snn.KernelNet(width=24, seed=0)
target = to_tensor(truth)


def kernel_loss(net, step):
    st = train_scene.render_uniform(SPP, seed=step)
    return snn.relmse_loss(net.denoise(snn.pixel_features(st), to_tensor(st.mean)), target)


run = snn.train(knet, kernel_loss, 60, lr=3e-3, seed=0)
losses = run["losses"]
print(f"{knet.n_parameters()} parameters; 60 steps in {run['seconds']:.1f} s; training relMSE "
      f"{losses[0]:.4f} -> {np.mean(losses[-10:]):.4f} (mean of the last 10 steps)")
learned_kernels = knet.kernels     # PixelStats -> statmc's (H, W, 5, 5) float64 kernels

# %% [markdown]
# Evaluation on renders with seeds never used in training, against the classical
# counterparts: the box filter (pixel means) and GEM's reconstruction (its final,
# pooled-bias selector, `statmc.gem.reconstruct`). The learned kernels are applied with
# `statmc.analytic.apply_kernels`; the first line checks it agrees with the torch twin.
# Then the same networks on a toy scene they never saw ("edges": checkerboard and a
# disc, gamma noise).

# %%
def evaluate(scene, seeds):
    rows = []
    for s in seeds:
        st = scene.render_uniform(SPP, seed=s)
        K = learned_kernels(st)
        ref = scene.true_mean()
        rows.append((metrics.relmse(st.mean, ref),
                     metrics.relmse(gem.reconstruct(st.mean, st.mean_var, n=st.n), ref),
                     metrics.relmse(analytic.apply_kernels(K, st.mean), ref)))
    return np.array(rows)


st = train_scene.render_uniform(SPP, seed=10_001)
with torch.no_grad():
    torch_out = snn.tensor_to_image(knet.denoise(snn.pixel_features(st), to_tensor(st.mean)))
print("max |statmc.apply_kernels − torch twin| =",
      f"{np.abs(analytic.apply_kernels(learned_kernels(st), st.mean) - torch_out).max():.1e}")

held_out = range(10_000, 10_010)
res = {"mixed (training scene, new noise)": evaluate(train_scene, held_out),
       "edges (unseen scene)": evaluate(ToyRenderer("edges", width=W, height=H), held_out)}
print(f"\nrelMSE at {SPP} spp, mean over 10 held-out renders")
print(f"{'':>36}{'box':>9}{'GEM':>9}{'learned 5x5':>13}")
for name, r in res.items():
    m = r.mean(0)
    print(f"{name:>36}{m[0]:9.4f}{m[1]:9.4f}{m[2]:13.4f}")

# %%
st = train_scene.render_uniform(SPP, seed=10_000)
K = learned_kernels(st)
fig, axes = plt.subplots(1, 5, figsize=(12, 2.8))
panels = [("8 spp", st.mean), ("GEM", gem.reconstruct(st.mean, st.mean_var, n=st.n)),
          ("learned 5x5 kernels", analytic.apply_kernels(K, st.mean)), ("truth", truth)]
for ax, (name, img) in zip(axes, panels):
    ax.imshow(np.clip(img / np.quantile(truth, 0.99), 0, 1) ** (1 / 2.2))
    ax.set_title(name, fontsize=9); ax.axis("off")
im = axes[4].imshow(K[:, :, 2, 2], cmap="magma")
axes[4].set_title("centre weight K[·,·,2,2]", fontsize=9); axes[4].axis("off")
fig.colorbar(im, ax=axes[4], fraction=0.046)
plt.tight_layout(); plt.show()

fig, ax = plt.subplots(figsize=(4, 2.8))
ax.semilogy(losses); ax.set_xlabel("step"); ax.set_ylabel("training relMSE")
plt.show()

# %% [markdown]
# ## The learned kernels in Salehi et al.'s closed-form expected loss
#
# Kernels predicted from a 4-spp pilot render and then **frozen** satisfy the condition
# of Lemma A.1 (Salehi et al. 2022): their expected error after adding `s` samples has a
# closed form, bias² + variance, from the pilot and the per-pixel moments. Here with the
# toy's exact moments; in a renderer they would be estimated (that is what the
# expected-error sampler does, `statmc.analytic.expected_error_sampler`). The same for
# GEM's kernels of the same pilot (`statmc.analytic.gem_kernels`, adaptive bank), and a
# Monte Carlo check over 100 real continuations of the pilot. (The network was trained
# on 8-spp inputs, not 4: one more reason not to read much into the comparison.)

# %%
x_g, var_g = train_scene.true_mean(), train_scene.true_var()
pilot = train_scene.render_uniform(4, seed=20_000)
s_bar = pilot.n.astype(float)
kernels = {"learned": learned_kernels(pilot),
           "GEM": analytic.gem_kernels(pilot.mean, pilot.mean_var, n=pilot.n)}
print(" s new   " + "".join(f"{name:>12}" for name in kernels))
for s in (4, 12, 60):
    vals = [analytic.expected_kernel_loss(Kk, pilot.mean, s_bar, float(s), x_g, var_g,
                                          loss="mrse") for Kk in kernels.values()]
    print(f"{s:6d}   " + "".join(f"{v:12.4f}" for v in vals))
mc = [metrics.relmse(analytic.apply_kernels(kernels["learned"],
                                            pilot.merge(train_scene.render_uniform(12, seed=30_000 + i,
                                                                                   features=False)).mean), x_g)
      for i in range(100)]
print(f"Monte Carlo, learned kernels, s = 12: {np.mean(mc):.4f} ± {np.std(mc, ddof=1) / 10:.4f} (1 se)")

# %% [markdown]
# Where the error is, by quadrant of the "mixed" scene (closed form at `s = 12`; the
# quadrants hold sharp shapes with exponential noise, a smooth Gaussian-noise gradient,
# a fine texture of period ~4 px with uniform noise, and fireflies):

# %%
quadrants = {"shapes": (slice(0, 32), slice(0, 32)), "gradient": (slice(0, 32), slice(32, 64)),
             "texture": (slice(32, 64), slice(0, 32)), "fireflies": (slice(32, 64), slice(32, 64))}
print(f"{'':>10}" + "".join(f"{q:>11}" for q in quadrants))
for name, Kk in kernels.items():
    b, v = analytic.kernel_bias_variance(Kk, pilot.mean, s_bar, 12.0, x_g, var_g)
    e = (b ** 2 + v) / (x_g ** 2 + 0.01)
    print(f"{name:>10}" + "".join(f"{e[q].mean():11.4f}" for q in quadrants.values()))

# %% [markdown]
# GEM chooses among isotropic Gaussians from a 4-spp pilot: on the texture it must blur
# (bias) or keep the noise, and on the firefly pixels the pilot's few samples mislead its
# choice, which then stays frozen. The network has learnt this particular image's
# quadrants; on the unseen "edges" scene above GEM is better.

# %% [markdown]
# ## 2. A mixing network for progressive denoising
#
# Firmino et al. 2022 (§4.3) predict the mixing α with a network. Here
# `statmc.nn.MixNet`, a tiny one (the same inputs plus, via `pixel_features(stats,
# extra=y)`, the denoised image `y` and its relative distance `|y − x|/(|x| + 0.1)`),
# outputs one α per pixel through a sigmoid; `y` is OIDN (CPU) with albedo and normal,
# bound to the render by `statmc.progressive.bind_denoiser`. Mixing matters when the
# render becomes better than the denoiser somewhere, i.e. at higher spp, so each of the
# 40 training steps draws its spp from 8, 32, 128 and 512; the loss is
# `relMSE(x + α(y − x))` against the truth, divided by OIDN's relMSE so that the low-spp
# steps, with errors 100× larger, do not drown the others.
# The classical counterpart is the default `progressive_denoise`: α from Eq. 9 with
# MC-SURE, then the Student-t gate. The network's α goes through the same gate
# (`alpha=`), and un-gated (`gate=False`) for comparison.

# %%
anet = snn.MixNet(seed=0)
spp_rng = np.random.default_rng(4)


def mix_loss(net, step):
    st = train_scene.render_uniform(int(spp_rng.choice([8, 32, 128, 512])), seed=40_000 + step)
    y = progressive.bind_denoiser("oidn", st)(st.mean.astype(np.float32))
    x_t, y_t = to_tensor(st.mean), to_tensor(y)
    # relative to OIDN's own error, so that the high-spp steps (small errors) count too
    return (snn.relmse_loss(net.mix(snn.pixel_features(st, extra=y), x_t, y_t), target)
            / snn.relmse_loss(y_t, target))


run = snn.train(anet, mix_loss, 40, lr=1e-2, seed=0)
print(f"{anet.n_parameters()} parameters; 40 steps in {run['seconds']:.1f} s")
learned_alpha = anet.alpha         # (PixelStats, y) -> (H, W) float64 α

# %%
def evaluate_alpha(scene, spp, seeds):
    rows = []
    for s in seeds:
        st = scene.render_uniform(spp, seed=s)
        f = progressive.bind_denoiser("oidn", st)
        y = f(st.mean.astype(np.float32))
        a = learned_alpha(st, y)
        ref = scene.true_mean()
        classical, info = progressive.progressive_denoise(st, f, rng=s, extra_output=True)
        rows.append((metrics.relmse(st.mean, ref), metrics.relmse(y, ref),
                     metrics.relmse(classical, ref),
                     metrics.relmse(progressive.progressive_denoise(st, f, alpha=a, rng=s), ref),
                     metrics.relmse(progressive.progressive_denoise(st, f, alpha=a, gate=False), ref),
                     np.mean(info["alpha_gated"]), a.mean()))
    return np.array(rows).mean(0)


print("relMSE, mean over 2 held-out renders; mean α of the classical (gated) and the network")
print(f"{'scene':>8}{'spp':>5}{'render':>9}{'OIDN':>9}{'Eq.9+gate':>11}{'net+gate':>10}"
      f"{'net, no gate':>14}{'α Eq.9':>8}{'α net':>7}")
for scene_name in ("mixed", "edges"):
    scene = train_scene if scene_name == "mixed" else ToyRenderer("edges", width=W, height=H)
    for spp in (8, 64, 256):
        m = evaluate_alpha(scene, spp, range(50_000, 50_002))
        print(f"{scene_name:>8}{spp:5d}" + "".join(f"{v:{w}.4f}" for v, w in zip(m[:5], (9, 9, 11, 10, 14)))
              + f"{m[5]:8.2f}{m[6]:7.2f}")
print(f"\nnotebook run time: {time.perf_counter() - t_start:.0f} s")

# %% [markdown]
# ## What this shows, and what it does not
#
# * The plumbing: a network's per-pixel kernels are an `(H, W, k, k)` array that
#   `statmc.analytic` applies and evaluates in closed form exactly like GEM's; a
#   network's α is an `(H, W)` array that `progressive_denoise` gates like Eq. 9's.
#   Layout conversions happen only at the boundary (`statmc.nn.layout`, the networks'
#   `kernels` and `alpha` methods).
# * The numbers come from a few dozen steps on one procedural scene, with the exact
#   truth as target. Where the learned kernels beat GEM on the training scene, that is
#   mostly the network fitting that image's statistics; on the unseen scene GEM wins.
#   The mixing network barely departs from "trust OIDN" in 40 steps, while Eq. 9 with
#   the gate needs no training and moves towards the render as spp grows. A real
#   comparison needs networks trained on many scenes (and, for renders without truth,
#   on high-spp references or with SURE-type losses) and evaluated on others.
# * The classical methods carry their guarantees on any scene: GEM's kernels, Eq. 9's α,
#   and the Student-t gate, which keeps progressive denoising convergent whatever α it
#   is given.
