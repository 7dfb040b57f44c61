"""MixNet with the mix_features inputs and random swapping (Firmino 2022 §4.3): the
measurement of docs/nn.md, "The mixing network with swapping (session 12)".

Usage (from the repository root; files go to $STATMC_MIXEXP, default out/bench/mixnet_swap):

    python bench/analysis_mixnet_swap.py data                       # 400 training renders
    python bench/analysis_mixnet_swap.py train ACT P STEPS [SEED]   # ACT sigmoid|f_act, P swap prob.
    python bench/analysis_mixnet_swap.py eval NAME [NAME ...]       # e.g. sigmoid_p0.5_s2000_seed0

--per-channel (anywhere on the train line): MixNet(..., per_channel=True), one α per pixel
and channel as the paper's network; the run's NAME ends in _pc, which eval reads back.
"""
import json, os, sys, time
import numpy as np
import torch, numba
torch.set_num_threads(1); numba.set_num_threads(1)
import statmc.nn as snn
from statmc.toy import ToyRenderer
from statmc import metrics, progressive
from scipy.stats import wilcoxon

D = os.environ.get("STATMC_MIXEXP", "out/bench/mixnet_swap")
os.makedirs(D, exist_ok=True)
SCENES = ["mixed", "edges", "texture", "fireflies", "gradient"]
SPPS = [8, 16, 32, 64, 128, 256, 512]
S = 32

def sample(scene, spp, seed):
    sc = ToyRenderer(scene, width=S, height=S)
    st = sc.render_uniform(spp, seed=seed)
    f = progressive.bind_denoiser("oidn", st)
    inp = snn.mix_inputs(st, f, rng=seed)
    return st, f, inp, sc.true_mean()

def data():
    rng = np.random.default_rng(12)
    rows = []
    for i in range(400):
        scene = SCENES[rng.integers(len(SCENES))]; spp = int(rng.choice(SPPS))
        st, f, inp, truth = sample(scene, spp, 100 + i)
        rows.append((snn.mix_features_of(inp, dtype=torch.float64)[0].numpy(), inp["x"], inp["y"], truth, scene, spp))
    np.savez(f"{D}/train.npz", feats=np.stack([r[0] for r in rows]),
             x=np.stack([r[1] for r in rows]), y=np.stack([r[2] for r in rows]),
             truth=np.stack([r[3] for r in rows]), scene=[r[4] for r in rows], spp=[r[5] for r in rows])

def nchw(a): return torch.from_numpy(np.ascontiguousarray(np.moveaxis(a, -1, 1))).float()

def smape(z, r):
    return torch.mean(torch.abs(z - r) / (z.abs() + r.abs() + 0.01))

def train(act, p, steps, seed=0, batch=8, lr=3e-3, lossname="relmse", per_channel=False):
    z = np.load(f"{D}/train.npz")
    F = torch.from_numpy(z["feats"]).float(); X, Y, T = nchw(z["x"]), nchw(z["y"]), nchw(z["truth"])
    net = snn.MixNet(activation=act, inputs="mix", per_channel=per_channel, seed=seed)
    g = np.random.default_rng(seed)
    def loss_fn(m, step):
        idx = torch.from_numpy(g.choice(len(F), batch, replace=False))
        return snn.swap_mix_loss(m, F[idx], X[idx], Y[idx], T[idx], p=p, loss=smape if lossname == "smape" else snn.relmse_loss)
    run = snn.train(net, loss_fn, steps, lr=lr, seed=seed)
    name = f"{act}_p{p}_s{steps}_seed{seed}" + ("" if lossname == "relmse" else "_" + lossname) + ("" if lr == 3e-3 else f"_lr{lr}") + ("_pc" if per_channel else "")
    torch.save(net.state_dict(), f"{D}/{name}.pt")
    L = run["losses"]
    print(name, f"{run['seconds']:.1f}s", "loss first50", np.mean(L[:50]).round(4), "last50", np.mean(L[-50:]).round(4))

def load(name, act):
    net = snn.MixNet(activation=act, inputs="mix", per_channel=name is not None and name.endswith("_pc"))
    if name is not None:
        net.load_state_dict(torch.load(f"{D}/{name}.pt")); net.eval()
    return net

