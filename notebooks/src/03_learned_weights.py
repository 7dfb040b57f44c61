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
# 2. the **mixing network** of progressive denoising (Firmino et al. 2022, §4.3:
#    `statmc.nn.MixNet` on the paper's inputs, trained with its random swapping): its α
#    goes into `statmc.progressive.progressive_denoise(..., alpha=...)`, through the same
#    Student-t gate as the classical α of Eq. 9.
#
# They train on the analytic toy renderer (`statmc.toy`), whose exact per-pixel truth
# serves as the target, on the CPU in seconds: a few dozen steps on one scene for the
# kernels, 600 steps on 64 small renders of four scenes for the mixing network. That is
# far too little training, on far too little data, to say anything about learned versus
# classical methods in general: what this notebook shows is the plumbing — shapes,
# conventions, where the outputs plug in — and honest numbers for these tiny networks,
# including on scenes they never saw.

# %%
import time

import numpy as np
import matplotlib.pyplot as plt
import numba
import torch

from statmc import analytic, gem, metrics, progressive
from statmc import nn as snn
from statmc.toy import ToyRenderer

# one thread each for torch and statmc's numba kernels: the networks are tiny, and on a
# busy 2-core machine other thread counts made a training step 8-20x slower, 13 ms ->
# 110-270 ms (torch and numba share one OpenMP runtime; docs/nn.md, "Threads")
torch.set_num_threads(1)
numba.set_num_threads(1)
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
# ## 2. The mixing network of Firmino et al. 2022 (§4.3), with random swapping
#
# Progressive denoising mixes the render `x` with its denoised image `y = f(x)`,
# `z = x + α (y − x)`; Eq. 9 gives the α that minimises the expected error from three
# estimates: the variance of the mean σ² of `x`, SURE of `y` and the divergence
# `σ² f'(x)` (`statmc.progressive.mixing_weights`). §4.3 of the paper predicts α with a
# network instead, from these inputs:
#
# * **HDR, VAR, DEN, SURE, `σ² f'(x)`, `‖y − x‖²`**: `statmc.nn.mix_inputs(stats, denoiser)`
#   denoises the render and runs MC-SURE (`statmc.sure.mc_sure`); its dict is exactly the
#   one `progressive_denoise` hands to a callable `alpha`. `statmc.nn.mix_features_of`
#   turns it into planes (radiances through `log(1 + x)`, the rest through `arctan`);
# * the network `statmc.nn.MixNet(activation="f_act", inputs="mix", per_channel=True)`:
#   three outputs per pixel and channel and the paper's `f_act` (Eq. 19),
#   `α = (x1 − x2)/max(x3, ε)` (clamped to [0, 1] here);
# * **random swapping** during training: with probability 1/2 a sample's render and
#   denoised image trade places *with their error estimates* ((HDR, VAR) ↔ (DEN, SURE),
#   `statmc.nn.random_swap`), so that the network must output β of Eq. 10 for the same
#   target. The paper reports that without it the network "failed to converge to the
#   desired solution": it learns to always trust the denoiser, α = 1.
#
# The denoiser is OIDN on the CPU with the toy's albedo and normal
# (`statmc.progressive.bind_denoiser("oidn", stats)`). Training set: 64 renders of 32×32
# from four toy scenes at 8 to 512 spp, features computed once; 600 Adam steps on batches
# of 8 with `statmc.nn.swap_mix_loss` (relMSE against the exact truth), and the same
# network trained without the swap (`p=0`) for comparison. The paper's network has 6
# layers of 48 features and trained for about 10 hours; this one has about 5000
# parameters and trains in seconds.

# %%
S = 32                                          # the mixing network's renders are 32×32
MIX_SCENES = ["mixed", "edges", "texture", "fireflies"]
MIX_SPPS = [8, 32, 128, 512]
mix_scenes = {name: ToyRenderer(name, width=S, height=S) for name in MIX_SCENES + ["gradient"]}


def mix_sample(name, spp, seed):
    """A render, its OIDN denoiser and the mixing network's inputs (y, MC-SURE, ...)."""
    st = mix_scenes[name].render_uniform(spp, seed=seed)
    f = progressive.bind_denoiser("oidn", st)
    return st, f, snn.mix_inputs(st, f, rng=seed)


spp_rng = np.random.default_rng(1)
train_set = []
for i in range(64):
    name = MIX_SCENES[i % 4]
    _, _, inp = mix_sample(name, int(spp_rng.choice(MIX_SPPS)), seed=60_000 + i)
    train_set.append((inp, mix_scenes[name].true_mean()))
