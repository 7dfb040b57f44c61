"""Mitsuba 3 backend: exact per-pixel counts, statistics against mi.render, bad input.

Statistical checks use fixed seeds and one-sample t-tests across pixels (pixels hold
disjoint samples, so they are independent).  Each per-pixel statistic has expectation
exactly 0 under the null hypothesis: it is either a difference of two unbiased estimates,
or such a difference divided by a scale taken from an *independent* render (a scale from
the same samples would bias a t-statistic under skewed radiance).
"""

from __future__ import annotations

import os
import sys
import warnings

import numpy as np
import pytest
from scipy import stats as sps

from _memory import traced_peak
from statmc import InputError
from statmc.errors import FileFormatError
from statmc import mitsuba_backend as mb
from statmc.scenes import BUILTIN_SCENES, load_scene_dict

pytestmark = pytest.mark.mitsuba

ALPHA = 1e-3      # per test; a handful of tests, so the family-wise rate stays below 1 %
SIZE = 32


def _ttest_zero(x, what):
    """One-sample t-test of E[x] = 0; returns p, with a useful message on failure."""
    x = np.asarray(x, np.float64).ravel()
    x = x[np.isfinite(x)]
    res = sps.ttest_1samp(x, 0.0)
    msg = (f"{what}: mean {x.mean():.4g} ± {x.std(ddof=1) / np.sqrt(x.size):.3g} over {x.size} "
           f"pixels, t = {res.statistic:.3f}, p = {res.pvalue:.3g}")
    print(msg)      # shown by pytest when a test fails (or with -s)
    return res.pvalue, msg


@pytest.fixture(scope="module")
def cornell():
    return mb.MitsubaRenderer("cornell-box", width=SIZE, height=SIZE)


@pytest.fixture(scope="module")
def mi(cornell):
    return cornell._mi


@pytest.fixture(scope="module")
def pilot(cornell):
    """Independent per-pixel sample variance, used only as a scale (seed not reused)."""
    return cornell.render_uniform(128, seed=999, features=False).sample_var


@pytest.fixture(scope="module")
def reference(cornell, mi):
    """High-spp mi.render reference (box filter), 2048 spp."""
    mi.set_variant(cornell.variant)
    return np.asarray(mi.render(cornell._scene, spp=2048, seed=7), np.float64)[..., :3]


def _ensure_variant(r):
    if r._mi.variant() != r.variant:
        r._mi.set_variant(r.variant)


# ------------------------------------------------------------------ agreement with mi.render
def test_uniform_counts_match_mi_render(cornell, mi, pilot):
    spp, k = 16, 8
    ours = cornell.render_uniform(spp, seed=11, features=False)
    assert np.array_equal(ours.n, np.full((SIZE, SIZE), spp))
    _ensure_variant(cornell)
    imgs = np.stack([np.asarray(mi.render(cornell._scene, spp=spp, seed=100 + j), np.float64)[..., :3]
                     for j in range(k)])
    mi_mean = imgs.mean(0)
    mi_var_of_image = imgs.var(0, ddof=1)            # variance of one spp-sample image
    scale = pilot / spp                              # independent of both renders
    ok = (scale > 0).all(-1)
    assert ok.mean() > 0.5

    # 1) means agree: z = (ours - mi) / sd, sd from the independent pilot
    z = (ours.mean - mi_mean) / np.sqrt(pilot * (1 / spp + 1 / (spp * k)) + 1e-300)
    p, msg = _ttest_zero(z[ok].mean(-1), "mean difference ours - mi.render (z)")
    assert p > ALPHA, msg
    # 2) variance of the mean agrees: our s²/n vs the spread of mi.render images
    d = (ours.mean_var - mi_var_of_image) / (scale + 1e-300)
    p, msg = _ttest_zero(d[ok].mean(-1), "variance of the mean ours - mi.render")
    assert p > ALPHA, msg
    # the t-tests have power: a 15 % shift of the mean is rejected
    z_bad = (1.15 * ours.mean - mi_mean) / np.sqrt(pilot * (1 / spp + 1 / (spp * k)) + 1e-300)
    assert _ttest_zero(z_bad[ok].mean(-1), "shifted")[0] < ALPHA


# ------------------------------------------------------------------ arbitrary count maps
def _random_counts(rng, h, w):
    kind = rng.random((h, w))
    counts = rng.integers(2, 64, size=(h, w))
    counts[kind < 0.15] = 0
    counts[(kind >= 0.15) & (kind < 0.25)] = 1
    counts[kind > 0.95] = rng.integers(256, 1025, size=int((kind > 0.95).sum()))
    return counts


