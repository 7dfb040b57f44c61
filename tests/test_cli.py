"""The statmc command line: outputs, reports, and one-line errors for bad input."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from statmc.cli import main


def run_cli(*args):
    """Run the console entry in-process; return (exit code, stdout, stderr)."""
    import contextlib
    import io
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def toy_ref(tmp_path_factory):
    d = tmp_path_factory.mktemp("ref")
    path = d / "ref.exr"
    code, _, err = run_cli("reference", "toy:mixed", "--spp", 512, "--size", "24x16",
                           "--pass-spp", 128, "--out", path, "-q")
    assert code == 0, err
    return path


def test_render_writes_exr_png_report_with_metrics(tmp_path, toy_ref):
    out = tmp_path / "r"
    code, stdout, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16",
                                "--out", out, "--reference", toy_ref, "-q")
    assert code == 0, err
    for f in ("render.exr", "render.png", "report.json"):
        assert (out / f).stat().st_size > 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["spp"] == 8 and rep["total_samples"] == 8 * 24 * 16
    assert rep["width"] == 24 and rep["height"] == 16
    assert rep["samples_per_second"] > 0
    assert rep["metrics"]["relmse"] > 0
    from statmc.exr import read_exr
    st = read_exr(out / "render.exr")
    assert np.all(st.n == 8)


def test_render_metrics_shrink_with_spp(tmp_path, toy_ref):
    rel = []
    for spp in (4, 64):
        code, _, err = run_cli("render", "toy:mixed", "--spp", spp, "--size", "24x16",
                               "--out", tmp_path / str(spp), "--reference", toy_ref, "-q")
        assert code == 0, err
        rel.append(json.loads((tmp_path / str(spp) / "report.json").read_text())["metrics"]["relmse"])
    assert rel[1] < rel[0] / 4  # 16x the samples: about 1/16 of the variance part


def test_render_with_integer_and_density_maps(tmp_path):
    rng = np.random.default_rng(0)
    counts = rng.integers(0, 9, size=(16, 24))
    np.save(tmp_path / "counts.npy", counts)
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", tmp_path / "counts.npy",
                           "--out", tmp_path / "a", "-q")
    assert code == 0, err
    from statmc.exr import read_exr
    assert np.array_equal(read_exr(tmp_path / "a" / "render.exr").n, counts)
    dens = rng.uniform(0.1, 1.0, size=(16, 24))
    np.save(tmp_path / "dens.npy", dens)
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", tmp_path / "dens.npy", "--spp", 4,
                           "--out", tmp_path / "b", "-q")
    assert code == 0, err
    assert read_exr(tmp_path / "b" / "render.exr").n.sum() == 4 * 16 * 24


def test_metrics_and_info_print_json(tmp_path, toy_ref):
    run_cli("render", "toy:mixed", "--spp", 4, "--size", "24x16", "--out", tmp_path, "-q")
    code, out, err = run_cli("metrics", tmp_path / "render.exr", toy_ref)
    assert code == 0, err
    m = json.loads(out)
    assert {"relmse", "mse", "rmse", "smape", "flip"} <= set(m)
    code, out, err = run_cli("info", tmp_path / "render.exr")
    assert code == 0, err
    info = json.loads(out)
    assert "SampleCount" in json.dumps(info) and "Variance.R" in json.dumps(info)


@pytest.mark.parametrize("args, needle", [
    (["render", "no-such-scene", "--spp", "4", "--out", "{tmp}/x"], "no-such-scene"),
    (["render", "{tmp}/missing.xml", "--spp", "4", "--out", "{tmp}/x"], "missing.xml"),
    (["render", "toy:mixed", "--spp", "-3", "--out", "{tmp}/x"], "--spp"),
    (["render", "toy:mixed", "--spp", "4", "--size", "12by4", "--out", "{tmp}/x"], "--size"),
    (["render", "toy:mixed", "--sample-map", "{tmp}/neg.npy", "--out", "{tmp}/x"], "negative"),
    (["render", "toy:mixed", "--sample-map", "{tmp}/nan.npy", "--out", "{tmp}/x"], "NaN"),
    (["render", "toy:mixed", "--sample-map", "{tmp}/counts.npy", "--size", "8x8", "--out", "{tmp}/x"],
     "sample map is"),
    (["render", "toy:mixed", "--spp", "4", "--size", "8x8", "--reference", "{tmp}/ref.exr",
      "--out", "{tmp}/x"], "reference"),
    (["metrics", "{tmp}/nothing.exr", "{tmp}/ref.exr"], "nothing.exr"),
    (["metrics", "{tmp}/garbage.exr", "{tmp}/ref.exr"], "garbage.exr"),
    (["info", "{tmp}/garbage.exr"], "garbage.exr"),
])
def test_bad_input_exits_nonzero_with_one_line(tmp_path, toy_ref, args, needle):
    np.save(tmp_path / "neg.npy", -np.ones((16, 24)))
    np.save(tmp_path / "nan.npy", np.full((16, 24), np.nan))
    np.save(tmp_path / "counts.npy", np.ones((16, 24), np.int64))
    (tmp_path / "garbage.exr").write_bytes(b"not an exr at all" * 10)
    os.link(toy_ref, tmp_path / "ref.exr")
    code, out, err = run_cli(*[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], err
    assert "Traceback" not in err
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_render_never_overwrites_its_reference(tmp_path, toy_ref):
    ref_copy = tmp_path / "render.exr"
    ref_copy.write_bytes(toy_ref.read_bytes())
    before = ref_copy.read_bytes()
    code, _, err = run_cli("render", "toy:mixed", "--spp", 4, "--size", "24x16", "--out", tmp_path,
                           "--reference", ref_copy, "-q")
    assert code != 0 and "overwrite" in err
    assert ref_copy.read_bytes() == before


def test_console_script_runs_as_a_process(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), "statmc")
    r = subprocess.run([exe, "render", "toy:nope", "--spp", "1", "--out", str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "toy" in r.stderr


def test_metrics_refuses_nan_pixels_unless_asked(tmp_path, toy_ref):
    import OpenEXR
    from statmc.exr import read_image
    img = read_image(toy_ref).copy()
    img[2, 3, 1] = np.nan
    img[0, 0, 0] = np.inf
    chans = {c: np.ascontiguousarray(img[..., k]) for k, c in enumerate("RGB")}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 chans).write(str(tmp_path / "nan.exr"))
    code, _, err = run_cli("metrics", tmp_path / "nan.exr", toy_ref)
    assert code == 2 and "NaN" in err and len(err.strip().splitlines()) == 1
    code, out, err = run_cli("metrics", tmp_path / "nan.exr", toy_ref, "--replace-nonfinite", 0)
    assert code == 0, err
    ref = read_image(toy_ref)
    fixed = img.copy()
    fixed[~np.isfinite(fixed)] = 0
    from statmc.metrics import mse
    assert json.loads(out)["mse"] == pytest.approx(mse(fixed, ref), rel=1e-6)


@pytest.fixture(scope="module")
def toy_render(tmp_path_factory):
    d = tmp_path_factory.mktemp("y")
    code, _, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--out", d, "-q")
    assert code == 0, err
    return d / "render.exr"


@pytest.mark.parametrize("den", ["gaussian", "gem", "oidn"])
def test_denoise_lowers_error_and_writes_variance(tmp_path, toy_render, toy_ref, den):
    from statmc.exr import read_exr, read_image
    from statmc.metrics import mse
    out = tmp_path / "d.exr"
    code, _, err = run_cli("denoise", toy_render, "--denoiser", den, "--variance", "--out", out, "-q")
    assert code == 0, err
    ref = read_image(toy_ref)
    raw = read_exr(toy_render)
    d = read_exr(out)
    assert mse(d.mean, ref) < mse(raw.mean, ref)
    assert np.array_equal(d.n, raw.n) and d.mean_var.max() > 0
    if den == "gaussian":  # linear: the output variance is exactly sum_j w_ij^2 var_j
        from statmc.denoisers import gaussian
        from statmc.sure import kernel_variance
        exact = kernel_variance(gaussian(1.0).kernels(raw.mean.shape), raw.mean_var)
        np.testing.assert_allclose(d.mean_var, exact, rtol=1e-4, atol=1e-9)


def test_combine_weights_and_errors(tmp_path, toy_render, toy_ref):
    from statmc.exr import read_exr, read_image
    from statmc.metrics import mse
    z = tmp_path / "z.exr"
    assert run_cli("denoise", toy_render, "--denoiser", "gaussian", "--variance", "--out", z, "-q")[0] == 0
    y = read_exr(toy_render).mean
    for weights in ("uniform", "gaussian", "statistical"):
        out = tmp_path / f"c-{weights}.exr"
        code, _, err = run_cli("combine", toy_render, z, "--weights", weights, "--size", 5, "--out", out, "-q")
        assert code == 0, err
        assert mse(read_image(out), read_image(toy_ref)) < mse(y, read_image(toy_ref))
    plain = tmp_path / "plain.exr"
    from statmc.exr import write_exr
    write_exr(plain, read_image(z))
    code, _, err = run_cli("combine", toy_render, plain, "--weights", "statistical", "--out", tmp_path / "x.exr")
    assert code == 2 and "Variance" in err and not (tmp_path / "x.exr").exists()
    small = tmp_path / "small.exr"
    write_exr(small, read_image(z)[:8, :8])
    code, _, err = run_cli("combine", toy_render, small, "--weights", "uniform", "--out", tmp_path / "x.exr")
    assert code == 2 and "same size" in err and not (tmp_path / "x.exr").exists()
    code, _, err = run_cli("combine", toy_render, z, "--weights", "uniform", "--out", z)
    assert code == 2 and "overwrite" in err


def test_progressive_command_and_denoising_aware_render(tmp_path, toy_render, toy_ref):
    from statmc.exr import read_channels, read_exr, read_image
    from statmc.metrics import mse
    out = tmp_path / "p.exr"
    code, _, err = run_cli("progressive", toy_render, "--denoiser", "oidn", "--out", out, "-q")
    assert code == 0, err
    ref = read_image(toy_ref)
    assert mse(read_image(out), ref) < mse(read_exr(toy_render).mean, ref)
    alpha = read_channels(out)["progressive.alpha"]
    assert alpha.min() >= 0 and alpha.max() <= 1
    code, _, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--sampler",
                           "denoising-aware", "--denoiser", "gaussian", "--reconstruct", "progressive",
                           "--out", tmp_path / "da", "--reference", toy_ref, "-q")
    assert code == 0, err
    rep = json.loads((tmp_path / "da" / "report.json").read_text())
    assert rep["total_samples"] == 8 * 24 * 16 and rep["spp_max"] > 8
    assert rep["metrics_reconstruction"]["mse"] < rep["metrics"]["mse"]
    code, _, err = run_cli("progressive", tmp_path / "nothing.exr", "--out", tmp_path / "q.exr")
    assert code == 2 and "nothing.exr" in err and not (tmp_path / "q.exr").exists()


def test_render_expected_error_sampler_kernel_denoisers(tmp_path):
    """--sampler expected-error runs with GEM pilot kernels (default) or a Gaussian, and
    refuses a denoiser that is not a kernel denoiser, with one line and exit code 2."""
    for extra in ([], ["--denoiser", "gaussian"]):
        out = tmp_path / ("d" + "".join(extra))
        code, _, err = run_cli("render", "toy:mixed", "--spp", 12, "--size", "24x16",
                               "--sampler", "expected-error", *extra, "--out", out, "-q")
        assert code == 0, err
        from statmc.exr import read_exr
        assert int(read_exr(out / "render.exr").n.sum()) == 12 * 24 * 16
    code, _, err = run_cli("render", "toy:mixed", "--spp", 12, "--size", "24x16",
                           "--sampler", "expected-error", "--denoiser", "oidn",
                           "--out", tmp_path / "bad", "-q")
    assert code == 2 and "kernel denoiser" in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()


def test_render_reconstruct_oidn_combine(tmp_path, toy_ref):
    """--reconstruct oidn+combine writes the combination and its mix-weight channel, and on
    the toy scene it is no worse than 1.05x plain OIDN on the same render."""
    from statmc.exr import exr_info
    rel = {}
    for method in ("oidn", "oidn+combine"):
        out = tmp_path / method.replace("+", "_")
        code, _, err = run_cli("render", "toy:mixed", "--spp", 16, "--size", "24x16",
                               "--reconstruct", method, "--reference", toy_ref, "--out", out, "-q")
        assert code == 0, err
        rel[method] = json.loads((out / "report.json").read_text())["metrics_reconstruction"]["relmse"]
    assert "oidn+combine.mix" in exr_info(out / "reconstruction.exr")["channels"]
    assert rel["oidn+combine"] <= 1.05 * rel["oidn"], rel


def test_reconstruct_gem_bias_option_matches_the_library(tmp_path, toy_render):
    """`statmc reconstruct --gem-bias paper|pooled` writes exactly gem.reconstruct(bias=...) of
    the file's statistics; --gamma changes the paper's reconstruction only."""
    from statmc import gem
    from statmc.exr import read_exr, read_image
    st = read_exr(toy_render)
    imgs = {}
    for bias, gamma in (("pooled", 0.2), ("pooled", 0.05), ("paper", 0.2), ("paper", 0.05)):
        out = tmp_path / f"{bias}_{gamma}.exr"
        code, _, err = run_cli("reconstruct", toy_render, "--gem-bias", bias, "--gamma", gamma,
                               "--out", out, "-q")
        assert code == 0, err
        imgs[bias, gamma] = read_image(out)[..., :3]
        want = gem.reconstruct(st.mean.astype(np.float32), st.mean_var.astype(np.float32),
                               gamma=gamma, n=st.n, bias=bias)
        np.testing.assert_allclose(imgs[bias, gamma], want, rtol=1e-6, atol=1e-7)
    assert np.array_equal(imgs["pooled", 0.2], imgs["pooled", 0.05])
    assert not np.array_equal(imgs["paper", 0.2], imgs["paper", 0.05])
    assert not np.array_equal(imgs["paper", 0.2], imgs["pooled", 0.2])
    with pytest.raises(SystemExit) as e:  # argparse refuses an unknown choice (exit 2)
        run_cli("reconstruct", toy_render, "--gem-bias", "robust", "--out", tmp_path / "x.exr")
    assert e.value.code == 2 and not (tmp_path / "x.exr").exists()


def test_denoise_and_progressive_forward_gem_bias(tmp_path, toy_render):
    """`denoise --denoiser gem` and `progressive --denoiser gem` pass --gem-bias and --gamma to
    GEM: the paper's rule moves with γ, the pooled default does not."""
    from statmc.exr import read_image
    out = {}
    for cmd in ("denoise", "progressive"):
        for bias, gamma in (("paper", 0.05), ("paper", 0.3), ("pooled", 0.05), ("pooled", 0.3)):
            path = tmp_path / f"{cmd}_{bias}_{gamma}.exr"
            code, _, err = run_cli(cmd, toy_render, "--denoiser", "gem", "--gem-bias", bias,
                                   "--gamma", gamma, "--out", path, "-q")
            assert code == 0, err
            out[cmd, bias, gamma] = read_image(path)
        assert not np.array_equal(out[cmd, "paper", 0.05], out[cmd, "paper", 0.3])
        assert np.array_equal(out[cmd, "pooled", 0.05], out[cmd, "pooled", 0.3])
        assert not np.array_equal(out[cmd, "paper", 0.3], out[cmd, "pooled", 0.3])