feats = torch.cat([snn.mix_features_of(inp) for inp, _ in train_set])       # (64, 18, 32, 32)
xs, ys, refs = (torch.cat([to_tensor(a) for a in arrays]) for arrays in
                ([inp["x"] for inp, _ in train_set], [inp["y"] for inp, _ in train_set],
                 [ref for _, ref in train_set]))

mix_nets = {}
for p in (0.5, 0.0):                            # with the paper's random swap, and without
    net = snn.MixNet(activation="f_act", inputs="mix", per_channel=True, seed=0)
    pick = np.random.default_rng(0)

    def swap_loss(model, step, p=p, pick=pick):
        idx = torch.from_numpy(pick.choice(len(feats), 8, replace=False))
        return snn.swap_mix_loss(model, feats[idx], xs[idx], ys[idx], refs[idx], p=p)

    run = snn.train(net, swap_loss, 600, seed=0)
    mix_nets[p] = net
    print(f"swap p = {p}: {net.n_parameters()} parameters; 600 steps in {run['seconds']:.1f} s; "
          f"training relMSE {np.mean(run['losses'][:30]):.4f} -> {np.mean(run['losses'][-30:]):.4f} "
          f"(first / last 30 steps)")
swap_net, plain_net = mix_nets[0.5], mix_nets[0.0]

# %% [markdown]
# Evaluation on 32 renders with noise seeds never used in training (the four training
# scenes × 8, 32, 128, 512 spp × 2 seeds), and 8 of the unseen "gradient" scene. The
# network's α goes into `progressive_denoise(stats, f, alpha=swap_net.alpha_from)`: the
# pipeline calls it with the `y`, MC-SURE and divergence that it then mixes, and applies the
# Student-t confidence gate (Eq. 12–18) to it as it does to Eq. 9's α. Baselines: OIDN alone,
# and the default `progressive_denoise` (Eq. 9 + gate), both with the same MC-SURE
# (same `rng`). The **swap consistency** is the mean of `|α(x, y) + α(y, x) − 1|`
# (`MixNet.swap_consistency`): 0 when swapping the inputs turns α into β = 1 − α, as it
# should. The p-values are one-sided Wilcoxon signed-rank tests over the renders.

# %%
from scipy.stats import wilcoxon


def evaluate_mix(names, seeds=(0, 1)):
    rows = []
    for name in names:
        for spp in MIX_SPPS:
            for i in seeds:
                seed = 70_000 + 1000 * list(mix_scenes).index(name) + 10 * spp + i
                st, f, inp = mix_sample(name, spp, seed)
                ref = mix_scenes[name].true_mean()
                eq9, info = progressive.progressive_denoise(st, f, rng=seed, extra_output=True)
                net_z = progressive.progressive_denoise(st, f, alpha=swap_net.alpha_from, rng=seed)
                with torch.no_grad():
                    f_in = snn.mix_features_of(inp)
                    dev = [float(m.swap_consistency(f_in).abs().mean()) for m in (swap_net, plain_net)]
                rows.append([spp, metrics.relmse(inp["x"], ref), metrics.relmse(inp["y"], ref),
                             metrics.relmse(eq9, ref), metrics.relmse(net_z, ref),
                             swap_net.alpha_from(inp).mean(),
                             (plain_net.alpha_from(inp) > 0.99).mean(), *dev,
                             info["alpha"].mean()])
    return np.array(rows)


mix_res = {"training scenes, new noise": evaluate_mix(MIX_SCENES),
           "unseen scene (gradient)": evaluate_mix(["gradient"])}
print(f"mean relMSE over {len(mix_res['training scenes, new noise']) // 4} renders per spp "
      "(training scenes, new noise); mean α before the gate")
print(f"{'spp':>5}{'render':>9}{'OIDN':>9}{'Eq.9+gate':>11}{'net+gate':>10}{'α Eq.9':>8}{'α net':>7}")
r = mix_res["training scenes, new noise"]
for spp in MIX_SPPS:
    m = r[r[:, 0] == spp].mean(0)
    print(f"{spp:5d}{m[1]:9.5f}{m[2]:9.5f}{m[3]:11.5f}{m[4]:10.5f}{m[9]:8.2f}{m[5]:7.2f}")