def test_random_counts_exact_and_consistent(cornell, pilot, reference):
    rng = np.random.default_rng(3)
    counts = _random_counts(rng, SIZE, SIZE)
    # small chunks: pixels are split across chunks, and chunks must be independent
    r = mb.MitsubaRenderer(cornell._scene, chunk_samples=5003)
    stats = r.render(counts, seed=21, features=False)
    assert stats.n.dtype == np.int64
    assert np.array_equal(stats.n, counts)
    assert stats.meta["chunks"] == -(-int(counts.sum()) // 5003)
    assert np.all(stats.mean[counts == 0] == 0)

    n = counts[..., None].astype(np.float64)
    ok = (counts >= 1) & (pilot > 0).all(-1)
    # 1) unbiased: standardised error against the reference, sd from the pilot
    z = (stats.mean - reference) / np.sqrt(pilot * (1 / np.maximum(n, 1) + 1 / 2048))
    p, msg = _ttest_zero(z[ok].mean(-1), "error vs reference (z)")
    assert p > ALPHA, msg
    # 2) the squared error is predicted by sample_var / n (+ the reference's own variance),
    #    per pixel averaged over 4 independent renders of the same counts (for power)
    ok2 = ok & (counts >= 2)
    w = reference ** 2 + 1e-2                        # independent positive scale
    renders = [stats] + [r.render(counts, seed=s, features=False) for s in (22, 23, 24)]
    sq = np.mean([(st.mean - reference) ** 2 for st in renders], axis=0)
    mv = np.mean([st.mean_var for st in renders], axis=0)
    d = (sq - mv - pilot / 2048) / w
    p, msg = _ttest_zero(d[ok2].mean(-1), "squared error - mean_var")
    assert p > ALPHA, msg
    # ... and the test would notice mean_var off by 30 %
    d_bad = (sq - 0.7 * mv - pilot / 2048) / w
    assert _ttest_zero(d_bad[ok2].mean(-1), "scaled")[0] < ALPHA


def test_channel_covariance_predicts_the_cross_error(cornell):
    """Two independent renders a, b with the same random counts (pixels split across
    chunks): ``E[(a_R − b_R)(a_G − b_G)] = Cov_a + Cov_b`` of the means, per channel pair,
    so ``(Δ_a Δ_b − mean_cov_a − mean_cov_b)/scale`` has mean 0 (scale from an independent
    render).  Power: the same test rejects a zero covariance (a diagonal ``mean_var``).
    Deterministic checks: diagonal = ``m2``, Cauchy-Schwarz, ``cross=False`` drops it."""
    rng = np.random.default_rng(4)
    counts = _random_counts(rng, SIZE, SIZE)
    r = mb.MitsubaRenderer(cornell._scene, chunk_samples=5003)
    a = r.render(counts, seed=31, features=False)
    b = r.render(counts, seed=32, features=False)
    scale_src = r.render_uniform(64, seed=33, features=False)
    k = np.arange(3)
    for s_ in (a, b):
        assert np.array_equal(s_.m2_cross[..., k, k], s_.m2)
        bound = np.sqrt(s_.m2[..., :, None] * s_.m2[..., None, :])
        assert np.all(np.abs(s_.m2_cross) <= bound * (1 + 1e-6) + 1e-9 * s_.m2.max())
    ok = (counts >= 2) & (scale_src.sample_var > 0).all(-1)
    w = scale_src.sample_var / 64 + 1e-4                     # independent positive scale
    d = a.mean - b.mean
    for ca, cb in ((0, 1), (0, 2), (1, 2)):
        ww = np.sqrt(w[..., ca] * w[..., cb])
        prod = d[..., ca] * d[..., cb]
        pred = a.mean_cov[..., ca, cb] + b.mean_cov[..., ca, cb]
        p, msg = _ttest_zero(((prod - pred) / ww)[ok], f"cross error - mean_cov ({ca}{cb})")
        assert p > ALPHA, msg
        assert _ttest_zero((prod / ww)[ok], f"cross error, no covariance ({ca}{cb})")[0] < ALPHA
    c = r.render(counts, seed=31, features=False, cross=False)
    assert c.m2_cross is None
    np.testing.assert_allclose(c.m2, a.m2, rtol=1e-9, atol=1e-12)
    one = r.render(np.ones((SIZE, SIZE), np.int64), seed=1, features=False)
    assert np.all(one.m2_cross == 0)


def test_seeds_give_independent_renders(cornell, pilot, reference):
    spp = 8
    a = cornell.render_uniform(spp, seed=1, features=False)
    b = cornell.render_uniform(spp, seed=2, features=False)
    a2 = cornell.render_uniform(spp, seed=1, features=False)
    np.testing.assert_allclose(a2.mean, a.mean, rtol=1e-9, atol=1e-12)   # same seed, same image
    assert not np.allclose(a.mean, b.mean)
    # independent errors: E[(a - ref)(b - ref)] = 0.  Pearson's r across pixels is no test
    # here (skewed, heavy-tailed pixels); a t-test of the scaled products is.  Pixels that
    # see the light (reference >= 1, chosen from the independent reference) are left out:
    # their errors are binomial-skewed and dominate any sum.
    # Per pixel, the products are averaged over 4 pairs of seeds (1, 2), (3, 4), ... (power).
    ok = (reference < 1).all(-1) & (pilot > 0).all(-1)
    pairs = [(a, b)] + [(cornell.render_uniform(spp, seed=s, features=False),
                         cornell.render_uniform(spp, seed=s + 1, features=False))
                        for s in (3, 5, 7)]
    u = np.mean([((x.mean - reference) * (y.mean - reference) / (pilot / spp)).mean(-1)
                 for x, y in pairs], axis=0)
    p, msg = _ttest_zero(u[ok], "product of the errors of seeds 2i+1 and 2i+2")
    assert p > ALPHA, msg
    # ... and the test notices a correlation of 0.5 (half of the samples shared)
    u_bad = np.mean([((x.mean - reference) * (0.5 * (x.mean + y.mean) - reference)
                      / (pilot / spp)).mean(-1) for x, y in pairs], axis=0)
    assert _ttest_zero(u_bad[ok], "correlated")[0] < ALPHA


def test_zero_counts_and_progress(cornell, capsys):
    s = cornell.render(np.zeros((SIZE, SIZE), np.int64), features=False)
    assert s.total_samples == 0 and s.meta["chunks"] == 0
    assert np.all(s.mean == 0) and np.all(s.m2 == 0)
    s = cornell.render_uniform(2, progress=True, features=False)
    assert s.total_samples == 2 * SIZE * SIZE
    assert "mitsuba cornell-box" in capsys.readouterr().err


def test_meta_and_features(cornell):
    s = cornell.render_uniform(4, seed=3, feature_spp=8)
    assert s.meta["variant"] == cornell.variant and s.meta["samples"] == 4 * SIZE * SIZE
    assert s.meta["seconds"] > 0 and s.meta["samples_per_second"] > 0
    assert s.meta["nonfinite_samples"] == 0
    assert s.albedo.shape == s.normal.shape == (SIZE, SIZE, 3)
    # the Cornell box's red wall has albedo (0.570068, 0.0430135, 0.0443706): left column
    np.testing.assert_allclose(s.albedo[SIZE // 2, 1], [0.570068, 0.0430135, 0.0443706], atol=1e-5)
    # ... whose normal is +x; the back wall, above the boxes, faces the camera: +z
    np.testing.assert_allclose(s.normal[SIZE // 2, 1], [1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(s.normal[10, 20], [0, 0, 1], atol=1e-5)
    np.testing.assert_allclose(s.albedo[10, 20], [0.885809, 0.698859, 0.666422], atol=1e-5)
    assert np.all(np.linalg.norm(s.normal, axis=-1) <= 1 + 1e-4)


# ------------------------------------------------------------------ built-in scenes
@pytest.mark.parametrize("name", sorted(BUILTIN_SCENES))
def test_builtin_scene_renders(name):
    r = mb.MitsubaRenderer(name, width=12, height=10)
    assert (r.height, r.width, r.channels, r.name) == (10, 12, 3, name)
    d = load_scene_dict(name, 12, 10)
    film = d["sensor"]["film"]
    assert film["rfilter"]["type"] == "box" and (film["width"], film["height"]) == (12, 10)
    assert d["integrator"]["type"] == "path"
    counts = np.arange(120).reshape(10, 12) % 5
    s = r.render(counts, seed=0, feature_spp=2)
    assert np.array_equal(s.n, counts)
    assert np.isfinite(s.mean).all() and (s.mean >= 0).all() and s.mean[counts > 0].max() > 0
    assert s.albedo.shape == (10, 12, 3) and np.isfinite(s.albedo).all()


# ------------------------------------------------------------------ XML scenes
XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/>
      <rfilter type="gaussian"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></shape>
  <emitter type="constant"/>
</scene>
"""


def test_xml_scene_with_size_override(tmp_path):
    path = tmp_path / "ball.xml"
    path.write_text(XML)
    with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
        r = mb.MitsubaRenderer(str(path))
    assert (r.height, r.width) == (30, 40)
    with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
        r = mb.MitsubaRenderer(path, width=9, height=7)
    assert (r.height, r.width, r.name) == (7, 9, str(path))
    s = r.render(np.full((7, 9), 3), seed=1, features=False)
    assert s.total_samples == 3 * 63
    # furnace: a convex white (albedo 1) diffuse sphere under a constant white sky sends
    # back exactly the sky's radiance, so every pixel's expectation is 1
    s = r.render_uniform(64, seed=2, features=False)
    p, msg = _ttest_zero((s.mean - 1.0).mean(-1), "furnace error")
    assert p > ALPHA, msg
    assert s.sample_var.max() > 0


# ------------------------------------------------------------------ bad input
def test_bad_counts_raise(cornell):
    good = np.ones((SIZE, SIZE))
    for bad, word in [(-good, "negative"), (np.full((SIZE, SIZE), np.nan), "NaN"),
                      (np.ones((SIZE, SIZE + 1)), "shape"), (np.ones(SIZE), "dimensions"),
                      (good * 0.5, "whole"), (np.full((SIZE, SIZE), np.inf), "Inf")]:
        with pytest.raises(InputError, match=word):
            cornell.render(bad)
    with pytest.raises(InputError, match="counts"):
        cornell.render(np.array([["a"]]))
    with pytest.raises(InputError, match="seed"):
        cornell.render(good, seed=-1)
    with pytest.raises(InputError, match="feature_spp"):
        cornell.render(good, feature_spp=0)
    with pytest.raises(InputError, match="spp"):
        cornell.render_uniform(1.5)


def test_bad_scene_raises(tmp_path):
    missing = str(tmp_path / "nope.xml")
    with pytest.raises(InputError, match="nope.xml"):
        mb.MitsubaRenderer(missing)
    with pytest.raises(InputError, match="cornell-box"):
        mb.MitsubaRenderer("no-such-scene")
    broken = tmp_path / "broken.xml"
    broken.write_text("<scene version='3.0.0'><shape type='sphere'")
    with pytest.raises(InputError, match="broken.xml"):
        mb.MitsubaRenderer(str(broken), width=8)
    with pytest.raises(InputError, match="width"):
        mb.MitsubaRenderer("cornell-box", width=0)
    with pytest.raises(InputError, match="chunk_samples"):
        mb.MitsubaRenderer("cornell-box", chunk_samples=0)
    with pytest.raises(InputError, match="scene"):
        mb.MitsubaRenderer(42)
    with pytest.raises(InputError, match="variant"):
        mb.MitsubaRenderer("cornell-box", variant="scalar_spectral")
    with pytest.raises(InputError, match="name"):
        load_scene_dict("nope")


def test_make_renderer_refuses_mitsuba_options_for_a_toy_scene():
    # regression: make_renderer's docstring offers sensor= and params=, and a toy scene
    # given one failed with ToyRenderer's TypeError (unexpected keyword argument)
    from statmc.renderers import make_renderer
    for option in ({"sensor": 0}, {"params": {"spp": 4}}, {"variant": "scalar_rgb"}):
        with pytest.raises(InputError, match=f"`{next(iter(option))}` is an option of Mitsuba "
                                             "scenes; 'toy:mixed' is an analytic toy scene"):
            make_renderer("toy:mixed", **option)


def test_python_integrator_rejected(cornell, mi):
    d = load_scene_dict("cornell-box", 8, 8)
    d["integrator"] = {"type": "prb"}
    with pytest.raises(InputError, match="PRBIntegrator, a Python integrator .*C\\+\\+ sampling "
                                         "integrators .*change the scene's <integrator>"):
        mb.MitsubaRenderer(mi.load_dict(d))


# ------------------------------------------------------------------ chunking (pure NumPy)
@pytest.mark.parametrize("chunk", [1, 7, 64, 1000, 10 ** 6])
def test_chunk_pixels_equals_repeat(chunk):
    rng = np.random.default_rng(chunk)
    counts = rng.integers(0, 9, size=300)
    counts[:5] = 0
    counts[-3:] = 0
    counts[100] = 500
    chunks = list(mb._chunk_pixels(counts, chunk))
    assert all(c.size <= chunk for c in chunks)
    assert sum(c.size == chunk for c in chunks) >= len(chunks) - 1
    np.testing.assert_array_equal(np.concatenate(chunks), np.repeat(np.arange(300), counts))
    assert list(mb._chunk_pixels(np.zeros(4, np.int64), chunk)) == []


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_chunk_samples_index_each_pixels_sequence(chunk):
    rng = np.random.default_rng(chunk)
    counts = rng.integers(0, 6, size=200)
    first = rng.integers(0, 50, size=200)
    parts = list(mb._chunk_samples(counts, first, chunk))
    pix = np.concatenate([p for p, _ in parts])
    index = np.concatenate([i for _, i in parts])
    np.testing.assert_array_equal(pix, np.repeat(np.arange(200), counts))
    want = np.concatenate([first[p] + np.arange(c) for p, c in enumerate(counts)])
    np.testing.assert_array_equal(index, want)


def test_sample_seeds_are_distinct_within_a_render_and_look_uniform():
    """Seeds are a keyed bijection of index·P + pixel: no two samples of one render share a
    stream while index < 2**32 / P (the former per-pixel scheme let ~N²/2³³ pairs of
    samples in different pixels share one); other seeds give other words."""
    P = 48 * 64
    pix = np.tile(np.arange(P, dtype=np.uint32), 1024)
    index = np.repeat(np.arange(1024), P)
    seeds = mb._sample_seeds(mb._seed_keys(3, mb._SALT_MAIN), P, pix, index)
    assert np.unique(seeds).size == seeds.size               # 3.1 M distinct words
    other = mb._sample_seeds(mb._seed_keys(4, mb._SALT_MAIN), P, pix, index)
    assert np.mean(seeds == other) < 1e-5
    # the words look uniform on 32 bits, also between consecutive pixels and indices
    bits = ((seeds[:, None] >> np.arange(32, dtype=np.uint32)) & 1).mean(0)
    assert np.all(np.abs(bits - 0.5) < 0.002), bits
    flips = ((seeds[1:] ^ seeds[:-1])[:, None] >> np.arange(32, dtype=np.uint32)) & 1
    assert np.all(np.abs(flips.mean(0) - 0.5) < 0.002)


def test_drjit_sample_seeds_equal_the_numpy_reference(cornell):
    """The seeds _render_jit forms inside Dr.Jit, fmix32(base[p] + g·P) ^ k2, equal
    _sample_seeds(pixel, first + rank) of the NumPy reference, chunk by chunk, also where
    the words wrap modulo 2**32."""
    if not cornell._jit:
        pytest.skip("needs a JIT variant")
    mi, dr = cornell._mi, cornell._dr
    _ensure_variant(cornell)
    rng = np.random.default_rng(8)
    counts = rng.integers(0, 9, size=500)
    first = rng.integers(0, 2 ** 31 - 10, size=500)
    k1, k2 = mb._seed_keys(17, mb._SALT_MAIN)
    base = mi.UInt32(mb._seed_bases(k1, counts, first))
    a = 0
    for (pix, index), pix2 in zip(mb._chunk_samples(counts, first, 97),
                                  mb._chunk_pixels(counts, 97)):
        g = (dr.arange(mi.UInt32, len(pix2)) + mi.UInt32(a)) * mi.UInt32(500)
        word = dr.gather(mi.UInt32, base, mi.UInt32(pix2)) + g
        got = np.asarray(mb._fmix32_drjit(mi, word) ^ mi.UInt32(k2))
        np.testing.assert_array_equal(got, mb._sample_seeds((k1, k2), 500, pix, index))
        a += pix2.size


def test_chunk_seeds_distinct():
    seeds = {mb._chunk_seed(s, salt, c) for s in range(20) for salt in (mb._SALT_MAIN, mb._SALT_FEATURES)
             for c in range(50)}
    assert len(seeds) == 20 * 2 * 50


# ------------------------------------------------------------------ LLVM discovery and fallback
def _touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return str(path)


def test_find_libllvm_picks_newest_supported(tmp_path, monkeypatch):
    gnu = tmp_path / "usr/lib/x86_64-linux-gnu"
    for name in ["libLLVM-14.so", "libLLVM-15.so.1", "libLLVM-18.so", "libLLVM-19.so",
                 "libLLVM-19.so.1", "libLLVM.so.19.1"]:
        _touch(gnu / name)
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(mb, "LLVM_SEARCH_PATTERNS", (str(gnu / "libLLVM-[0-9]*.so*"),
                                                    str(gnu / "libLLVM.so.[0-9]*")))
    assert mb.find_libllvm() == str(gnu / "libLLVM-19.so")
    # a newer one under /usr/lib/llvm-NN/ wins; its version comes from the folder
    newer = _touch(tmp_path / "usr/lib/llvm-21/lib/libLLVM.so.1")
    monkeypatch.setattr(mb, "LLVM_SEARCH_PATTERNS", mb.LLVM_SEARCH_PATTERNS
                        + (str(tmp_path / "usr/lib/llvm-[0-9]*/lib/libLLVM*.so*"),))
    assert mb.find_libllvm() == newer


def test_find_libllvm_env_and_too_old(tmp_path, monkeypatch):
    old = [_touch(tmp_path / n) for n in ["libLLVM-14.so", "libLLVM-15.so"]]
    monkeypatch.setattr(mb, "LLVM_SEARCH_PATTERNS", (str(tmp_path / "libLLVM-*.so*"),))
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert mb.find_libllvm() is None                      # only 14 and 15: too old
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", old[1])
    assert mb.find_libllvm() is None                      # env names a too-old one: ignored
    custom = _touch(tmp_path / "custom" / "libllvm-custom-build.so")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", custom)
    assert mb.find_libllvm() == custom                    # unknown version: trusted
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing-libLLVM-19.so"))
    good = _touch(tmp_path / "libLLVM-17.so")
    assert mb.find_libllvm() == good                      # env file missing: search
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", _touch(tmp_path / "x" / "libLLVM-16.so"))
    assert mb.find_libllvm() == str(tmp_path / "x" / "libLLVM-16.so")


def test_fallback_without_llvm_warns(monkeypatch):
    monkeypatch.setattr(mb, "find_libllvm", lambda: None)
    with pytest.warns(RuntimeWarning, match="apt-get install libllvm19"):
        assert mb._choose_auto_variant() == "scalar_rgb"
    with pytest.raises(InputError, match="libllvm19"):
        mb.setup_mitsuba("llvm_ad_rgb")


def test_import_statmc_does_not_import_mitsuba():
    import subprocess
    code = ("import sys, statmc, statmc.stats, statmc.scenes, statmc.mitsuba_backend; "
            "print('mitsuba' in sys.modules or 'drjit' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ}, check=True)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------------ per-sample streams
def _assert_same_samples(a, b, where=Ellipsis):
    """Equal per-pixel statistics, up to the order of the float64 sums."""
    np.testing.assert_array_equal(a.n[where], b.n[where])
    np.testing.assert_allclose(a.mean[where], b.mean[where], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(a.m2[where], b.m2[where], rtol=1e-9, atol=1e-14)


def _counts_pair(seed):
    rng = np.random.default_rng(seed)
    c1 = rng.integers(0, 6, (SIZE, SIZE))
    c2 = c1.copy()
    moved = np.zeros((SIZE, SIZE), bool)
    moved[16, 14] = moved[20, 12] = moved[SIZE - 1, 0] = True
    c1[16, 14] = 2
    c2[16, 14] = 5                    # 3 more samples in a lit pixel
    c2[20, 12] = 0
    c2[SIZE - 1, 0] += 1
    return c1, c2, moved


@pytest.mark.parametrize("variant", ["jit", "scalar_rgb"])
def test_moving_samples_changes_only_those_pixels(cornell, variant):
    """Sample j of pixel p depends on (seed, p, j) only: changing the counts of three
    pixels leaves the statistics of every other pixel as they were (they used to be
    re-randomised, because streams followed the position in the wavefront)."""
    r = cornell if variant == "jit" else mb.MitsubaRenderer("cornell-box", width=SIZE,
                                                            height=SIZE, variant=variant)
    try:
        c1, c2, moved = _counts_pair(1)
        a = r.render(c1, seed=3, features=False)
        b = r.render(c2, seed=3, features=False)
        _assert_same_samples(a, b, ~moved)
        lit = moved & (c1 > 0) & (c2 > 0)
        assert not np.allclose(a.mean[lit], b.mean[lit])
        # the common samples: the first min(c1, c2) samples of every pixel
        c = np.minimum(c1, c2)
        _assert_same_samples(r.render(c, seed=3, features=False),
                             r.render(c, seed=3, features=False, first_sample=None))
        other = r.render(c1, seed=4, features=False)
        both = (c1 > 0) & (a.mean.sum(-1) > 0)
        assert not np.allclose(a.mean[both], other.mean[both])
    finally:
        if variant != "jit":
            _ensure_variant(cornell)


def test_chunking_does_not_change_the_samples(cornell):
    """The wavefront is cut into chunks only to bound memory: with small chunks (pixels
    split across chunks, a pixel of 300 samples spanning several) the render holds the same
    samples as in one chunk."""
    rng = np.random.default_rng(4)
    counts = rng.integers(0, 9, (SIZE, SIZE))
    counts[16, 14] = 300
    first = rng.integers(0, 1000, (SIZE, SIZE))
    small = mb.MitsubaRenderer(cornell._scene, chunk_samples=97)
    for f in (None, first):
        a = small.render(counts, seed=9, features=False, first_sample=f)
        assert a.meta["chunks"] > 10
        _assert_same_samples(a, cornell.render(counts, seed=9, features=False, first_sample=f))


def test_memory_of_a_render_does_not_grow_with_its_chunks(cornell):
    """Dr.Jit's peak allocation over a render of 128 chunks is that of a render of 16 (and
    so for the albedo/normal pass): each chunk's memory goes back after it.  Before,
    Dr.Jit's allocation cache grew with every chunk until the render ended (here +80 %
    from 16 to 128 chunks; about 8 MB of resident memory per default chunk), and long
    renders filled the machine's memory."""
    if not cornell._jit:
        pytest.skip("the chunked wavefront is the JIT variants' path")
    dr = cornell._dr
    r = mb.MitsubaRenderer(cornell._scene, chunk_samples=2 ** 14)
    ones = np.ones((SIZE, SIZE), np.int64)

    def peak(spp, feature_spp=None):
        dr.detail.malloc_clear_statistics()
        out = r.render(spp * ones, seed=3, features=feature_spp is not None,
                       feature_spp=feature_spp or 1)
        return dr.detail.malloc_watermark(dr.JitBackend.LLVM), out.meta["chunks"]

    peak(16)                                            # compiles the kernels
    few, n_few = peak(256)
    many, n_many = peak(2048)
    assert (n_few, n_many) == (16, 128)
    assert many <= 1.05 * few, f"peak {many} B over {n_many} chunks, {few} B over {n_few}"
    peak(1, 16)
    few, _ = peak(1, 256)
    many, _ = peak(1, 2048)
    assert many <= 1.05 * few, f"albedo/normal pass: peak {many} B, {few} B with 16 chunks"


@pytest.mark.parametrize("variant", ["jit", "scalar_rgb"])
def test_first_sample_continues_the_sequence(cornell, variant):
    """Two passes, the second starting where the first stopped, merge to one render of
    the summed counts; a pass that restarts at 0 repeats the first pass's samples."""
    r = cornell if variant == "jit" else mb.MitsubaRenderer("cornell-box", width=SIZE,
                                                            height=SIZE, variant=variant)
    try:
        c1, c2, _ = _counts_pair(2)
        p1 = r.render(c1, seed=5, features=False)
        p2 = r.render(c2, seed=5, features=False, first_sample=c1)
        _assert_same_samples(p1.merge(p2), r.render(c1 + c2, seed=5, features=False))
        again = r.render(c1, seed=5, features=False, first_sample=np.zeros_like(c1))
        _assert_same_samples(p1, again)
    finally:
        if variant != "jit":
            _ensure_variant(cornell)


def test_adaptive_render_shares_samples_with_a_uniform_render(cornell):
    """adaptive_render continues every pixel's sequence: its result equals one render of
    its final counts with the same seed, so a uniform render of that seed holds the first
    min(n, spp) samples of every pixel (common random numbers between samplers)."""
    from statmc.adaptive import adaptive_render
    res = adaptive_render(cornell, 8, sampler="gem", initial_spp=4, iterations=2, seed=11)
    n = res.stats.n
    assert n.min() < 8 < n.max()
    _assert_same_samples(res.stats, cornell.render(n, seed=11, features=False))
    pilot = cornell.render(np.full(n.shape, 4), seed=11, features=False)
    _assert_same_samples(pilot, cornell.render(np.minimum(n, 4), seed=11, features=False))


def test_sample_bins_are_slices_of_one_render(cornell):
    """render_bins on the Mitsuba backend: bin b holds samples b*m .. (b+1)*m - 1 of every
    pixel, so the merged bins are one render of the seed, and the bins are disjoint."""
    from statmc.pipeline import merge_bins, render_bins
    bins = render_bins(cornell, 8, 4, seed=6)
    whole = cornell.render(np.full((SIZE, SIZE), 8), seed=6, features=False)
    _assert_same_samples(merge_bins(bins), whole)
    lit = whole.mean.sum(-1) > 0
    assert not np.allclose(bins[0].mean[lit], bins[1].mean[lit])


def test_first_sample_bad_input(cornell):
    c = np.ones((SIZE, SIZE), np.int64)
    for bad, msg in ((np.ones((SIZE, SIZE + 1)), "image shape"), (-c, "non-negative|>= 0"),
                     (c * 0.5, "whole sample indices"), (np.full((SIZE, SIZE), np.nan), "finite|NaN"),
                     (np.full((SIZE, SIZE), 2 ** 31), "2\\*\\*31")):
        with pytest.raises(InputError, match=msg):
            cornell.render(c, seed=0, features=False, first_sample=bad)


# ------------------------------------------------------------------ scalar fallback
def test_scalar_variant_renders_counts(cornell, pilot, reference):
    r = mb.MitsubaRenderer("cornell-box", width=SIZE, height=SIZE, variant="scalar_rgb")
    try:
        counts = np.random.default_rng(5).integers(0, 7, size=(SIZE, SIZE))
        s = r.render(counts, seed=4, feature_spp=2)
        assert r.variant == "scalar_rgb" and s.meta["variant"] == "scalar_rgb"
        assert np.array_equal(s.n, counts)
        assert s.albedo.shape == (SIZE, SIZE, 3)
        k = np.arange(3)
        assert s.m2_cross is not None and np.array_equal(s.m2_cross[..., k, k], s.m2)
        ok = (counts >= 1) & (pilot > 0).all(-1)
        z = (s.mean - reference) / np.sqrt(pilot * (1 / np.maximum(counts, 1)[..., None] + 1 / 2048))
        p, msg = _ttest_zero(z[ok].mean(-1), "scalar variant error vs reference (z)")
        assert p > ALPHA, msg
    finally:
        _ensure_variant(cornell)


def test_scalar_variant_takes_any_film_of_a_file_and_refuses_a_loaded_one(tmp_path, cornell, mi):
    # regression: a luminance film failed in the scalar fallback with an IndexError (its
    # one-sample mi.render images have one channel), and a loaded scene with a Gaussian
    # filter was rendered through it (filtered, so neighbouring pixels shared samples)
    ball = ('<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/>'
            '</bsdf></shape><emitter type="constant"/>')
    path = _xml_scene(tmp_path, ball, film='<rfilter type="box"/><string name="pixel_format" '
                      'value="luminance"/>', sensor='<transform name="to_world"><lookat '
                      'origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>')
    try:
        r = mb.MitsubaRenderer(path, variant="scalar_rgb")
        s = r.render_uniform(16, seed=2, feature_spp=1)
        assert s.mean.shape == (8, 8, 3) and s.albedo.shape == (8, 8, 3)
        p, msg = _ttest_zero((s.mean - 1.0).mean(-1), "scalar luminance-film furnace error")
        assert p > ALPHA, msg
        d = load_scene_dict("cornell-box", 8, 8)
        d["sensor"]["film"]["rfilter"] = {"type": "gaussian"}
        with pytest.raises(InputError, match="box filter and an RGB pixel_format"):
            mb.MitsubaRenderer(mi.load_dict(d), variant="scalar_rgb")
    finally:
        _ensure_variant(cornell)


def test_scalar_variant_renders_an_xyz_film_in_rgb(tmp_path, cornell, mi):
    # regression: an xyz film passed the scalar fallback's check (three channels), so its
    # one-sample mi.render images, X, Y, Z, were taken for R, G, B: a furnace of radiance
    # (1, 0.2, 0.1) rendered (0.52, 0.38, 0.14); a loaded scene with one was accepted too
    ball = ('<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/>'
            '</bsdf></shape><emitter type="constant"><rgb name="radiance" value="1, 0.2, 0.1"/>'
            '</emitter>')
    path = _xml_scene(tmp_path, ball, film='<rfilter type="box"/><string name="pixel_format" '
                      'value="xyz"/>', sensor='<transform name="to_world"><lookat '
                      'origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>')
    try:
        s = mb.MitsubaRenderer(path, variant="scalar_rgb").render_uniform(16, seed=2,
                                                                         features=False)
        for c, value in enumerate((1.0, 0.2, 0.1)):
            p, msg = _ttest_zero(s.mean[..., c] - value, f"scalar xyz-film furnace, channel {c}")
            assert p > ALPHA, msg
        d = load_scene_dict("cornell-box", 8, 8)
        d["sensor"]["film"]["pixel_format"] = "xyz"
        with pytest.raises(InputError, match="box filter and an RGB pixel_format"):
            mb.MitsubaRenderer(mi.load_dict(d), variant="scalar_rgb")
    finally:
        _ensure_variant(cornell)


def test_parameters_of_replaced_film_settings_are_not_unused(tmp_path, cornell):
    # regression: the scalar fallback replaces the film's filter and pixel format, and a
    # size replaces its width: a $name used only there was then Mitsuba's "Found unused
    # parameters" error (the file loaded in llvm_ad_rgb without a size)
    ball = ('<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/>'
            '</bsdf></shape><emitter type="constant"/>')
    path = _xml_scene(tmp_path, ball, film='<rfilter type="gaussian"><float name="stddev" '
                      'value="$sd"/></rfilter><string name="pixel_format" value="$pf"/>',
                      sensor='<transform name="to_world"><lookat origin="0, 0, 4" '
                      'target="0, 0, 0" up="0, 1, 0"/></transform>')
    path.write_text(path.read_text().replace('name="width" value="8"', 'name="width" value="$w"'))
    params = {"sd": 0.4, "pf": "rgb", "w": 8}
    try:
        with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
            r = mb.MitsubaRenderer(path, variant="scalar_rgb", params=params)
        s = r.render_uniform(4, seed=2, feature_spp=1)
        assert s.mean.shape == (8, 8, 3)
        with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
            r = mb.MitsubaRenderer(path, variant="scalar_rgb", params=params, width=5, height=3)
        assert (r.height, r.width) == (3, 5)
    finally:
        _ensure_variant(cornell)
    with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
        r = mb.MitsubaRenderer(path, params=params, width=6, height=4)   # --size wins over $w
    assert (r.height, r.width) == (4, 6)
    with pytest.raises(InputError, match="unused parameters"):          # one it never used
        mb.MitsubaRenderer(path, params={**params, "other": 1}, width=6, height=4)


def test_scalar_variant_renders_the_chosen_sensor(tmp_path, cornell):
    # sensor=1 in the scalar fallback: its film (not the first sensor's) is reloaded with a
    # box filter (a warning says its Gaussian is not used), and mi.render renders it for
    # the samples and for the features (no test rendered a sensor other than 0 there)
    ball = ('<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/>'
            '</bsdf></shape><emitter type="constant"/>')
    second = ('<sensor type="orthographic"><transform name="to_world"><lookat origin="4, 0, 0" '
              'target="0, 0, 0" up="0, 1, 0"/></transform><film type="hdrfilm"><integer '
              'name="width" value="6"/><integer name="height" value="5"/><rfilter '
              'type="gaussian"/></film></sensor>')
    path = _xml_scene(tmp_path, second + ball, sensor='<transform name="to_world"><lookat '
                      'origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>')
    try:
        with pytest.warns(RuntimeWarning, match="GaussianFilter is not used"):
            r = mb.MitsubaRenderer(path, variant="scalar_rgb", sensor=1)
        s = r.render_uniform(16, seed=3, feature_spp=2)
        assert s.mean.shape == s.albedo.shape == s.normal.shape == (5, 6, 3)
        assert s.meta["sensor"] == 1
        # the white furnace: every sample's expectation is 1
        p, msg = _ttest_zero((s.mean - 1.0).mean(-1), "scalar sensor-1 furnace error")
        assert p > ALPHA, msg
        # the sphere's normals, seen from +x, point to +x
        assert s.normal[2, 3, 0] > 0.9
    finally:
        _ensure_variant(cornell)


# ------------------------------------------------------------------ common random numbers
CRN_RENDERS = 48
CRN_SPP = 4


@pytest.fixture(scope="module")
def crn_renders(cornell):
    """``CRN_RENDERS`` independent CRN renders (seeds 0, 1, ...): means and 5x5 stencils."""
    if not cornell._jit:
        pytest.skip("CRN renders need a JIT variant")
    out = [cornell.render_crn(CRN_SPP, seed=s, stencil=5, features=False)
           for s in range(CRN_RENDERS)]
    return np.array([st.mean for st, _ in out]), np.array([c for _, c in out]), out[0][0]


def test_crn_render_is_unbiased(crn_renders, reference):
    """Each CRN render is an unbiased image: its pixels are correlated, so the test is
    across renders (i.i.d.): t-test of the per-render image mean minus the reference's."""
    means, _, st = crn_renders
    assert st.meta["crn"] and np.all(st.n == CRN_SPP)
    d = means.mean(axis=(1, 2, 3)) - reference.mean()
    p, msg = _ttest_zero(d, "CRN image mean − reference")
    assert p > ALPHA, msg


@pytest.mark.parametrize("dy,dx", [(0, 0), (0, 1), (1, 0), (-1, 2), (2, 2)])
def test_crn_covariance_stencil_is_unbiased(crn_renders, reference, pilot, dy, dx):
    """``cov_z[p, R+dy, R+dx]`` estimates cov(z_p, z_q), q = p + (dy, dx), without bias:
    per render, u = mean over p of (stencil − (z_p − μ_p)(z_q − μ_q)) / (s_p s_q) has
    expectation 0 (μ: the 2048-spp reference, whose own noise adds ~0.2 % of the
    covariance; s²: an independent render's sample variance, a fixed scale that keeps
    the light's pixels from drowning the rest); t-test over the i.i.d. renders."""
    means, covs, _ = crn_renders
    H, W = means.shape[1:3]
    ys, yq = slice(max(-dy, 0), H - max(dy, 0)), slice(max(dy, 0), H + min(dy, 0))
    xs, xq = slice(max(-dx, 0), W - max(dx, 0)), slice(max(dx, 0), W + min(dx, 0))
    e = means - reference[None]
    s = np.sqrt(np.maximum(pilot, 1e-8) / CRN_SPP)
    scale = s[ys, xs] * s[yq, xq]
    prod = e[:, ys, xs] * e[:, yq, xq]
    est = covs[:, ys, xs, 2 + dy, 2 + dx]
    u = ((est - prod) / scale).mean(axis=(1, 2, 3))
    p, msg = _ttest_zero(u, f"stencil ({dy}, {dx}) − MC product")
    assert p > ALPHA, msg
    assert np.all(covs[:, :, :, 2, 2] >= 0)


def test_crn_pixels_are_correlated_and_centre_is_the_variance(crn_renders, cornell):
    """The point of CRN: neighbouring errors are strongly positively correlated (an
    independent render's are not), and the stencil's centre is ``mean_var``."""
    _, covs, st = crn_renders
    np.testing.assert_array_equal(covs[0][:, :, 2, 2], st.mean_var)     # exactly, never < 0
    v = covs[..., 2, 2, :]
    right = covs[:, :, :-1, 2, 3]
    ok = (v[:, :, :-1] > 0) & (v[:, :, 1:] > 0)
    corr = right[ok] / np.sqrt(v[:, :, :-1][ok] * v[:, :, 1:][ok])
    assert np.median(corr) > 0.5, np.median(corr)
    # outside the image: 0
    assert np.all(covs[:, 0, :, 0:2] == 0) and np.all(covs[:, :, -1, :, 3:] == 0)


def test_crn_render_bad_input(cornell):
    if not cornell._jit:
        pytest.skip("CRN renders need a JIT variant")
    with pytest.raises(InputError, match="stencil"):
        cornell.render_crn(4, stencil=4)
    with pytest.raises(InputError, match="spp"):
        cornell.render_crn(0)
    with pytest.raises(InputError, match="GiB.*smaller `stencil`"):
        cornell.render_crn(4, stencil=401)


def test_crn_neighbour_gather_matches_a_direct_loop():
    """The neighbour gather behind the stencil's mean products, borders and offsets wider
    than the image included (no Mitsuba needed; the product kernel is tested in
    test_combine.py)."""
    rng = np.random.default_rng(11)
    for h, w, R in ((7, 5, 0), (7, 5, 2), (6, 9, 3), (3, 4, 4)):
        img = rng.normal(size=(h, w, 3))
        nb = mb._neighbours(img, R)
        for y in range(h):
            for x in range(w):
                for dy in range(-R, R + 1):
                    for dx in range(-R, R + 1):
                        inside = 0 <= y + dy < h and 0 <= x + dx < w
                        want = img[y + dy, x + dx] if inside else 0.0
                        np.testing.assert_array_equal(nb[y, x, R + dy, R + dx], want)


def test_crn_render_memory_is_the_two_arrays_it_checks(cornell):
    """The ``CRN_MAX_BYTES`` check counts two ``(H, W, m, m, 3)`` float64 arrays; the
    stencil is formed in place, so the peak NumPy allocation stays there (forming it by
    temporaries took twice as much: 4 arrays)."""
    if not cornell._jit:
        pytest.skip("CRN renders need a JIT variant")
    m = 15
    need = 2 * cornell.height * cornell.width * m * m * 3 * 8
    cornell.render_crn(2, seed=5, stencil=1, features=False)    # compile/load the kernel first
    _, peak = traced_peak(cornell.render_crn, 2, seed=5, stencil=m, features=False)
    assert peak < 1.25 * need, (peak, need)


def test_crn_render_draws_other_numbers_than_render_with_the_same_seed(cornell):
    """A CRN render is independent of :meth:`render` with the same seed: its streams are
    salted apart.  A render with one sample in one lit pixel traces it in lane 0, the lane
    whose stream a one-lane (CRN) wavefront would share under the same salt; the values
    must differ.  Different seeds of render_crn differ too."""
    if not cornell._jit:
        pytest.skip("CRN renders need a JIT variant")
    H, W = cornell.height, cornell.width
    counts = np.zeros((H, W), np.int64)
    counts[H // 2, W // 2] = 1
    for seed in (0, 7):
        one = cornell.render(counts, seed=seed, features=False).mean[H // 2, W // 2]
        crn, _ = cornell.render_crn(1, seed=seed, stencil=1, features=False)
        assert np.any(one != 0) and not np.array_equal(one, crn.mean[H // 2, W // 2])
    a, _ = cornell.render_crn(1, seed=1, stencil=1, features=False)
    b, _ = cornell.render_crn(1, seed=2, stencil=1, features=False)
    assert not np.array_equal(a.mean, b.mean)


def test_words_wrapping_around_warn_and_repeat_a_stream():
    """Sample j of pixel p has the word j·P + p (mod 2**32): on a 2x2 image (P = 4) sample
    2**30 of pixel 0 has the word 2**32 ≡ 0, the word of sample 0 of pixel 0, so it repeats
    that sample exactly, and ``render`` says so; one index lower nothing wraps."""
    r = mb.MitsubaRenderer("cornell-box", width=2, height=2)
    one = np.zeros((2, 2), np.int64)
    one[0, 0] = 1
    first = np.zeros((2, 2), np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = r.render(one, seed=7, features=False)
        first[0, 0] = 2 ** 30 - 1               # word (2**30 - 1)·4 = 2**32 - 4: no wrap
        b = r.render(one, seed=7, features=False, first_sample=first)
        full = np.ones((2, 2), np.int64)        # last word (2**30 - 1)·4 + 3 = 2**32 - 1
        r.render(full, seed=7, features=False, first_sample=first * 0 + 2 ** 30 - 1)
    first[0, 0] = 2 ** 30
    with pytest.warns(RuntimeWarning, match="wrap around"):
        c = r.render(one, seed=7, features=False, first_sample=first)
    assert not np.array_equal(a.mean[0, 0], b.mean[0, 0])
    np.testing.assert_array_equal(a.mean[0, 0], c.mean[0, 0])


# ------------------------------------------------------------------ user XML scenes
def _xml_scene(tmp_path, body, *, name="scene.xml", size=(8, 8), sensor="", film="",
               integrator='<integrator type="path"/>'):
    """A small XML scene: ``body`` (shapes, emitters, media) seen by a perspective camera
    at the origin looking down -z (``sensor``: extra sensor children)."""
    w, h = size
    text = f"""<scene version="3.0.0">
  {integrator}
  <sensor type="perspective"><float name="fov" value="40"/>{sensor}
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/>
      {film or '<rfilter type="box"/>'}</film></sensor>
  {body}
</scene>"""
    path = tmp_path / name
    path.write_text(text)
    return path


def test_camera_inside_a_medium_sees_through_it(tmp_path):
    # regression: the sensor's medium was not passed to integrator.sample, so a camera
    # inside fog rendered as if in vacuum (every sample 1 instead of Bernoulli(e^-1)).
    # Purely absorbing fog (albedo 0, sigma_t 1) in a unit sphere around the camera, white
    # sky of radiance 1: volpath's sample is 1 when the sampled free path leaves the
    # sphere (probability e^-1) and 0 otherwise, so every pixel's expectation is e^-1.
    path = _xml_scene(tmp_path, """
  <medium type="homogeneous" id="fog"><rgb name="albedo" value="0"/>
    <float name="sigma_t" value="1"/></medium>
  <shape type="sphere"><bsdf type="null"/><ref name="interior" id="fog"/></shape>
  <emitter type="constant"/>""", sensor='<ref name="medium" id="fog"/>',
                      integrator='<integrator type="volpath"/>')
    r = mb.MitsubaRenderer(path)
    s = r.render_uniform(32, seed=3, features=False)
    p0 = np.exp(-1.0)
    x = s.mean[..., 0]
    z = (x.mean() - p0) / np.sqrt(p0 * (1 - p0) / s.total_samples)
    p = 2 * sps.norm.sf(abs(z))
    assert p > ALPHA, f"mean {x.mean():.4f}, expected e^-1 = {p0:.4f}, z = {z:.2f}"


def test_integrators_without_per_pixel_samples_are_refused(tmp_path):
    # regression: a ptracer scene loaded and then failed in render() with Mitsuba's
    # TypeError (no `sample` taking a ray); an aov integrator without a nested one
    # rendered an all-black image without a word
    ball = ('<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="1"/>'
            '</bsdf></shape><emitter type="constant"/>')
    path = _xml_scene(tmp_path, ball, integrator='<integrator type="ptracer"/>')
    with pytest.raises(InputError, match="ptracer.*change the scene's <integrator>"):
        mb.MitsubaRenderer(path)
    path = _xml_scene(tmp_path, ball, integrator='<integrator type="aov">'
                      '<string name="aovs" value="dd.y:depth"/></integrator>')
    with pytest.raises(InputError, match="'aov' integrator without a nested integrator"):
        mb.MitsubaRenderer(path)
    # with a nested integrator the colour is the nested one's: the white furnace again
    path = _xml_scene(tmp_path, ball, integrator='<integrator type="aov">'
                      '<string name="aovs" value="dd.y:depth"/><integrator type="path"/>'
                      '</integrator>', sensor='<transform name="to_world">'
                      '<lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>')
    s = mb.MitsubaRenderer(path).render_uniform(16, seed=4, features=False)
    p, msg = _ttest_zero((s.mean - 1.0).mean(-1), "aov(path) furnace error")
    assert p > ALPHA, msg


def test_xml_parameters_take_values_and_a_missing_one_says_how(tmp_path):
    # regression: a file using $spp without a <default> could not be loaded at all (no way
    # to pass a value), and the error carried Mitsuba's "[parser.cpp:451]" prefix
    ball = ('<shape type="sphere"><float name="radius" value="$r"/><bsdf type="diffuse"/></shape>'
            '<emitter type="constant"/>')
    path = _xml_scene(tmp_path, ball, sensor='<sampler type="independent">'
                      '<integer name="sample_count" value="$spp"/></sampler>')
    with pytest.raises(InputError, match=r"undefined parameter: \$(spp|r); give it a value with "
                                         r"`params` .*<default name=") as e:
        mb.MitsubaRenderer(path)
    assert ".cpp:" not in str(e.value) and "\n" not in str(e.value)
    for size in ({}, {"width": 6, "height": 4}):         # load_file and load_string paths
        r = mb.MitsubaRenderer(path, params={"spp": 16, "r": 0.25}, **size)
        assert r._sensor.sampler().sample_count() == 16
        assert r.params == {"spp": "16", "r": "0.25"}         # as the file received them
        assert r._scene.shapes()[0].bbox().extents()[0] == pytest.approx(0.5)
    with pytest.raises(InputError, match="unused parameters"):
        mb.MitsubaRenderer(path, params={"spp": 16, "r": 0.25, "other": 1})
    for bad, word in (([("spp", 1)], "mapping"), ({"1x": 2}, "names"),
                      ({"parallel": 1}, "names"), ({"optimize": 0}, "not 'parallel' or "
                                                   "'optimize' .*rename such a \\$name"),
                      ({"spp": None}, "string or a number")):
        with pytest.raises(InputError, match=word):
            mb.MitsubaRenderer(path, params=bad)
    with pytest.raises(InputError, match="leave `params` unset"):
        mb.MitsubaRenderer("cornell-box", width=8, height=8, params={"spp": 4})


def test_a_film_filter_that_is_not_used_and_a_scene_without_light_warn(tmp_path):
    # regression: statmc replaced a film's Gaussian filter by a box and rendered a scene
    # without emitters as black, both without a word
    ball = '<shape type="sphere"><bsdf type="diffuse"/></shape>'
    path = _xml_scene(tmp_path, ball + '<emitter type="constant"/>', film='<rfilter type="gaussian"/>')
    with pytest.warns(RuntimeWarning, match="GaussianFilter is not used.*<rfilter type=\"box\"/>"):
        mb.MitsubaRenderer(path)
    path = _xml_scene(tmp_path, ball + '<emitter type="constant"/>')          # a box: quiet
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mb.MitsubaRenderer(path)
    path = _xml_scene(tmp_path, ball)
    with pytest.warns(RuntimeWarning, match="no emitter, so every pixel renders black"):
        r = mb.MitsubaRenderer(path)
    with warnings.catch_warnings():         # a depth integrator needs no light
        warnings.simplefilter("error")
        mb.MitsubaRenderer(_xml_scene(tmp_path, ball, name="depth.xml",
                                      integrator='<integrator type="depth"/>'))
    assert not r.render_uniform(2, features=False).mean.any()


def test_crop_window_renders_the_window_and_refuses_a_new_size(tmp_path):
    # the crop window of the film is what mi.render renders: same size, same pixels
    checker = ('<bsdf type="diffuse"><texture type="checkerboard" name="reflectance">'
               '<transform name="to_uv"><scale x="6" y="6"/></transform></texture></bsdf>')
    path = _xml_scene(tmp_path, f'<shape type="sphere">{checker}</shape>'
                      '<emitter type="constant"/>', size=(12, 10), film=(
                          '<rfilter type="box"/><integer name="crop_offset_x" value="3"/>'
                          '<integer name="crop_offset_y" value="2"/><integer name="crop_width" '
                          'value="6"/><integer name="crop_height" value="5"/>'),
                      sensor='<transform name="to_world"><lookat origin="0, 0, 4" '
                             'target="0, 0, 0" up="0, 1, 0"/></transform>')
    r = mb.MitsubaRenderer(path)
    assert (r.height, r.width) == (5, 6)
    s = r.render_uniform(256, seed=5, features=False)
    scale = r.render_uniform(256, seed=6, features=False).sample_var / 256   # independent
    _ensure_variant(r)
    ref = np.asarray(r._mi.render(r._scene, spp=4096, seed=8), np.float64)[..., :3]
    assert ref.shape == (5, 6, 3)
    # chi-square of the red channel's z-scores (pixels are independent; the scale comes
    # from an independent render, so z^2 is F(1, 255), nearly chi2(1)); one pixel of shift
    # of the window gave chi2/k = 160, the right window 0.7-1.5 over 12 seeds
    z = ((s.mean - ref) / np.sqrt(scale * (1 + 256 / 4096)))[..., 0]
    chi2 = float((z ** 2).sum())
    p = sps.chi2.sf(chi2, z.size)
    assert p > ALPHA, f"crop window vs mi.render: chi2/k = {chi2 / z.size:.3f}, p = {p:.3g}"
    # regression: --size on a cropped film was Mitsuba's "Invalid crop window" from "string"
    with pytest.raises(InputError, match="crop window .*crop_offset_x.* of 6x5, .*new film size "
                                         "8x6.*make the size the crop window's.*leave `width`"):
        mb.MitsubaRenderer(path, width=8, height=6)
    # regression: the crop window's own size was refused too (a sample map of the render's
    # shape sets it), saying to leave the size unset; it is no change of size
    same = mb.MitsubaRenderer(path, width=6, height=5)
    assert (same.height, same.width) == (5, 6)
    np.testing.assert_array_equal(same.render_uniform(4, seed=5, features=False).mean,
                                  r.render_uniform(4, seed=5, features=False).mean)


def test_sensor_chooses_which_camera_of_the_file_renders(tmp_path):
    # the first sensor was the only one a user could render
    checker = ('<bsdf type="diffuse"><texture type="checkerboard" name="reflectance">'
               '<transform name="to_uv"><scale x="6" y="6"/></transform></texture></bsdf>')
    second = ('<sensor type="orthographic"><transform name="to_world"><scale x="1.2" y="1.2"/>'
              '<lookat origin="4, 0, 0" target="0, 0, 0" up="0, 1, 0"/></transform>'
              '<film type="hdrfilm"><integer name="width" value="6"/><integer name="height" '
              'value="5"/><rfilter type="box"/></film></sensor>')
    path = _xml_scene(tmp_path, f'{second}<shape type="sphere">{checker}</shape>'
                      '<emitter type="constant"/>', size=(8, 8))
    r = mb.MitsubaRenderer(path, sensor=1)
    assert (r.height, r.width, r.sensor) == (5, 6, 1)
    s = r.render_uniform(256, seed=5, features=False)
    assert s.meta["sensor"] == 1
    scale = r.render_uniform(256, seed=6, features=False).sample_var / 256     # independent
    _ensure_variant(r)
    ref = np.asarray(r._mi.render(r._scene, sensor=1, spp=4096, seed=8), np.float64)[..., :3]
    ok = scale[..., 0] > 0                  # the corners see only the sky (variance 0)
    assert ok.sum() >= 20 and np.allclose(s.mean[~ok], ref[~ok], rtol=1e-5)
    z = ((s.mean - ref)[ok] / np.sqrt(scale[ok] * (1 + 256 / 4096)))[..., 0]
    chi2 = float((z ** 2).sum())
    p = sps.chi2.sf(chi2, z.size)
    assert p > ALPHA, f"sensor 1 vs mi.render(sensor=1): chi2/k = {chi2 / z.size:.3f}, p = {p:.3g}"
    r = mb.MitsubaRenderer(path, sensor=1, width=4, height=3)        # resizes sensor 1's film
    assert (r.height, r.width) == (3, 4) and mb.MitsubaRenderer(path).width == 8
    for bad, word in ((2, "one of the 2 sensors"), (-1, "sensor"), (1.0, "sensor")):
        with pytest.raises(InputError, match=word):
            mb.MitsubaRenderer(path, sensor=bad)
    # regression: with a size, a sensor past the last said to add a <film> to it
    with pytest.raises(InputError, match=r"`sensor` must be .* one of the 2 sensors .*got 2"):
        mb.MitsubaRenderer(path, sensor=2, width=4, height=3)
    # a sensor of an included file renders, but its film cannot be resized (regression:
    # with the file's own sensor after the include, sensor 0 rendered at its own size, as
    # the size went to the file's <sensor> 0, the scene's sensor 2)
    inc = '<include filename="scene.xml"/>'
    (tmp_path / "main.xml").write_text(f'<scene version="3.0.0">{inc}</scene>')
    own = second.replace('value="6"', 'value="7"').replace('<scale x="1.2" y="1.2"/>', '')
    (tmp_path / "both.xml").write_text(f'<scene version="3.0.0">{inc}{own}</scene>')
    assert mb.MitsubaRenderer(tmp_path / "main.xml", sensor=1).width == 6
    assert mb.MitsubaRenderer(tmp_path / "both.xml", sensor=2).width == 7
    r = mb.MitsubaRenderer(tmp_path / "both.xml", sensor=2, width=4, height=3)
    assert (r.width, r.height, r._sensor.film().size()[0]) == (4, 3, 4)
    for name, index in (("main.xml", 0), ("main.xml", 1), ("both.xml", 0), ("both.xml", 1)):
        with pytest.raises(InputError, match=f"sensor {index} of .* not a <sensor> written in "
                                             "the file itself .*<include>d file"):
            mb.MitsubaRenderer(tmp_path / name, sensor=index, width=4, height=3)
    with pytest.raises(InputError, match="one of the 3 sensors .* got 3"):
        mb.MitsubaRenderer(tmp_path / "both.xml", sensor=3, width=4, height=3)


def test_nonfinite_samples_warn(tmp_path):
    # regression: NaN/Inf samples were counted as zeros without a word (meta only)
    path = _xml_scene(tmp_path, '<shape type="sphere"><bsdf type="diffuse"/><emitter type="area">'
                      '<rgb name="radiance" value="inf"/></emitter></shape>'
                      '<emitter type="constant"/>', sensor='<transform name="to_world"><lookat '
                      'origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>')
    r = mb.MitsubaRenderer(path)
    with pytest.warns(RuntimeWarning, match=r"\d+ of 256 samples .* were NaN or Inf"):
        s = r.render_uniform(4, features=False)
    assert s.meta["nonfinite_samples"] > 0 and np.isfinite(s.mean).all()
    with warnings.catch_warnings():         # once per renderer: an adaptive loop's passes
        warnings.simplefilter("error")      # would repeat it
        t = r.render_uniform(2, features=False)
    assert t.meta["nonfinite_samples"] > 0
    # the renderer counts every render's (a merge keeps the first's meta only)
    assert r.nonfinite_samples == s.meta["nonfinite_samples"] + t.meta["nonfinite_samples"]
    if r._jit:
        with pytest.warns(RuntimeWarning, match="NaN or Inf"):
            mb.MitsubaRenderer(path).render_crn(2, stencil=1, features=False)


def test_a_resized_scene_does_not_lend_its_folder_to_later_scenes(tmp_path, mi):
    # regression: loading a file with a new size prepended its folder to Mitsuba's global
    # file resolver for good, so a later scene (statmc's or the user's own mi.load_file)
    # naming a file it lacks silently loaded the first scene's file of that name
    texture = ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" '
               'name="reflectance"><string name="filename" value="tex.exr"/></texture></bsdf>'
               '</shape><emitter type="constant"/>')
    paths = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        paths.append(_xml_scene(tmp_path / name, texture))
    mi.Bitmap(np.full((2, 2, 3), 0.5, np.float32)).write(str(tmp_path / "a" / "tex.exr"))
    n = len(mi.file_resolver())
    assert mb.MitsubaRenderer(paths[0], width=4, height=3).width == 4
    assert len(mi.file_resolver()) == n
    with pytest.raises(FileFormatError, match="tex.exr"):
        mb.MitsubaRenderer(paths[1], width=4, height=3)
    with pytest.raises(FileFormatError, match="tex.exr"):
        mb.MitsubaRenderer(paths[1])


def test_size_of_a_sensor_after_a_batch_sensor(tmp_path):
    # regression: the film to resize was looked up among all <sensor> elements, so the
    # parts of a batch sensor shifted the count (sensor=1 found a part without a film)
    cam = ('<sensor type="perspective"><transform name="to_world"><lookat origin="{o}" '
           'target="0, 0, 0" up="0, 1, 0"/></transform>{film}</sensor>')
    film = ('<film type="hdrfilm"><integer name="width" value="8"/><integer name="height" '
            'value="4"/><rfilter type="box"/></film>')
    batch = ('<sensor type="batch">' + cam.format(o="0, 0, 4", film="")
             + cam.format(o="4, 0, 0", film="") + film + '</sensor>')
    path = _xml_scene(tmp_path, batch + cam.format(o="0, 4, 0.1", film=film)
                      + '<shape type="sphere"><bsdf type="diffuse"/></shape>'
                        '<emitter type="constant"/>')
    r = mb.MitsubaRenderer(path, sensor=2, width=5, height=3)     # the file's third sensor
    assert (r.height, r.width) == (3, 5) and len(r._scene.sensors()) == 3
    assert mb.MitsubaRenderer(path, sensor=1, width=6, height=2).width == 6   # the batch