def evaluate(names):
    nets = {n: load(None if n.startswith("untrained") else n, ("f_act" if n.startswith("f_act") else "sigmoid") if not n.startswith("untrained") else n.split("-")[1]) for n in names}
    res = {k: [] for k in ["x", "y", "eq9"] + [f"{n}:gated" for n in names] + [f"{n}:raw" for n in names]}
    amean = {n: [] for n in names}; cons = {n: [] for n in names}
    meta = []
    for scene in SCENES:
        for spp in [8, 32, 128, 512]:
            for s in range(4):
                seed = 50_000 + 100 * SCENES.index(scene) + 10 * spp + s
                st, f, inp, truth = sample(scene, spp, seed)
                x, y = inp["x"], inp["y"]
                res["x"].append(metrics.relmse(x, truth)); res["y"].append(metrics.relmse(y, truth))
                res["eq9"].append(metrics.relmse(progressive.progressive_denoise(st, f, rng=seed), truth))
                feats = snn.mix_features_of(inp)
                for n, net in nets.items():
                    a = net.alpha_from(inp)
                    res[f"{n}:raw"].append(metrics.relmse(x + (a if a.ndim == 3 else a[..., None]) * (y - x), truth))
                    res[f"{n}:gated"].append(metrics.relmse(progressive.progressive_denoise(st, f, alpha=net.alpha_from, rng=seed), truth))
                    amean[n].append(a.mean())
                    with torch.no_grad():
                        cons[n].append(float(net.swap_consistency(feats).abs().mean()))
                meta.append((scene, spp, seed))
    res = {k: np.array(v) for k, v in res.items()}
    spp = np.array([m[1] for m in meta])
    out = {"res": {k: v.tolist() for k, v in res.items()}, "meta": meta,
           "amean": {k: np.array(v).tolist() for k, v in amean.items()}, "cons": {k: np.array(v).tolist() for k, v in cons.items()}}
    json.dump(out, open(f"{D}/eval.json", "w"))
    print("mean relMSE per spp:", "  ".join(f"{k}" for k in [8, 32, 128, 512]))
    for k, v in res.items():
        print(f"{k:40s}", " ".join(f"{v[spp == q].mean():.5f}" for q in [8, 32, 128, 512]), f"all {v.mean():.5f}")
    for n in names:
        print(n, "mean alpha", np.mean(amean[n]).round(3), "swap dev |a(x,y)+a(y,x)-1|", np.mean(cons[n]).round(4))
        for b in ["x", "y", "eq9"]:
            for kind in ["gated", "raw"]:
                v = res[f"{n}:{kind}"]; w = res[b]
                p = wilcoxon(v, w, alternative="less").pvalue if np.any(v != w) else 1.0
                per = " ".join(f"{int((v[spp == q] < w[spp == q]).sum())}/{int((spp == q).sum())}" for q in [8, 32, 128, 512])
                print(f"  {kind} vs {b}: wins {(v < w).sum()}/{len(v)} (per spp {per}) ratio {v.mean() / w.mean():.3f} p_less={p:.2g}")
    for n in names:                     # per-channel network against its per-pixel twin
        if n.endswith("_pc") and n[:-3] in names:
            v, w = res[f"{n}:gated"], res[f"{n[:-3]}:gated"]
            per = " ".join(f"{int((v[spp == q] < w[spp == q]).sum())}/{int((spp == q).sum())}" for q in [8, 32, 128, 512])
            print(f"{n} vs {n[:-3]} (gated): wins {(v < w).sum()}/{len(v)} (per spp {per}) ratio {v.mean() / w.mean():.3f}"
                  f" p_less={wilcoxon(v, w, alternative='less').pvalue:.2g} p_greater={wilcoxon(v, w, alternative='greater').pvalue:.2g}")

if __name__ == "__main__":
    pc = "--per-channel" in sys.argv
    sys.argv = [a for a in sys.argv if a != "--per-channel"]
    cmd = sys.argv[1]
    t = time.time()
    if cmd == "data": data()
    elif cmd == "train": train(sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]) if len(sys.argv) > 5 else 0, lossname=sys.argv[6] if len(sys.argv) > 6 else "relmse", lr=float(sys.argv[7]) if len(sys.argv) > 7 else 3e-3, per_channel=pc)
    elif cmd == "eval": evaluate(sys.argv[2:])
    print("seconds", round(time.time() - t, 1))