for label, r in mix_res.items():
    print(f"\n{label}, {len(r)} renders: mean relMSE OIDN {r[:, 2].mean():.5f}, "
          f"Eq. 9 + gate {r[:, 3].mean():.5f}, net + gate {r[:, 4].mean():.5f}")
    for j, base in ((2, "OIDN alone"), (3, "Eq. 9 + gate")):
        print(f"  net + gate vs {base}: ratio {r[:, 4].mean() / r[:, j].mean():.3f}, "
              f"{int((r[:, 4] < r[:, j]).sum())}/{len(r)} wins, "
              f"p (net better) = {wilcoxon(r[:, 4], r[:, j], alternative='less').pvalue:.2g}")
    print(f"  swap consistency |α(x,y) + α(y,x) − 1|: {r[:, 7].mean():.3f} with the swap, "
          f"{r[:, 8].mean():.3f} without; the network trained without the swap has "
          f"α > 0.99 at {100 * r[:, 6].mean():.1f} % of the pixels")

# %% [markdown]
# The α maps of one held-out render ("mixed", 128 spp; channel mean): the swap-trained
# network's α before the gate, the network trained without the swap, and Eq. 9's α
# (before and after the gate) — in the pipeline's own `extra_output`.

# %%
seed = 70_000 + 10 * 128 + 5
st, f, inp = mix_sample("mixed", 128, seed)
_, info_net = progressive.progressive_denoise(st, f, alpha=swap_net.alpha_from, rng=seed,
                                              extra_output=True)
_, info_eq9 = progressive.progressive_denoise(st, f, rng=seed, extra_output=True)
scale = np.quantile(mix_scenes["mixed"].true_mean(), 0.99)
fig, axes = plt.subplots(1, 6, figsize=(14, 2.6), layout="constrained")
for ax, (name, img) in zip(axes[:2], [("128 spp render", inp["x"]), ("OIDN", inp["y"])]):
    ax.imshow(np.clip(img / scale, 0, 1) ** (1 / 2.2))
    ax.set_title(name, fontsize=9); ax.axis("off")
maps = [("α, swap-trained net", info_net["alpha"]), ("α, net without swap", plain_net.alpha_from(inp)),
        ("α, Eq. 9", info_eq9["alpha"]), ("α, Eq. 9 gated", info_eq9["alpha_gated"])]
for ax, (name, a) in zip(axes[2:], maps):
    im = ax.imshow(a.mean(axis=2), cmap="viridis", vmin=0, vmax=1)
    ax.set_title(name, fontsize=9); ax.axis("off")
fig.colorbar(im, ax=axes[2:], shrink=0.9)
plt.show()
print(f"notebook run time: {time.perf_counter() - t_start:.0f} s")

# %% [markdown]
# Read the maps with the table: both α maps trust OIDN (α ≈ 1) where it is good and move
# towards the render elsewhere; the network's map is noisier, since Eq. 9 averages its
# estimates over σ = 4 px (`DEFAULT_SMOOTH`) and the network sees a 5×5 neighbourhood.
# The network trained without the swap gives α ≈ 1 at every pixel: its mix is OIDN.

# %% [markdown]
# ## What this shows, and what it does not
#
# * The plumbing: a network's per-pixel kernels are an `(H, W, k, k)` array that
#   `statmc.analytic` applies and evaluates in closed form exactly like GEM's; a
#   network's α is an `(H, W)` or `(H, W, C)` array (or a callable on the pipeline's own
#   `y` and MC-SURE, `alpha_from`) that `progressive_denoise` gates like Eq. 9's. Layout
#   conversions happen only at the boundary (`statmc.nn.layout`, the networks'
#   `kernels` and `alpha` methods).
# * The numbers come from short training with the exact truth as target. Where the
#   learned kernels beat GEM on the training scene, that is mostly the network fitting
#   that image's statistics; on the unseen scene GEM wins.
# * The mixing network: the random swap is what makes it learn a mix. Trained without it,
#   the network outputs α ≈ 1 everywhere — it copies OIDN, as the paper reports — and is
#   not swap-consistent at all; with it, α falls from about 1 at 8 spp towards 1/2 at 512
#   spp, like Eq. 9's, and the gated mix beats OIDN alone on the training scenes (not at
#   8 spp, where OIDN is hard to improve on). It does **not** beat Eq. 9 + gate, which
#   needs no training: at this size the two are about even on new noise, and Eq. 9 is
#   ahead on the unseen scene. docs/nn.md has the larger measurement (400 renders, 2000
#   steps, 80 held-out renders): there too the swap-trained networks beat OIDN (0.84–0.90×)
#   but not reliably Eq. 9 + gate. A real comparison needs networks of the paper's size
#   trained on many scenes (and, for renders without truth, on high-spp references or with
#   SURE-type losses) and evaluated on others.
# * The classical methods carry their guarantees on any scene: GEM's kernels, Eq. 9's α,
#   and the Student-t gate, which keeps progressive denoising convergent whatever α it
#   is given.
