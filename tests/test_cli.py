"""The statmc command line: outputs, reports, and one-line errors for bad input."""

import json
import os
import re
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
    # report.json said "sampler": "uniform" for both: it names the map and how it was used
    for d, name, use in (("a", "counts.npy", "counts"), ("b", "dens.npy", "density")):
        rep = json.loads((tmp_path / d / "report.json").read_text())
        assert rep["sampler"] == "sample-map"
        assert rep["sample_map"] == {"path": str(tmp_path / name), "used_as": use}
    code, _, err = run_cli("render", "toy:mixed", "--spp", 2, "--size", "4x4", "--out",
                           tmp_path / "c", "-q")
    rep = json.loads((tmp_path / "c" / "report.json").read_text())
    assert (rep["sampler"], rep["sample_map"]) == ("uniform", None)


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


def test_info_summarises_stencil_covariance_and_bins(tmp_path, toy_render):
    """Regression: `statmc info` listed a --crn file's stencil as one group per offset (225
    groups, 691 channels at 15x15) and its layout named neither Covariance.*, the stencil nor
    sample bins.  Each family is now one entry, and the layout names them."""
    from statmc.exr import bin_channels, exr_info, spatial_covariance_channels
    ch = _stat_channels(toy_render)
    h, w = ch["R"].shape
    rng = np.random.default_rng(0)
    cov = rng.uniform(0, 1, (h, w, 5, 5, 3))
    extra = {**spatial_covariance_channels(cov, ch["SampleCount"]),
             **bin_channels(rng.uniform(0, 1, (3, h, w, 3)), rng.uniform(0, 1, (3, h, w, 3)))}
    extra = {k: np.asarray(v, np.float32) for k, v in extra.items()}
    extra["SpatialCovariance.-1+2.G"][3, 4] = np.nan
    path = tmp_path / "crn.exr"
    _write_channels(path, {**ch, **extra})
    code, out, err = run_cli("info", path)
    assert code == 0, err
    info = json.loads(out)
    full = exr_info(path)
    assert len(full["groups"]) > 25 + 6                  # what was printed before
    layout = info["layout"]
    assert layout["covariance"] is True and layout["spatial_covariance"] == "stencil 5x5"
    assert layout["bins"] == 3 and layout["bins_denoised"] is True
    assert info["groups"]["SpatialCovariance.<dy><dx>"] == ("stencil 5x5: 25 offsets (dy, dx) x "
                                                            "R,G,B = 75 channels")
    assert info["groups"]["Bin<b>"] == info["groups"]["Bin<b>.Denoised"] == (
        "3 bins x R,G,B = 9 channels")
    assert not any(g.startswith(("SpatialCovariance.+", "SpatialCovariance.-", "Bin0"))
                   for g in info["groups"])
    assert info["channel_count"] == len(full["channels"]) == len(ch) + 75 + 18
    assert info["channels"]["SpatialCovariance.<dy><dx>.<R|G|B>"] == "float"
    assert {k: v for k, v in info["channels"].items() if "<" not in k} == {
        k: v for k, v in full["channels"].items() if k in ch}
    assert info["groups"]["Covariance"] == ["Covariance.GB", "Covariance.RB", "Covariance.RG"]
    assert info["nonfinite"] == {"SpatialCovariance.<dy><dx>": {"nan": 1, "inf": 0}}
    # a plain render: nothing to summarise, the new layout keys say so
    code, out, err = run_cli("info", toy_render)
    layout = json.loads(out)["layout"]
    assert (layout["spatial_covariance"], layout["bins"], layout["bins_denoised"]) == (None, None, False)


def test_bin_channel_names_agree_between_exr_and_cli(tmp_path):
    """The sample-bin channel pattern is statmc.exr's alone (read_bins, and the CLI's
    _has_bins and `info` summary, which had their own copies): names near it are no bins
    for any of the three, Bin<b>.R/G/B and Bin<b>.Denoised.R/G/B are bins for all."""
    from types import SimpleNamespace

    from statmc import cli
    from statmc.exr import read_bins
    img = np.zeros((3, 4), np.float32)
    near = ["Bin0.A", "Bin.R", "Bin0.Denoised.X", "bin0.R", "Bin0.R.x", "Bin0.Denoised",
            "BinA.R", "Bin0.Denoised.Denoised.R"]
    bins = [f"Bin{b}.{d}{c}" for b in (0, 1) for d in ("", "Denoised.") for c in "RGB"]
    for names, nbins in ((near, None), (near + bins, 2)):
        path = tmp_path / f"b{nbins}.exr"
        _write_channels(path, {n: img for n in ["R", "G", "B"] + names})
        got = read_bins(path)
        assert (None if got is None else got[0].shape[0]) == nbins
        assert cli._has_bins(SimpleNamespace(meta={"extra_channels": names})) == bool(nbins)
        code, out, err = run_cli("info", path)
        assert code == 0, err
        info = json.loads(out)
        assert info["layout"]["bins"] == nbins
        assert info["layout"]["bins_denoised"] is bool(nbins)
        assert set(near) <= set(info["channels"])          # listed one by one, not as bins


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


_SCENE_EXPECTED = ("expected a built-in scene name (cornell-box, glass-caustic, glossy-spheres, "
                   "textured-dof, toy:constant, toy:edges, toy:fireflies, toy:gradient, "
                   "toy:mixed, toy:texture) or the path of an existing Mitsuba XML file.")


@pytest.mark.parametrize("command", ["render", "reference"])
def test_scene_that_is_an_image_or_a_directory_is_refused_in_cli_terms(tmp_path, toy_ref, command):
    # before: an EXR given as SCENE gave Mitsuba's "Parsing of XML file ... failed: No document
    # element found (line 13, col 179)", and a directory "`scene` 'bad' is neither a built-in
    # scene (...) nor an existing Mitsuba XML file" (the Python parameter's name)
    bad = tmp_path / "bad"
    bad.mkdir()
    image = bad / "good.exr"
    image.write_bytes(toy_ref.read_bytes())
    empty = tmp_path / "empty.xml"
    empty.write_bytes(b"")
    out = tmp_path / ("o" if command == "render" else "o.exr")
    for scene, what in ((image, "is an OpenEXR file, not a scene file"),
                        (bad, "is a directory"), (empty, "is an empty file")):
        code, _, err = run_cli(command, scene, "--spp", 4, "--out", out, "-q")
        _assert_one_line_error(code, err, f"SCENE {str(scene)!r} {what}; {_SCENE_EXPECTED}")
        assert "`scene`" not in err and "Parsing of XML" not in err
        assert not out.exists()


@pytest.mark.parametrize("command", ["render", "reference"])
@pytest.mark.parametrize("scene, why", [
    ("nonexistent.xml", "which is neither a built-in scene nor an existing file"),
    ("toy:nope", "which is not one of the toy scenes"), ("", "an empty name")])
def test_a_scene_that_does_not_exist_is_named_as_SCENE(tmp_path, command, scene, why):
    # before: "scene 'nonexistent.xml' is neither a file nor a built-in scene (...)", "unknown
    # toy scene 'toy:nope'; ..." and "`scene` must be a scene name or a Mitsuba XML path;
    # got ''" (the library's lowercase parameter, not the argument the user typed)
    out = tmp_path / ("o" if command == "render" else "o.exr")
    code, _, err = run_cli(command, scene, "--spp", 4, "--out", out, "-q")
    _assert_one_line_error(code, err, f"error: SCENE must be {_SCENE_EXPECTED[9:-1]}; got "
                                      f"{scene!r}, {why}.")
    assert "`scene`" not in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["counts.exr", "render.exr"])
def test_render_input_missing_in_out_is_missing_not_an_overwrite(tmp_path, toy_ref, name):
    # before: `--sample-map OUT/counts.exr --out OUT` (or --reference OUT/render.exr) with no
    # such file said "refusing to write 'OUT/counts.exr': it is the input file
    # 'OUT/counts.exr'", a guard meant for an output that would overwrite an existing input
    out = tmp_path / "OUT"
    out.mkdir()
    missing = out / name
    option = "--sample-map" if name == "counts.exr" else "--reference"
    spp = () if option == "--sample-map" else ("--spp", 2)
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", *spp, option, missing,
                           "--out", out, "-q")
    _assert_one_line_error(code, err, "does not exist")
    assert "input file" not in err and str(missing) in err
    assert os.listdir(out) == []
    # the guard stays for a file that exists: a sample map render would overwrite
    counts = out / "counts.exr"
    from statmc.exr import write_exr
    write_exr(counts, np.full((16, 24), 2.0, np.float32))   # one channel Y
    before = counts.read_bytes()
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", counts, "--out", out, "-q")
    _assert_one_line_error(code, err, f"it is the input file {str(counts)!r}")
    assert counts.read_bytes() == before and os.listdir(out) == ["counts.exr"]


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


@pytest.fixture(scope="module")
def toy_render2(tmp_path_factory):
    """An independent render of toy_render's scene (another seed): a Z for `combine`."""
    d = tmp_path_factory.mktemp("z")
    code, _, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--seed", 1,
                           "--out", d, "-q")
    assert code == 0, err
    return d / "render.exr"


def test_only_denoise_variance_oidn_builds_the_channel_covariance(tmp_path, toy_render,
                                                                   toy_render2, monkeypatch):
    """The commands read their statistics with read_exr(covariance=False) (no m2_cross:
    0.3-0.5 s and 143 MiB less at 1920x1080), except `denoise --variance --denoiser oidn`,
    whose first-order output variance uses the file's channel covariance (cmd_denoise's
    mean_cov).  Fails before: every read built m2_cross."""
    import statmc.exr as exr
    real, built = exr.read_exr, []

    def spy(*a, **k):
        s = real(*a, **k)
        built.append(s.has_cov)
        return s

    monkeypatch.setattr(exr, "read_exr", spy)
    out = tmp_path / "o.exr"
    assert real(toy_render).has_cov                   # the file has Covariance.* channels
    for argv, want in (
            (("reconstruct", toy_render), [False]),
            (("progressive", toy_render, "--denoiser", "gaussian"), [False]),
            (("denoise", toy_render, "--denoiser", "gem"), [False]),
            (("denoise", toy_render, "--denoiser", "gaussian"), [False]),
            (("denoise", toy_render, "--denoiser", "gaussian", "--variance"), [False]),
            (("denoise", toy_render, "--denoiser", "oidn", "--variance"), [True]),
            (("combine", toy_render, toy_render2, "--weights", "statistical", "--size", 5),
             [False, False]),
            (("combine", toy_render, toy_render2, "--weights", "uniform", "--size", 5), [False])):
        built.clear()
        code, _, err = run_cli(*argv, "--out", out, "-q")
        assert code == 0, err
        assert built == want, argv


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
    if den == "gem":  # the selected filter's exact variance, given GEM's selection
        from statmc.analytic import scale_kernels
        from statmc.gem import select
        from statmc.sure import kernel_variance
        x = raw.mean.astype(np.float32)
        info = select(x, raw.mean_var.astype(np.float32), n=np.maximum(raw.n, 2))
        np.testing.assert_array_equal(d.mean, info["image"])
        exact = kernel_variance(scale_kernels(info["scales"], info["sigmas"], dtype=np.float64),
                                raw.mean_var)
        # (finite differences crossed the selection's switches: up to 75,000x off)
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
    assert "statmc denoise --variance" in err and "require_variance" not in err
    small = tmp_path / "small.exr"
    write_exr(small, read_image(z)[:8, :8])
    code, _, err = run_cli("combine", toy_render, small, "--weights", "uniform", "--out", tmp_path / "x.exr")
    assert code == 2 and "same size" in err and not (tmp_path / "x.exr").exists()
    code, _, err = run_cli("combine", toy_render, z, "--weights", "uniform", "--out", z)
    assert code == 2 and "overwrite" in err


def test_combine_fixed_weights_take_a_plain_image_as_y(tmp_path, toy_render, toy_render2):
    """Regression: `combine Y Z --weights uniform|gaussian` refused a plain RGB Y without
    Variance.* and SampleCount (exit 2, 'has no Variance.R...'), which these weights never
    read.  It is combined now, exactly as the statistics file with the same colour; --spp
    (read by nothing there) is refused; --weights statistical still needs Y's statistics and
    says why; a --crn render (SpatialCovariance.*) or a bins file is still refused as Y even
    without Variance.*."""
    from statmc import combine as cb
    from statmc.exr import read_exr, read_image, spatial_covariance_channels
    st = read_exr(toy_render)
    rgb = {c: st.mean[..., k] for k, c in enumerate("RGB")}
    plain = tmp_path / "plain.exr"
    _write_channels(plain, rgb)
    y, z = read_image(plain), read_image(toy_render2)
    h, w, _ = y.shape
    for weights, wt in (("uniform", cb.uniform_weights(h, w, 1, 5)),
                        ("gaussian", cb.gaussian_weights(h, w, 1, 5, 3.0))):
        got = {}
        for name, path in (("plain", plain), ("stats", toy_render)):
            out = tmp_path / f"{weights}-{name}.exr"
            code, _, err = run_cli("combine", path, toy_render2, "--weights", weights,
                                   "--size", 5, "--out", out, "-q")
            assert code == 0, err
            got[name] = read_image(out)
        np.testing.assert_array_equal(got["plain"], got["stats"])
        np.testing.assert_array_equal(got["plain"], cb.combine(y, z, wt))
        code, _, err = run_cli("combine", plain, toy_render2, "--weights", weights, "--spp", 8,
                               "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, f"--spp has no effect with --weights {weights}")
    code, _, err = run_cli("combine", plain, toy_render2, "--out", tmp_path / "x.exr")
    _assert_one_line_error(code, err, "--weights statistical reads Y's statistics; --weights "
                           "uniform or gaussian combine a plain image.")
    assert "has no Variance.R" in err and "require_variance" not in err
    # a CRN file as Y, recognised by its SpatialCovariance.* channels without Variance.*
    cov = np.random.default_rng(0).uniform(0, 1, (h, w, 3, 3, 3))
    crn = tmp_path / "crn.exr"
    _write_channels(crn, {**rgb, **spatial_covariance_channels(cov, np.full((h, w), 8))})
    bins_dir = tmp_path / "b"
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--spp", 8, "--reconstruct",
                           "gem+bins", "--bins", 2, "--out", bins_dir, "-q")
    assert code == 0, err
    for yy, needle, all_weights in (
            (crn, "is a common-random-number render", ("uniform", "gaussian")),
            (bins_dir / "bins.exr", "combine it alone, without Z",
             ("uniform", "gaussian", "statistical"))):
        for weights in all_weights:
            code, _, err = run_cli("combine", yy, toy_render2, "--weights", weights,
                                   "--size", 3, "--out", tmp_path / "x.exr")
            _assert_one_line_error(code, err, needle)
    assert not (tmp_path / "x.exr").exists()


def test_combine_refuses_the_same_file_twice(tmp_path, toy_render):
    """Regression: `combine Y.exr Y.exr` was taken silently (Y combined with itself); the same
    path, another spelling of it, or a link to it is refused in one line."""
    import shutil
    link, hard = tmp_path / "link.exr", tmp_path / "hard.exr"
    os.symlink(toy_render, link)
    os.link(toy_render, hard)
    dotted = os.path.join(os.path.dirname(toy_render), ".", os.path.basename(toy_render))
    for z in (toy_render, dotted, link, hard):
        code, _, err = run_cli("combine", toy_render, z, "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, "Y and Z are the same file")
        assert not (tmp_path / "x.exr").exists()
    copy = tmp_path / "copy.exr"   # another file (with equal content) is not this check's
    shutil.copy(toy_render, copy)
    code, _, err = run_cli("combine", toy_render, copy, "--out", tmp_path / "x.exr", "-q")
    assert code == 0, err


def test_combine_same_file_check_resolves_symlinked_dirs_and_missing_files(tmp_path, toy_render,
                                                                           toy_render2):
    """Regression: the same-file check compared abspath lexically.  With a symlinked
    directory ``A/L -> ../B/C``, ``A/L/../y.exr`` is ``B/y.exr``, another file than
    ``A/y.exr``, but was refused as 'the same file'; and ``missing.exr ./missing.exr`` was
    called the same file instead of not found.  It now shares statmc._atomic.same_file with
    the output checks (samefile when both exist, else realpath)."""
    import shutil

    from statmc._atomic import same_file
    a, c = tmp_path / "A", tmp_path / "B" / "C"
    a.mkdir()
    c.mkdir(parents=True)
    shutil.copy(toy_render, a / "y.exr")
    shutil.copy(toy_render2, tmp_path / "B" / "y.exr")
    os.symlink(os.path.join("..", "B", "C"), a / "L")
    z = os.path.join(a, "L", "..", "y.exr")
    assert not same_file(a / "y.exr", z) and same_file(tmp_path / "B" / "y.exr", z)
    code, _, err = run_cli("combine", a / "y.exr", z, "--out", tmp_path / "x.exr", "-q")
    assert code == 0, err
    missing = tmp_path / "missing.exr"
    dotted = os.path.join(tmp_path, ".", "missing.exr")
    assert same_file(missing, dotted)            # an output path not written yet
    code, _, err = run_cli("combine", missing, dotted, "--out", tmp_path / "y.exr")
    _assert_one_line_error(code, err, "does not exist")
    assert "same file" not in err and not (tmp_path / "y.exr").exists()


def test_combine_refuses_a_window_wider_than_the_image(tmp_path, toy_render, toy_render2):
    """Regression: `combine --size 99999` tried to allocate the H·W·size² weights and failed
    with 'out of memory (596 TiB)'.  A window wider than 2·max(H, W) − 1 has taps outside
    the image for every pixel; it is refused up front, naming the image size and the
    largest useful --size, in both forms; that size itself is accepted."""
    d = tmp_path / "b"
    code, _, err = run_cli("render", "toy:edges", "--size", "6x4", "--spp", 4,
                           "--reconstruct", "gem+bins", "--bins", 2, "--out", d, "-q")
    assert code == 0, err
    for files, wh, largest in (((toy_render, toy_render2), "24x16", 47),
                               ((d / "bins.exr",), "6x4", 11)):
        for size in (99999, max(largest, 15) + 2):     # up to the default 15 is always taken
            code, _, err = run_cli("combine", *files, "--weights", "uniform", "--size", size,
                                   "--out", tmp_path / "x.exr")
            _assert_one_line_error(code, err, f"--size {size} is wider than a {wh} image can use")
            assert f"the largest useful --size is {largest}" in err
            assert "out of memory" not in err and not (tmp_path / "x.exr").exists()
    code, _, err = run_cli("combine", d / "bins.exr", "--weights", "uniform", "--size", 11,
                           "--out", tmp_path / "x.exr", "-q")
    assert code == 0, err


def test_combine_default_size_fits_small_images(tmp_path):
    """Regression: the check of dffda54 refused combine's own default --size 15 on any image
    with max(H, W) <= 7 ('--size 15 is wider than a 6x4 image can use'), which had worked.
    Without --size the window is 15 again on any image (byte-identical to the library's at
    15, as before dffda54); a --size the user gives is still refused when wider than
    2·max(H, W) − 1."""
    from statmc import combine as cb
    from statmc.exr import read_bins, read_exr, read_image
    d = tmp_path / "tiny"
    code, _, err = run_cli("render", "toy:mixed", "--size", "6x4", "--spp", 8,
                           "--reconstruct", "gem+bins", "--out", d, "-q")
    assert code == 0, err
    z = tmp_path / "z"
    code, _, err = run_cli("render", "toy:mixed", "--size", "6x4", "--spp", 8, "--seed", 1,
                           "--out", z, "-q")
    assert code == 0, err
    ys, zs = read_bins(d / "bins.exr")
    code, _, err = run_cli("combine", d / "bins.exr", "--out", tmp_path / "b.exr", "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_image(tmp_path / "b.exr"),
                                  cb.combine_bin_images(ys, zs, size=15).astype(np.float32))
    code, _, err = run_cli("combine", d / "bins.exr", "--size", 11, "--out", tmp_path / "b11.exr",
                           "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_image(tmp_path / "b11.exr"), read_image(tmp_path / "b.exr"))
    # the two-file form, each --weights: the library at the old default 15
    y_st, z_st = read_exr(d / "render.exr"), read_exr(z / "render.exr")
    y, zz = y_st.mean.astype(np.float32), z_st.mean.astype(np.float32)
    h, w, _ = y.shape
    expect = {"uniform": cb.uniform_weights(h, w, 1, 15),
              "gaussian": cb.gaussian_weights(h, w, 1, 15, 3.0),
              "statistical": cb.statistical_weights(y, zz, y_st.mean_var.astype(np.float32),
                                                    z_st.mean_var.astype(np.float32), 15)}
    for weights, wt in expect.items():
        out = tmp_path / f"{weights}.exr"
        code, _, err = run_cli("combine", d / "render.exr", z / "render.exr", "--weights", weights,
                               "--out", out, "-q")
        assert code == 0, err
        np.testing.assert_array_equal(read_image(out), cb.combine(y, zz, wt).astype(np.float32))
    # --size 15 typed out does what leaving it out does (it was refused: review, session 9)
    code, _, err = run_cli("combine", d / "bins.exr", "--size", 15, "--out", tmp_path / "b15.exr",
                           "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_image(tmp_path / "b15.exr"), read_image(tmp_path / "b.exr"))
    code, _, err = run_cli("combine", d / "render.exr", z / "render.exr", "--size", 15,
                           "--out", tmp_path / "x15.exr", "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_image(tmp_path / "x15.exr"), read_image(tmp_path / "statistical.exr"))


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
    the file's statistics; --gamma changes the paper's reconstruction only, and is refused with
    the pooled bias (it was accepted and the output was byte-identical to the default's)."""
    from statmc import gem
    from statmc.exr import read_exr, read_image
    st = read_exr(toy_render)
    imgs = {}
    for bias, gamma in (("pooled", None), ("paper", 0.2), ("paper", 0.05)):
        out = tmp_path / f"{bias}_{gamma}.exr"
        opts = () if gamma is None else ("--gamma", gamma)
        code, _, err = run_cli("reconstruct", toy_render, "--gem-bias", bias, *opts,
                               "--out", out, "-q")
        assert code == 0, err
        imgs[bias, gamma] = read_image(out)[..., :3]
        want = gem.reconstruct(st.mean.astype(np.float32), st.mean_var.astype(np.float32),
                               gamma=0.2 if gamma is None else gamma, n=st.n, bias=bias)
        np.testing.assert_allclose(imgs[bias, gamma], want, rtol=1e-6, atol=1e-7)
    assert not np.array_equal(imgs["paper", 0.2], imgs["paper", 0.05])
    assert not np.array_equal(imgs["paper", 0.2], imgs["pooled", None])
    for opts in (("--gem-bias", "pooled", "--gamma", 0.05), ("--gamma", 0.05)):
        code, _, err = run_cli("reconstruct", toy_render, *opts, "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, "--gamma has no effect on --method gem under "
                               "--gem-bias pooled")
        assert "--gem-bias paper" in err and not (tmp_path / "x.exr").exists()
    code, _, err = run_cli("reconstruct", toy_render, "--gem-bias", "robust", "--out", tmp_path / "x.exr")
    assert code == 2 and "robust" in err and not (tmp_path / "x.exr").exists()  # argparse's choices


def test_reconstruct_oidn_combine_matches_the_library(tmp_path, toy_render):
    """`statmc reconstruct --method oidn+combine` writes reconstruct_stats(..., "oidn+combine")
    of the file (Back 2020 with probed covariances and the SURE mix) and its mix channel; the
    GEM options are refused there, and so is a file without 2 samples in every pixel."""
    from statmc.exr import exr_info, read_exr, read_image
    from statmc.pipeline import reconstruct_stats
    out = tmp_path / "oc.exr"
    code, _, err = run_cli("reconstruct", toy_render, "--method", "oidn+combine", "--out", out, "-q")
    assert code == 0, err
    want, maps = reconstruct_stats(read_exr(toy_render), "oidn+combine")
    assert np.array_equal(read_image(out)[..., :3], want)
    assert "oidn+combine.mix" in exr_info(out)["channels"] and (tmp_path / "oc.png").exists()
    for opt in (("--gamma", 0.1), ("--gem-bias", "paper")):
        code, _, err = run_cli("reconstruct", toy_render, "--method", "oidn+combine", *opt,
                               "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, f"{opt[0]} has no effect on --method oidn+combine")
        assert not (tmp_path / "x.exr").exists()
    st = read_exr(toy_render)
    n = st.n.copy()
    n[0, 0] = 1
    one = tmp_path / "one.exr"
    from statmc.exr import write_exr
    from statmc.stats import PixelStats
    write_exr(one, PixelStats(n, st.mean, st.m2, albedo=st.albedo, normal=st.normal))
    code, _, err = run_cli("reconstruct", one, "--method", "oidn+combine", "--out", tmp_path / "x.exr")
    _assert_one_line_error(code, err, "--method oidn+combine needs a variance in every pixel")


def test_denoise_and_progressive_forward_gem_bias(tmp_path, toy_render):
    """`denoise --denoiser gem` and `progressive --denoiser gem` pass --gem-bias and --gamma to
    GEM: the paper's rule moves with γ; with the pooled default, which does not read γ,
    --gamma is refused (it was accepted, and the output did not change)."""
    from statmc.exr import read_image
    out = {}
    for cmd in ("denoise", "progressive"):
        for bias, gamma in (("paper", 0.05), ("paper", 0.3), ("pooled", None)):
            path = tmp_path / f"{cmd}_{bias}_{gamma}.exr"
            opts = () if gamma is None else ("--gamma", gamma)
            code, _, err = run_cli(cmd, toy_render, "--denoiser", "gem", "--gem-bias", bias,
                                   *opts, "--out", path, "-q")
            assert code == 0, err
            out[cmd, bias, gamma] = read_image(path)
        assert not np.array_equal(out[cmd, "paper", 0.05], out[cmd, "paper", 0.3])
        assert not np.array_equal(out[cmd, "paper", 0.3], out[cmd, "pooled", None])
        for opts in (("--gem-bias", "pooled", "--gamma", 0.3), ("--gamma", 0.3)):
            path = tmp_path / "x.exr"
            code, _, err = run_cli(cmd, toy_render, "--denoiser", "gem", *opts, "--out", path)
            _assert_one_line_error(code, err, "--gamma has no effect on --denoiser gem under "
                                   "--gem-bias pooled")
            assert not path.exists()


def _write_channels(path, channels):
    import OpenEXR
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}).write(str(path))


def test_denoise_takes_a_plain_image(tmp_path, toy_render):
    """Regression: `denoise --denoiser oidn|gaussian` (no --variance) refused a plain RGB EXR
    without Variance.* and SampleCount (say a reconstruction.exr), which it never reads.  It
    denoises it now, with OIDN's albedo/normal when the file has them; --variance and
    --denoiser gem still need the statistics and say why."""
    from statmc import denoisers
    from statmc.exr import read_exr, read_image
    from statmc.progressive import bind_denoiser
    st = read_exr(toy_render)
    rgb = {c: st.mean[..., k] for k, c in enumerate("RGB")}
    feats = {**{f"Albedo.{c}": st.albedo[..., k] for k, c in enumerate("RGB")},
             **{f"N.{c}": st.normal[..., k] for k, c in enumerate("XYZ")}}
    plain, with_features = tmp_path / "plain.exr", tmp_path / "feat.exr"
    _write_channels(plain, rgb)
    _write_channels(with_features, {**rgb, **feats})
    x = read_image(plain)
    got = {}
    for name, path in (("gaussian", plain), ("oidn", plain), ("oidn", with_features)):
        out = tmp_path / f"{name}-{path.stem}.exr"
        code, _, err = run_cli("denoise", path, "--denoiser", name, "--out", out, "-q")
        assert code == 0, err
        got[name, path.stem] = read_image(out)
    np.testing.assert_array_equal(got["gaussian", "plain"], denoisers.get("gaussian", sigma=1.0)(x))
    np.testing.assert_array_equal(got["oidn", "plain"], denoisers.oidn()(x))
    # the features are read: the same as the statistics file's OIDN (which binds them)
    np.testing.assert_array_equal(got["oidn", "feat"], bind_denoiser("oidn", st)(x))
    assert not np.array_equal(got["oidn", "feat"], got["oidn", "plain"])
    for opts, what in ((("--variance",), "--variance"), (("--denoiser", "gem"), "--denoiser gem")):
        code, _, err = run_cli("denoise", plain, *opts, "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, f"{what} reads the file's statistics; --denoiser oidn "
                               "or gaussian without --variance denoises a plain image.")
        assert "has no Variance.R" in err and not (tmp_path / "x.exr").exists()
    # --spp is still checked against a SampleCount channel where the statistics are read
    code, _, err = run_cli("denoise", toy_render, "--variance", "--spp", 3,
                           "--out", tmp_path / "x.exr")
    _assert_one_line_error(code, err, "--spp disagrees with the SampleCount channel")


def test_denoise_refuses_spp_where_nothing_reads_it(tmp_path, toy_render):
    """Regression: `denoise plain.exr --denoiser oidn --spp 4` took --spp silently, which
    nothing reads without --variance or --denoiser gem (the output was the same without
    it).  It is refused, as combine refuses it with --weights uniform|gaussian; a
    statistics file without SampleCount under --variance or --denoiser gem still reads it."""
    from statmc.exr import read_image
    st = _stat_channels(toy_render)
    plain = tmp_path / "plain.exr"
    _write_channels(plain, {c: st[c] for c in "RGB"})
    for path in (plain, toy_render):
        for den in ("oidn", "gaussian"):
            code, _, err = run_cli("denoise", path, "--denoiser", den, "--spp", 4,
                                   "--out", tmp_path / "x.exr")
            _assert_one_line_error(code, err, f"--spp has no effect on --denoiser {den} "
                                   "without --variance")
            assert not (tmp_path / "x.exr").exists()
    no_counts = tmp_path / "no-counts.exr"
    _write_channels(no_counts, {k: v for k, v in st.items() if k != "SampleCount"})
    for opts in (("--variance", "--denoiser", "gaussian"), ("--denoiser", "gem")):
        out = tmp_path / f"{opts[-1]}.exr"
        code, _, err = run_cli("denoise", no_counts, *opts, "--spp", 8, "--out", out, "-q")
        assert code == 0, err
        ref = tmp_path / f"{opts[-1]}-ref.exr"
        code, _, err = run_cli("denoise", toy_render, *opts, "--out", ref, "-q")
        assert code == 0, err
        np.testing.assert_array_equal(read_image(out), read_image(ref))


def _stat_channels(exr):
    """The channels of a statistics EXR as float32 arrays, to edit and write back."""
    from statmc.exr import read_channels
    return {k: np.array(v, np.float32) for k, v in read_channels(exr).items()}


def _assert_one_line_error(code, err, needle):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], err
    assert "Traceback" not in err


def _files(d):
    return sorted(p.name for p in d.rglob("*") if p.is_file())


@pytest.mark.parametrize("args, needle", [
    (["render", "toy:mixed", "--spp", "0", "--size", "24x16", "--out", "{tmp}/x"], "--spp"),
    (["render", "toy:mixed", "--spp", "2.5", "--size", "24x16", "--out", "{tmp}/x"], "--spp"),
    (["render", "toy:mixed", "--spp", "4.0", "--size", "24x16", "--out", "{tmp}/x"], "--spp"),
    (["render", "toy:mixed", "--spp", "4", "--seed", "-1", "--size", "24x16", "--out", "{tmp}/x"], "--seed"),
    (["render", "toy:mixed", "--spp", "4", "--gamma", "nan", "--out", "{tmp}/x"], "--gamma"),
    (["render", "toy:mixed", "--spp", "4", "--gamma", "0.9", "--out", "{tmp}/x"], "--gamma"),
    (["render", "toy:mixed", "--spp", "2", "--sampler", "gem", "--size", "24x16", "--out", "{tmp}/x"],
     "--spp budget above 4"),
    (["render", "toy:mixed", "--spp", "10000000000", "--size", "24x16", "--out", "{tmp}/x"], "--spp"),
    (["reference", "toy:mixed", "--spp", "8", "--pass-spp", "0", "--out", "{tmp}/x/r.exr"], "--pass-spp"),
    (["reference", "toy:mixed", "--spp", "0", "--out", "{tmp}/x/r.exr"], "--spp"),
    (["reconstruct", "{tmp}/in.exr", "--spp", "0", "--out", "{tmp}/x/r.exr"], "--spp"),
    (["denoise", "{tmp}/in.exr", "--denoiser", "gaussian", "--sigma", "0", "--out", "{tmp}/x/d.exr"],
     "--sigma"),
    (["progressive", "{tmp}/in.exr", "--seed", "-2", "--out", "{tmp}/x/p.exr"], "--seed"),
    (["combine", "{tmp}/in.exr", "{tmp}/in.exr", "--size", "4", "--out", "{tmp}/x/c.exr"], "--size"),
    (["metrics", "{tmp}/in.exr", "{tmp}/in.exr", "--replace-nonfinite", "nan"], "--replace-nonfinite"),
    (["render", "toy:mixed", "--spp", "4", "--bogus", "--out", "{tmp}/x"], "--bogus"),
])
def test_bad_numbers_are_refused_in_one_line_before_any_work(tmp_path, toy_render, args, needle):
    """Regression: --spp 0 rendered an empty image, --pass-spp 0 raised ZeroDivisionError,
    --seed -1 failed inside NumPy, and argparse's refusals printed a usage block."""
    os.link(toy_render, tmp_path / "in.exr")
    code, out, err = run_cli(*[a.replace("{tmp}", str(tmp_path)) for a in args])
    _assert_one_line_error(code, err, needle)
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_spp_help_and_library_agree_on_whole_numbers():
    """--spp is a positive integer on the command line ("4.0" is refused by the parser) and in
    counts_for_render, which used to accept 4.0 and 0."""
    from statmc.cli import counts_for_render
    from statmc.errors import InputError
    assert counts_for_render(2, 3, spp=np.int64(4)).tolist() == [[4] * 3] * 2
    for bad in (4.0, 0, -1, True, "4"):
        with pytest.raises(InputError, match="--spp must be a positive integer"):
            counts_for_render(2, 3, spp=bad)


@pytest.mark.parametrize("cmd", ["reconstruct", "denoise", "progressive", "combine", "reference"])
def test_out_paths_are_refused_before_any_work(tmp_path, toy_render, toy_render2, cmd):
    """Regression: `--out x.png` wrote the EXR and then the PNG preview onto the same path
    (the EXR was lost); an --out under a file or in an unwritable directory failed after the
    work with an OSError naming a temporary file."""
    inp = tmp_path / "in.exr"
    os.link(toy_render, inp)
    os.link(toy_render2, tmp_path / "in2.exr")
    (tmp_path / "file.txt").write_text("a file, not a directory")
    (tmp_path / "pv.png").mkdir()
    before = _files(tmp_path)
    head = {"reference": ["reference", "toy:mixed", "--spp", 4, "--size", "24x16"],
            "combine": ["combine", inp, tmp_path / "in2.exr", "--weights", "uniform"]}.get(cmd, [cmd, inp])
    for out, needle in ((tmp_path / "x.png", ".exr"), (tmp_path / "x.txt", ".exr"),
                        (tmp_path / "file.txt" / "x.exr", "not a directory"),
                        (tmp_path, "directory"), ("/proc/statmc-test.exr", "cannot create a file"),
                        (tmp_path / "pv.exr", "preview")):
        code, _, err = run_cli(*head, "--out", out)
        _assert_one_line_error(code, err, needle)
        assert "--out" in err and ".statmc-" not in err
    if cmd != "reference":
        code, _, err = run_cli(*head, "--out", inp)
        _assert_one_line_error(code, err, "input file")
    assert _files(tmp_path) == before and inp.read_bytes() == toy_render.read_bytes()


def test_render_out_must_be_a_writable_directory(tmp_path):
    (tmp_path / "file.txt").write_text("a file")
    (tmp_path / "d" / "counts.png").mkdir(parents=True)
    for out, needle in ((tmp_path / "file.txt", "not a directory"),
                        (tmp_path / "d", "counts.png"),
                        (tmp_path / "file.txt" / "sub", "not a directory"),
                        ("/proc/statmc-test", "cannot create a file")):
        code, _, err = run_cli("render", "toy:mixed", "--spp", 2, "--size", "24x16", "--out", out)
        _assert_one_line_error(code, err, needle)
        assert "--out" in err
    assert _files(tmp_path) == ["file.txt"]


def test_render_writes_nothing_when_the_reference_does_not_fit(tmp_path, toy_ref):
    """Regression: a one-channel reference of the right size failed in the metrics, after
    render.exr, render.png and counts.* had been written."""
    from statmc.exr import read_image
    gray = tmp_path / "gray.exr"
    _write_channels(gray, {"Y": read_image(toy_ref)[..., 0]})
    code, _, err = run_cli("render", "toy:mixed", "--spp", 2, "--size", "24x16", "--reference", gray,
                           "--out", tmp_path / "o", "-q")
    _assert_one_line_error(code, err, "1 channel")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_file_errors_name_the_command_line_options(tmp_path, toy_render):
    """Library hints (spp=, require_variance=False, nonfinite='replace') are worded as the
    command's options."""
    ch = _stat_channels(toy_render)
    nocount = {k: v for k, v in ch.items() if k != "SampleCount"}
    _write_channels(tmp_path / "nocount.exr", nocount)
    _write_channels(tmp_path / "novar.exr", {k: ch[k] for k in "RGB"})
    nan = dict(ch)
    nan["G"] = ch["G"].copy()
    nan["G"][1, 2] = np.nan
    _write_channels(tmp_path / "nan.exr", nan)
    # (plain `denoise` reads neither counts nor variances: test_denoise_takes_a_plain_image)
    for cmd in (("reconstruct",), ("denoise", "--variance"), ("progressive",)):
        code, _, err = run_cli(*cmd, tmp_path / "nocount.exr", "--out", tmp_path / "o.exr")
        _assert_one_line_error(code, err, "--spp N")
        assert "spp=" not in err
        code, _, err = run_cli(*cmd, toy_render, "--spp", 3, "--out", tmp_path / "o.exr")
        _assert_one_line_error(code, err, "omit --spp")
        code, _, err = run_cli(*cmd, tmp_path / "novar.exr", "--out", tmp_path / "o.exr")
        _assert_one_line_error(code, err, "Variance.R")
        assert "require_variance" not in err
        code, _, err = run_cli(*cmd, tmp_path / "nan.exr", "--out", tmp_path / "o.exr")
        _assert_one_line_error(code, err, "1 NaN")
        assert "nonfinite=" not in err
    code, _, err = run_cli("metrics", tmp_path / "nan.exr", toy_render)
    _assert_one_line_error(code, err, "--replace-nonfinite VALUE")
    _write_channels(tmp_path / "one.exr", dict(ch, SampleCount=np.ones_like(ch["SampleCount"])))
    code, _, err = run_cli("reconstruct", tmp_path / "one.exr", "--out", tmp_path / "o.exr")
    _assert_one_line_error(code, err, "sample count must be >= 2")
    _write_channels(tmp_path / "y.exr", {"Y": ch["G"], "Variance.Y": ch["Variance.G"],
                                         "SampleCount": ch["SampleCount"]})
    code, _, err = run_cli("denoise", tmp_path / "y.exr", "--denoiser", "oidn", "--out", tmp_path / "o.exr")
    # refused by the command before OIDN's own "`color` must be an (H, W, 3) image" (session 11)
    _assert_one_line_error(code, err, "is a one-channel (Y) image, but --denoiser oidn runs OIDN")
    assert not (tmp_path / "o.exr").exists()


def test_sample_map_mistakes(tmp_path):
    """An all-zero map, counts beyond what an EXR SampleCount holds (the render used to run
    for hours), and a file that is not a .npy array are refused before rendering."""
    np.save(tmp_path / "zeros.npy", np.zeros((16, 24)))
    np.save(tmp_path / "huge.npy", np.full((16, 24), 1e12))
    (tmp_path / "text.npy").write_text("not an array")
    for name, needle in (("zeros", "only zeros"), ("huge", "4294967295"), ("text", "not a NumPy")):
        code, _, err = run_cli("render", "toy:mixed", "--sample-map", tmp_path / f"{name}.npy",
                               "--out", tmp_path / "o")
        _assert_one_line_error(code, err, needle)
    np.save(tmp_path / "ones.npy", np.tile([0, 1, 4], (16, 8)))
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", tmp_path / "ones.npy",
                           "--reconstruct", "gem", "--out", tmp_path / "o")
    _assert_one_line_error(code, err, "--reconstruct gem needs at least 2 samples")
    assert not (tmp_path / "o").exists()


def test_denoising_aware_gem_sampler_gets_gem_bias_and_gamma(tmp_path, monkeypatch):
    """Regression: `render --sampler denoising-aware --denoiser gem` built its GEM denoiser
    without --gem-bias and --gamma.  Every GEM built inside the sampler gets both, and the
    paper's bias places samples differently from the pooled one."""
    import statmc.denoisers
    from statmc.exr import read_exr
    seen = []
    real = statmc.denoisers.gem

    def spy(*a, **kw):
        seen.append((kw.get("bias"), kw.get("gamma")))
        return real(*a, **kw)

    monkeypatch.setattr(statmc.denoisers, "gem", spy)
    counts = {}
    for bias, gamma in (("paper", 0.1), ("pooled", None)):  # pooled refuses --gamma
        seen.clear()
        opts = () if gamma is None else ("--gamma", gamma)
        code, _, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--sampler",
                               "denoising-aware", "--denoiser", "gem", "--gem-bias", bias, *opts,
                               "--out", tmp_path / bias, "-q")
        assert code == 0, err
        assert len(seen) >= 8 and set(seen) == {(bias, gamma or 0.2)}, seen  # one GEM per iteration
        counts[bias] = read_exr(tmp_path / bias / "render.exr").n
    assert counts["paper"].sum() == counts["pooled"].sum() == 8 * 24 * 16
    assert not np.array_equal(counts["paper"], counts["pooled"])


def test_expected_error_sampler_gem_kernels_get_gamma(tmp_path, monkeypatch):
    """--gamma reaches the GEM pilot kernels of --sampler expected-error (it was dropped)."""
    import statmc.analytic
    seen = []
    real = statmc.analytic.gem_kernels

    def spy(*a, **kw):
        seen.append(kw.get("gamma"))
        return real(*a, **kw)

    monkeypatch.setattr(statmc.analytic, "gem_kernels", spy)
    code, _, err = run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--sampler",
                           "expected-error", "--gamma", 0.1, "--out", tmp_path / "o", "-q")
    assert code == 0, err
    assert seen == [0.1]


def _subparsers():
    import argparse
    from statmc.cli import build_parser
    p = build_parser()
    action = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_every_command_has_help_and_every_option_is_documented():
    """Each subcommand's --help exits 0; docs/cli.md documents every option of every command
    in that command's section, and every option its synopsis shows exists."""
    import re
    docs = open(os.path.join(os.path.dirname(__file__), "..", "docs", "cli.md"), encoding="utf-8").read()
    sections = dict(re.findall(r"^## `statmc (\w+)`\n(.*?)(?=^## |\Z)", docs, flags=re.S | re.M))
    for name, sub in _subparsers().items():
        code, out, err = run_cli(name, "--help")
        assert code == 0 and out.startswith("usage: statmc " + name) and "by by" not in out, err
        if name == "scenes":
            continue
        assert name in sections, f"docs/cli.md has no section for statmc {name}"
        text = sections[name]
        synopsis = " ".join(line for line in text.splitlines() if line.startswith("    "))
        actions = [a for a in sub._actions if a.option_strings and "--help" not in a.option_strings]
        opts = {o for a in actions for o in a.option_strings}
        missing = {a.option_strings[-1] for a in actions
                   if not any(re.search(re.escape(o) + r"(?![\w-])", text) for o in a.option_strings)}
        assert not missing, f"statmc {name}: options not in docs/cli.md: {sorted(missing)}"
        shown = set(re.findall(r"(--[a-z][a-z-]*)", synopsis))
        assert shown <= opts, f"statmc {name}: docs show options that do not exist: {shown - opts}"


def test_render_into_a_used_directory_names_the_stale_files(tmp_path):
    """A second render into the same --out without --reconstruct leaves the first one's
    reconstruction behind: report.json lists this render's files and a note names the rest."""
    out = tmp_path / "o"
    code, _, err = run_cli("render", "toy:mixed", "--spp", 4, "--size", "24x16", "--reconstruct", "gem",
                           "--out", out, "-q")
    assert code == 0 and err == "", err
    assert "scales.exr" in json.loads((out / "report.json").read_text())["files"]
    code, _, err = run_cli("render", "toy:mixed", "--spp", 4, "--size", "24x16", "--out", out, "-q")
    assert code == 0
    files = json.loads((out / "report.json").read_text())["files"]
    assert sorted(files) == ["counts.exr", "counts.png", "render.exr", "render.png", "report.json"]
    assert "note" in err and "reconstruction.exr" in err and "scales.png" in err and "Traceback" not in err


def test_render_with_sampler_refuses_a_fractional_uniform_spp():
    """render_with_sampler(r, 2.5) rendered int(2.5) = 2 spp without a word."""
    from statmc.errors import InputError
    from statmc.pipeline import render_with_sampler
    from statmc.toy import ToyRenderer
    r = ToyRenderer("mixed", width=8, height=6)
    assert int(render_with_sampler(r, np.int64(3)).n.sum()) == 3 * 48
    for bad in (2.5, 0, -1, "4"):
        with pytest.raises(InputError, match="`spp` must be a positive integer"):
            render_with_sampler(r, bad)


def test_one_spp_files_are_refused_where_a_variance_is_needed(tmp_path):
    """A 1-spp render has no variance estimate; progressive denoising, GEM, --variance and
    statistical weights used to treat it as noise-free and return the raw image."""
    code, _, err = run_cli("render", "toy:mixed", "--spp", 1, "--size", "24x16", "--out", tmp_path, "-q")
    assert code == 0, err
    one = tmp_path / "render.exr"
    code, _, err = run_cli("render", "toy:mixed", "--spp", 1, "--size", "24x16", "--seed", 1,
                           "--out", tmp_path / "z", "-q")
    assert code == 0, err
    for args in (["progressive", one], ["denoise", one, "--denoiser", "gem"],
                 ["denoise", one, "--denoiser", "gaussian", "--variance"],
                 ["combine", one, tmp_path / "z" / "render.exr"]):
        code, _, err = run_cli(*args, "--out", tmp_path / "x.exr")
        _assert_one_line_error(code, err, "fewer than 2 samples")
    for rec in ("progressive", "oidn+combine"):
        code, _, err = run_cli("render", "toy:mixed", "--spp", 1, "--size", "24x16", "--reconstruct", rec,
                               "--out", tmp_path / "r")
        _assert_one_line_error(code, err, "at least 2 samples")
    assert not (tmp_path / "x.exr").exists() and not (tmp_path / "r").exists()
    code, _, err = run_cli("denoise", one, "--denoiser", "gaussian", "--out", tmp_path / "x.exr", "-q")
    assert code == 0, err  # a denoiser that needs no variance still runs


def test_a_closed_output_pipe_ends_quietly(toy_render):
    """`statmc info FILE | head -1` printed 'error: [Errno 32] Broken pipe' when head left."""
    exe = os.path.join(os.path.dirname(sys.executable), "statmc")
    p = subprocess.Popen([exe, "info", str(toy_render)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # the reader is gone before the command prints
    err = p.stderr.read().decode()
    assert p.wait() == 141 and err == "", err


# ------------------------------------------------------------------ common random numbers
def _render_y_and_crn_z(tmp_path, size, spp, stencil):
    """An independent render (seed 1) in ``tmp_path/y`` and a CRN render (seed 2) with a
    ``stencil``-wide covariance stencil in ``tmp_path/z``."""
    y_dir, z_dir = tmp_path / "y", tmp_path / "z"
    for d, seed, extra in ((y_dir, 1, ()), (z_dir, 2, ("--crn", "--stencil", stencil))):
        code, _, err = run_cli("render", "cornell-box", "--size", size, "--spp", spp,
                               "--seed", seed, *extra, "--out", d, "-q")
        assert code == 0, err
    return y_dir, z_dir


@pytest.mark.mitsuba
def test_render_crn_writes_the_stencil_and_combine_uses_it(tmp_path):
    """`render --crn` stores the covariance stencil beside the statistics; `combine
    --weights statistical` with that file as Z gives exactly the library's combination with
    the stencil, not the one with Z's per-pixel variance alone."""
    from statmc import combine as cb
    from statmc.exr import read_channels, read_exr, read_image, read_spatial_covariance

    y_dir, z_dir = _render_y_and_crn_z(tmp_path, "24x16", 4, 5)
    rep = json.loads((z_dir / "report.json").read_text())
    assert rep["crn"] is True and rep["stencil"] == 5 and rep["renderer_info"]["crn"]
    names = read_channels(z_dir / "render.exr")
    assert sum(n.startswith("SpatialCovariance.") for n in names) == 5 * 5 * 3
    z_stats = read_exr(z_dir / "render.exr")
    cov = read_spatial_covariance(z_dir / "render.exr")
    np.testing.assert_allclose(cov[:, :, 2, 2], z_stats.mean_var, rtol=1e-5, atol=1e-12)
    right = cov[:, :-1, 2, 3, :]
    assert np.median(right[right != 0]) > 0          # CRN: neighbouring errors correlate

    out = tmp_path / "c.exr"
    code, _, err = run_cli("combine", y_dir / "render.exr", z_dir / "render.exr", "--size", 5,
                           "--out", out, "-q")
    assert code == 0, err
    y_stats = read_exr(y_dir / "render.exr")
    y = y_stats.mean.astype(np.float32)
    z = z_stats.mean.astype(np.float32)
    want = cb.combine(y, z, cb.statistical_weights(y, z, y_stats.mean_var.astype(np.float32),
                                                   cov, 5))
    np.testing.assert_allclose(read_image(out), want, rtol=1e-5, atol=1e-6)
    diag = cb.combine(y, z, cb.statistical_weights(y, z, y_stats.mean_var.astype(np.float32),
                                                   z_stats.mean_var.astype(np.float32), 5))
    assert np.max(np.abs(want - diag)) > 1e-3

    # a window wider than the stencil, and --crn where it cannot work: one line, no files
    code, _, err = run_cli("combine", y_dir / "render.exr", z_dir / "render.exr", "--size", 7,
                           "--out", tmp_path / "c7.exr", "-q")
    assert code != 0 and "5x5 covariance stencil; --size must be at most 5" in err
    assert not (tmp_path / "c7.exr").exists()
    # without --size the default window is narrowed to the stencil (it was refused: 'got the
    # default 15', so render --crn --stencil 5, the 1080p setting, needed --size 5 spelled out)
    code, _, err = run_cli("combine", y_dir / "render.exr", z_dir / "render.exr",
                           "--out", tmp_path / "cd.exr", "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_image(tmp_path / "cd.exr"), read_image(out))
    code, _, err = run_cli("render", "cornell-box", "--size", "24x16", "--spp", 4, "--stencil", 5,
                           "--out", tmp_path / "nocrn", "-q")
    assert code != 0 and "--stencil" in err and "needs --crn" in err
    assert not (tmp_path / "nocrn").exists()
    for args, msg in ((("toy:mixed", "--spp", 4), "needs a Mitsuba scene"),
                      (("cornell-box", "--spp", 4, "--sampler", "gem"), "cannot be combined"),
                      (("cornell-box", "--spp", 1), "--crn needs --spp >= 2")):
        bad = tmp_path / "bad"
        code, _, err = run_cli("render", *args, "--size", "24x16", "--crn", "--out", bad, "-q")
        assert code != 0 and msg in err and "Traceback" not in err, err
        assert not bad.exists() or not any(bad.iterdir())


@pytest.mark.mitsuba
def test_crn_render_refused_where_independent_pixels_are_assumed(tmp_path):
    """A CRN render's pixel errors are correlated: it is refused as combine's Y (Back 2020
    §3.1 assumes an independent Y; with the roles swapped the 'combination' was worse than Y
    alone) and for --reconstruct (GEM, OIDN, ... assume independent pixels; on a 128x128
    Cornell box at 16 spp OIDN took an independent render's relMSE 0.016 -> 0.0028 but a
    CRN render's only 0.014 -> 0.014), also as the input of reconstruct, denoise and
    progressive.  One line, nothing written."""
    import shutil
    y_dir, z_dir = _render_y_and_crn_z(tmp_path, "12x8", 2, 3)
    z2_dir = tmp_path / "z2"      # another CRN file (Y and Z may not be one file)
    z2_dir.mkdir()
    shutil.copy(z_dir / "render.exr", z2_dir / "render.exr")
    for weights in ("statistical", "uniform"):
        for y, z in ((z_dir, y_dir), (z_dir, z2_dir)):
            out = tmp_path / f"c-{weights}.exr"
            code, _, err = run_cli("combine", y / "render.exr", z / "render.exr", "--size", 3,
                                   "--weights", weights, "--out", out, "-q")
            assert code != 0 and "is a common-random-number render" in err, err
            assert "pass the --crn render as Z" in err and "Traceback" not in err
            assert len(err.strip().splitlines()) == 1 and not out.exists()
    code, _, err = run_cli("combine", y_dir / "render.exr", z_dir / "render.exr", "--size", 3,
                           "--out", tmp_path / "ok.exr", "-q")
    assert code == 0, err
    for method in ("gem", "gaussian", "oidn", "progressive", "oidn+combine"):
        bad = tmp_path / f"rec-{method}"
        code, _, err = run_cli("render", "cornell-box", "--size", "12x8", "--spp", 2, "--crn",
                               "--reconstruct", method, "--out", bad, "-q")
        assert code != 0 and f"--crn cannot be combined with --reconstruct {method}" in err, err
        assert "Traceback" not in err and not bad.exists()
    # the same for the commands that reconstruct or denoise a file
    for cmd, opts in (("reconstruct", ()), ("denoise", ()), ("denoise", ("--variance",)),
                      ("progressive", ())):
        out = tmp_path / f"{cmd}.exr"
        code, _, err = run_cli(cmd, z_dir / "render.exr", *opts, "--out", out, "-q")
        assert code != 0 and f"but statmc {cmd} assumes independent pixel errors" in err, err
        assert "Traceback" not in err and not out.exists()


def test_render_gem_bins_and_oidn_bins_write_the_bins_and_match_the_library(tmp_path):
    """`render --reconstruct gem+bins` renders --bins equal sample bins: render.exr is their
    merge, bins.exr holds each bin's mean and its image under GEM's full-sample kernel
    (shared by the bins, Back 2020 §4.4), and the reconstruction is the library's Eq. 14
    on them.  Bad combinations are refused in one line with no files."""
    from statmc import gem
    from statmc.exr import read_bins, read_exr, read_image
    from statmc.pipeline import reconstruct_bins, render_bins
    from statmc.renderers import make_renderer

    out = tmp_path / "g"
    code, _, err = run_cli("render", "toy:edges", "--size", "24x16", "--spp", 8, "--seed", 3,
                           "--reconstruct", "gem+bins", "--out", out, "-q")
    assert code == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["bins"] == 4 and "bins.exr" in rep["files"]
    bins = render_bins(make_renderer("toy:edges", width=24, height=16), 8, 4, seed=3)
    stats = read_exr(out / "render.exr")
    ys, zs = read_bins(out / "bins.exr")
    assert ys.shape == zs.shape == (4, 16, 24, 3)
    np.testing.assert_allclose(ys, np.stack([b.mean for b in bins]), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(stats.mean, ys.mean(axis=0), rtol=1e-5, atol=1e-6)
    assert np.all(stats.n == 8)
    _, f = gem.selected_filter(stats.mean.astype(np.float32), stats.mean_var.astype(np.float32))
    np.testing.assert_allclose(zs, np.stack([f(y) for y in ys]), rtol=1e-5, atol=1e-6)
    want, _ = reconstruct_bins(bins, "gem+bins", seed=3)
    np.testing.assert_allclose(read_image(out / "reconstruction.exr"), want, rtol=1e-5, atol=1e-6)

    out2 = tmp_path / "o"
    code, _, err = run_cli("render", "toy:edges", "--size", "24x16", "--spp", 6, "--bins", 3,
                           "--reconstruct", "oidn+bins", "--out", out2, "-q")
    assert code == 0, err
    ys2, zs2 = read_bins(out2 / "bins.exr")
    assert ys2.shape == (3, 16, 24, 3) and np.max(np.abs(zs2 - ys2)) > 1e-3

    smap = tmp_path / "map.npy"
    np.save(smap, np.full((16, 24), 8.0))
    for args, msg in ((("--spp", 6), "multiple of --bins 4"),
                      (("--spp", 4), "at least 2 samples per bin"),
                      (("--spp", 8, "--bins", 1), "--bins must be at least 2"),
                      (("--spp", 8, "--sampler", "gem"), "cannot be combined"),
                      (("--spp", 8, "--sample-map", smap), "or a --sample-map")):
        bad = tmp_path / "bad"
        code, _, err = run_cli("render", "toy:edges", "--size", "24x16", "--reconstruct",
                               "gem+bins", *args, "--out", bad, "-q")
        assert code != 0 and msg in err and "Traceback" not in err, err
        assert not bad.exists() or not any(bad.iterdir())
    code, _, err = run_cli("render", "toy:edges", "--size", "24x16", "--spp", 8, "--bins", 4,
                           "--out", tmp_path / "nobins", "-q")
    assert code != 0 and "--bins" in err and "needs one of them" in err
    assert not (tmp_path / "nobins").exists()


def test_files_with_empty_or_single_sample_pixels_are_refused_where_variances_are_needed(tmp_path):
    """A sample-map render with holes (0 samples) and 1-sample pixels has no variance
    there; progressive, denoise --variance, combine --weights statistical and render
    --reconstruct progressive would take those pixels as exact (a hole as exact black).
    They refuse in one line naming how many pixels, and write nothing; plain OIDN and the
    uniform-weight combination still accept the file."""
    counts = np.full((16, 24), 8)
    counts[3, 4], counts[5, 6] = 0, 1
    np.save(tmp_path / "map.npy", counts)
    r = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--sample-map",
                           tmp_path / "map.npy", "--out", r, "-q")
    assert code == 0, err
    f = r / "render.exr"
    import shutil
    shutil.copy(f, tmp_path / "z.exr")    # Y and Z may not be one file
    for args in (("progressive", f, "--denoiser", "gaussian"),
                 ("denoise", f, "--denoiser", "oidn", "--variance"),
                 ("combine", f, tmp_path / "z.exr", "--weights", "statistical")):
        out = tmp_path / "o.exr"
        code, _, err = run_cli(*args, "--out", out, "-q")
        assert code != 0 and "2 of its 384 pixels" in err and "Traceback" not in err, err
        assert not out.exists()
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--sample-map",
                           tmp_path / "map.npy", "--reconstruct", "progressive", "--out",
                           tmp_path / "r2", "-q")
    assert code != 0 and "2 pixels with fewer" in err
    assert not (tmp_path / "r2").exists()
    code, _, err = run_cli("denoise", f, "--denoiser", "oidn", "--out", tmp_path / "d.exr", "-q")
    assert code == 0, err


def test_combine_takes_a_bins_file_without_z(tmp_path):
    """`statmc combine bins.exr` combines the file's bins with their denoised images by
    Eq. 14: statistical weights from the bins' spread, or uniform / Gaussian windows."""
    from statmc import combine as cb
    from statmc.exr import read_bins, read_image

    d = tmp_path / "b"
    code, _, err = run_cli("render", "toy:edges", "--size", "24x16", "--spp", 8,
                           "--reconstruct", "gem+bins", "--out", d, "-q")
    assert code == 0, err
    ys, zs = read_bins(d / "bins.exr")
    for weights, want in (("statistical", cb.combine_bin_images(ys, zs, size=5)),
                          ("uniform", cb.combine_multi(ys, zs, cb.uniform_weights(16, 24, 4, 5))),
                          ("gaussian", cb.combine_multi(ys, zs,
                                                        cb.gaussian_weights(16, 24, 4, 5, 3.0)))):
        out = tmp_path / f"{weights}.exr"
        code, _, err = run_cli("combine", d / "bins.exr", "--weights", weights, "--size", 5,
                               "--out", out, "-q")
        assert code == 0, err
        np.testing.assert_allclose(read_image(out), want, rtol=1e-5, atol=1e-6)
    code, _, err = run_cli("combine", d / "bins.exr", d / "render.exr", "--out",
                           tmp_path / "yz.exr", "-q")
    assert code != 0 and "combine it alone, without Z" in err and "Traceback" not in err, err
    assert not (tmp_path / "yz.exr").exists()
    from statmc.exr import bin_channels, write_exr
    write_exr(tmp_path / "ybins.exr", ys.mean(axis=0), extra=bin_channels(ys))
    for path, msg in ((d / "render.exr", "has no sample bins"),
                      (tmp_path / "ybins.exr", "no Bin<b>.Denoised.* channels")):
        code, _, err = run_cli("combine", path, "--out", tmp_path / "x.exr", "-q")
        assert code != 0 and msg in err and "Traceback" not in err, err
        assert not (tmp_path / "x.exr").exists()
    # --spp means nothing for a bins file (it was silently ignored); one bin has no spread
    write_exr(tmp_path / "one.exr", ys[0], extra=bin_channels(ys[:1], zs[:1]))
    for args, msg in (((d / "bins.exr", "--spp", 8), "leave --spp out"),
                      ((tmp_path / "one.exr",), "holds 1 sample bin")):
        code, _, err = run_cli("combine", *args, "--out", tmp_path / "x.exr", "-q")
        assert code != 0 and msg in err and "Traceback" not in err, err
        assert not (tmp_path / "x.exr").exists()


@pytest.mark.parametrize("extra", [("--reconstruct", "gem+bins"), ("--reconstruct", "oidn+bins"),
                                   ("--reconstruct", "gem"), ("--sampler", "gem"), ()])
def test_render_refuses_a_denoiser_it_would_ignore(tmp_path, extra):
    """`--denoiser` only matters to --sampler denoising-aware / expected-error and to
    --reconstruct progressive; elsewhere it used to be dropped without a word."""
    out = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--spp", 8, "--denoiser",
                           "gaussian", *extra, "--out", out, "-q")
    assert code != 0 and "--denoiser" in err and "no effect" in err
    assert "Traceback" not in err and not out.exists()


def test_render_accepts_a_denoiser_where_it_is_used(tmp_path):
    for extra in (("--reconstruct", "progressive"), ("--sampler", "denoising-aware")):
        out = tmp_path / extra[1]
        code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--spp", 8, "--denoiser",
                               "gaussian", *extra, "--out", out, "-q")
        assert code == 0, err
        assert (out / "render.exr").exists()


def test_adaptive_sampler_needs_more_than_its_pilot(tmp_path):
    """At --spp 4 the 4-spp pilot is the whole budget: the 'adaptive' render was a uniform
    one without a word."""
    out = tmp_path / "a"
    code, _, err = run_cli("render", "toy:mixed", "--size", "24x16", "--spp", 4, "--sampler",
                           "gem", "--out", out, "-q")
    assert code != 0 and "above 4" in err and not out.exists()


def test_bin_progress_goes_to_stderr(capsys):
    """Progress lines go to stderr (docs/cli.md), so stdout stays the result summary."""
    from statmc.pipeline import render_bins
    from statmc.renderers import make_renderer
    render_bins(make_renderer("toy:edges", width=8, height=8), 4, 2, seed=1, progress=True)
    out, err = capsys.readouterr()
    assert out == "" and "bin 1/2" in err and "bin 2/2" in err


def test_cli_gamma_default_is_gems():
    from statmc import cli, gem
    assert cli.DEFAULT_GAMMA == gem.DEFAULT_GAMMA


@pytest.mark.parametrize("args, bad", [
    (("denoise", "--denoiser", "oidn", "--gamma", "0.1"), "--gamma"),
    (("denoise", "--denoiser", "gaussian", "--gem-bias", "paper"), "--gem-bias"),
    (("denoise", "--denoiser", "gem", "--sigma", "2"), "--sigma"),
    (("progressive", "--denoiser", "oidn", "--gamma", "0.1", "--gem-bias", "paper"),
     "--gamma and --gem-bias"),
    (("combine", "--weights", "statistical", "--sigma", "2"), "--sigma"),
])
def test_options_without_effect_are_refused(tmp_path, toy_render, toy_render2, args, bad):
    """An option the command would ignore is refused in one line, before any output."""
    out = tmp_path / "o.exr"
    files = (toy_render, toy_render2) if args[0] == "combine" else (toy_render,)
    code, _, err = run_cli(args[0], *files, *args[1:], "--out", out, "-q")
    assert code != 0 and bad in err and "no effect" in err and "Traceback" not in err
    assert not out.exists()


def test_options_with_effect_are_accepted(tmp_path, toy_render, toy_render2):
    for args in (("denoise", toy_render, "--denoiser", "gem", "--gamma", "0.1", "--gem-bias",
                  "paper"),
                 ("denoise", toy_render, "--denoiser", "gaussian", "--sigma", "2"),
                 ("progressive", toy_render, "--denoiser", "gem", "--gem-bias", "paper"),
                 ("combine", toy_render, toy_render2, "--weights", "gaussian", "--sigma", "2")):
        out = tmp_path / f"{args[0]}-{len(args)}.exr"
        code, _, err = run_cli(*args, "--out", out, "-q")
        assert code == 0, err
        assert out.exists()


@pytest.mark.parametrize("opts, bad", [
    (("--spp", "4", "--gamma", "0.1"), "--gamma has no effect on --sampler uniform"),
    (("--spp", "4", "--reconstruct", "oidn", "--gem-bias", "paper"), "--gem-bias has no effect"),
    (("--spp", "4", "--reconstruct", "gaussian", "--gamma", "0.1", "--gem-bias", "paper"),
     "--gamma and --gem-bias have no effect"),
    (("--spp", "8", "--sampler", "gem", "--gem-bias", "paper"), "--sampler gem reads --gamma only"),
    # the reason must not list the --denoiser gem just given: only that of denoising-aware /
    # progressive reads --gem-bias (the message said "read by ... --denoiser gem")
    (("--spp", "8", "--sampler", "expected-error", "--denoiser", "gem", "--gem-bias", "paper"),
     "--denoiser gem with --sampler denoising-aware or --reconstruct progressive; --sampler "
     "expected-error reads --gamma only"),
    (("--spp", "8", "--sampler", "expected-error", "--denoiser", "gaussian", "--gamma", "0.1"),
     "--gamma has no effect on --sampler expected-error"),
    (("--spp", "8", "--sampler", "denoising-aware", "--gamma", "0.1"), "--gamma has no effect"),
    # GEM's pooled final selection does not read γ (the outputs were byte-identical)
    (("--spp", "4", "--reconstruct", "gem", "--gamma", "0.3"),
     "--gamma has no effect on --sampler uniform with --reconstruct gem under --gem-bias pooled "
     "(the default)"),
    (("--spp", "4", "--reconstruct", "gem+bins", "--bins", "2", "--gem-bias", "pooled",
      "--gamma", "0.3"), "under --gem-bias pooled: the pooled bias estimate does not use"),
    (("--spp", "4", "--reconstruct", "progressive", "--denoiser", "gem", "--gamma", "0.3"),
     "--gamma has no effect"),
    (("--spp", "8", "--sampler", "denoising-aware", "--denoiser", "gem", "--gamma", "0.3"),
     "read only with --gem-bias paper"),
])
def test_render_refuses_gem_options_it_would_ignore(tmp_path, opts, bad):
    """`render --gamma` / `--gem-bias` were accepted and dropped when nothing in the render
    reads them (no GEM sampler, reconstruction or denoiser); refused like denoise's."""
    out = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", *opts, "--out", out, "-q")
    _assert_one_line_error(code, err, bad)
    assert not out.exists()


def test_render_accepts_gem_options_where_they_are_read(tmp_path):
    # (--sampler gem / expected-error --gamma: test_expected_error_sampler_gem_kernels_get_gamma
    # and the adaptive tests above; an adaptive render here would cost ~6 s)
    for opts in (("--spp", "4", "--reconstruct", "gem", "--gamma", "0.1", "--gem-bias", "paper"),
                 ("--spp", "4", "--reconstruct", "progressive", "--denoiser", "gem",
                  "--gem-bias", "paper")):
        out = tmp_path / str(len(os.listdir(tmp_path)))
        code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", *opts, "--out", out, "-q")
        assert code == 0, err
        rep = json.loads((out / "report.json").read_text())
        assert rep["gamma"] == (0.1 if "--gamma" in opts else 0.2)
        assert rep["gem_bias"] == ("paper" if "--gem-bias" in opts else "pooled")
    # an adaptive sampler reads --gamma, so it is taken beside a pooled final selection
    import argparse
    from statmc.cli import _render_gem_defaults
    for sampler, denoiser in (("gem", None), ("expected-error", None), ("expected-error", "gem")):
        args = argparse.Namespace(sampler=sampler, reconstruct="gem", denoiser=denoiser,
                                  gamma=0.3, gem_bias=None)
        _render_gem_defaults(args)
        assert (args.gamma, args.gem_bias) == (0.3, "pooled")


@pytest.mark.parametrize("kind, needle", [
    ("empty", "not a NumPy .npy array file"),           # was an EOFError traceback
    ("complex", "real-valued (H, W) array"),            # was cast to real with a warning
    ("npz", "is a .npz archive of arrays ['a']"),       # was "got <U1 (1,)"
])
def test_bad_sample_map_files_are_one_line_errors(tmp_path, kind, needle):
    path = tmp_path / "map.npy"
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "complex":
        np.save(path, np.ones((6, 8), complex))
    else:
        with open(path, "wb") as f:
            np.savez(f, a=np.ones((6, 8)))
    out = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", path, "--out", out, "-q")
    _assert_one_line_error(code, err, needle)
    assert not out.exists()


@pytest.mark.parametrize("kind, needle", [
    # before: "cannot read sample map ...: not a NumPy .npy array file." for a .npy of
    # Python objects (np.save of a list of dicts), which is one
    ("object", r"holds Python objects \(dtype object, saved with pickle\); expected one \(H, W\) "
               r"array of numbers"),
    # before: "holds 384 NaN/Inf values." / "holds 384 negative values." without the expectation
    ("nan", r"holds 384 NaN/Inf values; expected finite numbers >= 0"),
    ("negative", r"holds 384 negative values; expected finite numbers >= 0"),
])
def test_sample_map_errors_say_what_was_expected(tmp_path, kind, needle):
    path = tmp_path / "map.npy"
    if kind == "object":
        np.save(path, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    else:
        np.save(path, np.full((16, 24), np.nan if kind == "nan" else -1.0))
    out = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--sample-map", path, "--out", out, "-q")
    _assert_one_line_error(code, err, "")
    assert re.search(needle, err), err
    assert not out.exists()


@pytest.mark.parametrize("name", ["cb16.exr", "out.png", "report.json", "Render.EXR"])
def test_render_out_named_like_a_file_is_refused(tmp_path, name):
    # before: `statmc render toy:mixed --spp 2 --out cb16.exr` made a directory cb16.exr/
    # holding render.exr, render.png, ... (the other commands' --out is a file)
    out = tmp_path / name
    code, _, err = run_cli("render", "toy:mixed", "--spp", "2", "--size", "8x8", "--out", out, "-q")
    _assert_one_line_error(code, err, f"--out {str(out)!r} ends in {os.path.splitext(name)[1]!r} "
                           "like a file, but render writes a directory of files (render.exr, "
                           "render.png, counts.exr, ...)")
    assert not out.exists() and os.listdir(tmp_path) == []
    out.mkdir()                  # a directory that exists is taken as named
    code, _, err = run_cli("render", "toy:mixed", "--spp", "2", "--size", "8x8", "--out", out, "-q")
    assert code == 0, err
    assert (out / "render.exr").is_file()
    slash = tmp_path / "new" / name   # a trailing separator names a directory: made and used
    code, _, err = run_cli("render", "toy:mixed", "--spp", "2", "--size", "8x8", "--out",
                           str(slash) + os.sep, "-q")
    assert code == 0, err
    assert (slash / "render.exr").is_file()


@pytest.mark.parametrize("command, option", [
    ("metrics", "--image-layer"), ("metrics", "--reference-layer"), ("metrics", "--layer"),
    ("combine", "--y-layer"), ("combine", "--z-layer"), ("reconstruct", "--layer"),
])
@pytest.mark.parametrize("name", ["", "ViewLayer.Combined."])
def test_a_bad_layer_name_is_refused_naming_the_option_given(tmp_path, command, option, name):
    # before: `metrics A B --image-layer ''` said "--layer must be a layer name ...", an
    # option the user had not given
    files = {"metrics": ["a.exr", "b.exr"], "combine": ["a.exr", "b.exr", "--out", "c.exr"],
             "reconstruct": ["a.exr", "--out", "c.exr"]}[command]
    code, _, err = run_cli(command, *[tmp_path / f if f.endswith(".exr") else f for f in files],
                           option, name)
    _assert_one_line_error(code, err, f"argument {option}: expected a layer name such as "
                           f"'ViewLayer.Combined' (without the channel's last part); got {name!r}")
    assert os.listdir(tmp_path) == []


def test_a_parent_layer_hint_names_the_whole_layer(tmp_path):
    # before: `--image-layer ViewLayer` on Blender's ViewLayer.Combined.R/G/B suggested
    # "--image-layer 'Combined'" (the name inside the layer), which reads nothing
    import OpenEXR
    rng = np.random.default_rng(0)
    p = tmp_path / "blender.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {f"ViewLayer.Combined.{c}": rng.random((4, 5)).astype(np.float32)
                  for c in "RGB"}).write(str(p))
    ref = tmp_path / "ref.exr"
    from statmc.exr import write_exr
    write_exr(ref, rng.random((4, 5, 3)))
    code, _, err = run_cli("metrics", p, ref, "--image-layer", "ViewLayer")
    _assert_one_line_error(code, err, "has no colour channels R, G, B (or Y) in layer "
                           "'ViewLayer'; channels present there: ['Combined.B', 'Combined.G', "
                           "'Combined.R']")
    assert ("R, G, B are only inside layer(s) 'ViewLayer.Combined' (e.g. "
            "'ViewLayer.Combined.R')") in err
    assert "R=ViewLayer.Combined.R,G=ViewLayer.Combined.G,B=ViewLayer.Combined.B" in err
    assert "give --image-layer 'ViewLayer.Combined' for IMAGE alone" in err
    code, out, err = run_cli("metrics", p, ref, "--image-layer", "ViewLayer.Combined")
    assert code == 0, err


def _tree(root):
    """{relative path: bytes} of every file under ``root`` (hidden ones included)."""
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            p = os.path.join(d, f)
            out[os.path.relpath(p, root)] = open(p, "rb").read()
    return out


@pytest.mark.parametrize("failure", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_failed_write_leaves_earlier_outputs_as_they_were(tmp_path, toy_render, monkeypatch,
                                                          failure):
    """Each file was atomic but the set was not: a full disk (or Ctrl-C) at the preview left
    a new OUT.exr beside the old OUT.png, and a render directory with the new render.exr and
    the old report.json.  Now all files of a command are renamed into place together."""
    import statmc.exr
    import statmc.plots
    d = tmp_path / "o"
    code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", "--spp", 4, "--out", d / "r", "-q")
    assert code == 0, err
    code, _, err = run_cli("reconstruct", toy_render, "--out", d / "rc.exr", "-q")
    assert code == 0, err
    before = _tree(tmp_path)

    def fail(*args, **kwargs):
        raise failure

    monkeypatch.setattr(statmc.plots, "write_map_png", fail)       # after render.exr/.png
    code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", "--spp", 8, "--out", d / "r",
                           "-q")
    monkeypatch.setattr(statmc.exr, "write_png_preview", fail)     # after rc.exr
    code2, _, err2 = run_cli("reconstruct", toy_render, "--out", d / "rc.exr", "-q")
    code3, _, err3 = run_cli("render", "toy:mixed", "--size", "8x6", "--spp", 4,
                             "--out", d / "new" / "r", "-q")
    assert _tree(tmp_path) == before                # nothing replaced, no temporary left
    assert not (d / "new").exists()                 # nor a directory made for the outputs
    if isinstance(failure, KeyboardInterrupt):
        assert (code, code2, code3) == (130, 130, 130)
    else:
        _assert_one_line_error(code, err, "could not write")
        assert f"{d / 'r' / 'counts.png'}" in err and "nothing was written" in err
        _assert_one_line_error(code2, err2, f"could not write {str(d / 'rc.png')!r}")
        assert ".statmc-" not in err + err2 + err3


def test_an_out_whose_directories_cannot_all_be_made_leaves_none(tmp_path, toy_render):
    """os.makedirs made a/ and a/b/ for --out a/b/<name too long>/out.exr, then failed: the
    staging left a/b/ behind (its cleanup ran only once the directory was made)."""
    code, _, err = run_cli("reconstruct", toy_render, "--out",
                           tmp_path / "a" / "b" / ("x" * 300) / "out.exr", "-q")
    _assert_one_line_error(code, err, "too long")
    assert os.listdir(tmp_path) == []


def test_sigterm_while_writing_is_cleaned_up_like_ctrl_c(tmp_path, monkeypatch):
    """SIGTERM (kill, timeout) ended the process without running `finally`, so a staged or
    temporary output stayed in the output directory; it now unwinds like Ctrl-C (exit 143)."""
    import signal

    import statmc.plots
    out = tmp_path / "r"
    code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", "--spp", 4, "--out", out, "-q")
    assert code == 0, err
    before = _tree(tmp_path)
    real = statmc.plots.write_map_png

    def killed(*args, **kwargs):
        real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(statmc.plots, "write_map_png", killed)
    handler = signal.getsignal(signal.SIGTERM)
    code, _, err = run_cli("render", "toy:mixed", "--size", "8x6", "--spp", 8, "--out", out, "-q")
    assert code == 143 and err.strip() == "statmc: terminated"
    assert _tree(tmp_path) == before
    assert signal.getsignal(signal.SIGTERM) is handler      # restored for in-process callers


def test_out_of_memory_is_one_line_naming_the_sizes(tmp_path, monkeypatch):
    import statmc.renderers

    def huge(*args, **kwargs):
        raise MemoryError("Unable to allocate 74.5 GiB for an array with shape (100000, 100000)")

    monkeypatch.setattr(statmc.renderers, "make_renderer", huge)
    code, _, err = run_cli("render", "toy:mixed", "--size", "100000x100000", "--spp", 4,
                           "--out", tmp_path / "r", "-q")
    _assert_one_line_error(code, err, "out of memory (Unable to allocate 74.5 GiB")
    assert "smaller --size" in err and not (tmp_path / "r").exists()


def test_warnings_are_one_line_naming_the_command(monkeypatch, capsys):
    """A library warning during a command (e.g. Mitsuba's slow fallback, or sample seeds
    wrapping around) is printed as ``statmc CMD: warning: ...``, without the source file
    and line of Python's default format; ``--debug`` keeps Python's format."""
    import warnings

    import statmc.cli as cli

    def noisy(args):
        warnings.warn("statmc: seed words wrap around", RuntimeWarning)
        return 0

    monkeypatch.setattr(cli, "cmd_scenes", noisy)
    assert main(["scenes"]) == 0
    err = capsys.readouterr().err
    assert err == "statmc scenes: warning: seed words wrap around\n"
    with pytest.warns(RuntimeWarning, match="wrap around"):   # Python's own handling
        assert main(["--debug", "scenes"]) == 0
    assert "warning:" not in capsys.readouterr().err


@pytest.mark.parametrize("denoiser", ["gaussian", "oidn"])
def test_denoise_refuses_a_file_without_samples(tmp_path, denoiser):
    """A statistics file whose SampleCount is 0 everywhere holds no render: denoise (whose
    gaussian / oidn paths need no variance) says so instead of writing a denoised zero image."""
    from statmc.exr import write_exr
    from statmc.stats import PixelStats
    write_exr(tmp_path / "empty.exr", PixelStats.empty(12, 16))
    code, _, err = run_cli("denoise", tmp_path / "empty.exr", "--denoiser", denoiser,
                           "--out", tmp_path / "den.exr")
    assert code == 2 and "no samples" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "den.exr").exists() and not (tmp_path / "den.png").exists()


def test_corrupt_exr_is_one_line_with_openexrs_diagnosis(tmp_path):
    """The command line captures OpenEXR's console lines about a damaged chunk: `info` prints
    one error line carrying OpenEXR's diagnosis (EXR_ERR_...) and nothing on stdout."""
    from statmc.exr import write_exr
    y, x = np.mgrid[0:256, 0:64]
    good = tmp_path / "good.exr"
    write_exr(good, np.repeat((np.sin(x / 7.0) * np.cos(y / 9.0))[..., None], 3, axis=2))
    d = bytearray(good.read_bytes())
    d[len(d) // 2:len(d) // 2 + 16] = b"\x55" * 16
    (tmp_path / "bad.exr").write_bytes(bytes(d))
    exe = os.path.join(os.path.dirname(sys.executable), "statmc")
    r = subprocess.run([exe, "info", str(tmp_path / "bad.exr")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == "", r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "EXR_ERR" in lines[0] and "bad.exr" in lines[0], r.stderr


def test_cached_reference_has_the_asked_samples_when_not_a_multiple_of_the_pass(tmp_path):
    """300 spp in passes of 256 is 256 + 44 (it rendered 256 into a file named 300spp); a
    multiple of the pass is rendered as before (same passes, same seeds)."""
    from statmc.demo import cached_reference
    from statmc.exr import read_exr
    from statmc.renderers import make_renderer
    r = make_renderer("toy:mixed", width=8, height=6)
    _, path = cached_reference(r, 300, str(tmp_path), pass_spp=256)
    assert path.endswith("300spp.exr") and np.all(read_exr(path).n == 300)
    _, path = cached_reference(r, 512, str(tmp_path), pass_spp=256)
    want = r.render(np.full((6, 8), 256), seed=1_000_003, features=False).merge(
        r.render(np.full((6, 8), 256), seed=1_000_003 + 7919, features=False))
    np.testing.assert_allclose(read_exr(path).mean, want.mean, rtol=1e-6, atol=1e-7)


def test_cached_reference_tells_sensors_and_scene_parameters_apart(tmp_path):
    """Regression (session 10 review): the cache file name was scene, size and spp only, so
    another camera (``sensor``) or other ``$name`` values (``params``) of one scene file at
    the same size were served the first one's reference.  The attributes are set on a toy
    renderer here (no Mitsuba needed): the name is all cached_reference reads of them."""
    from statmc.demo import cached_reference
    from statmc.renderers import make_renderer
    paths = []
    for sensor, params in ((0, {}), (1, {}), (0, {"w": 2}), (0, {"w": 3}), (0, {"w": 2})):
        r = make_renderer("toy:mixed", width=4, height=3)
        r.sensor, r.params = sensor, params
        paths.append(cached_reference(r, 4, str(tmp_path), pass_spp=4)[1])
    assert len(set(paths[:4])) == 4 and paths[4] == paths[2]
    assert paths[0].endswith("-4x3-4spp.exr")            # the default's name is unchanged


def test_combine_spp_for_y_leaves_zs_own_counts(tmp_path):
    """`--spp` is for a Y without SampleCount; a Z with its own counts (say a --crn render at
    another spp) keeps them (`--spp` was applied to Z too: 'disagrees with SampleCount')."""
    from statmc.exr import read_exr, write_exr
    run_cli("render", "toy:mixed", "--spp", 16, "--size", "24x16", "--out", tmp_path / "y", "-q")
    run_cli("render", "toy:mixed", "--spp", 8, "--size", "24x16", "--seed", 3,
            "--out", tmp_path / "z", "-q")
    ys = read_exr(tmp_path / "y" / "render.exr")
    v = ys.sample_var
    write_exr(tmp_path / "y_nocount.exr", ys.mean,
              extra={f"Variance.{c}": v[..., k] for k, c in enumerate("RGB")})
    code, _, err = run_cli("combine", tmp_path / "y_nocount.exr", tmp_path / "z" / "render.exr",
                           "--spp", 16, "--out", tmp_path / "c.exr", "-q")
    assert code == 0, err
    code, _, err = run_cli("combine", tmp_path / "y_nocount.exr", tmp_path / "z" / "render.exr",
                           "--out", tmp_path / "c2.exr", "-q")
    assert code == 2 and "SampleCount" in err and "--spp" in err, err


@pytest.mark.parametrize("extra, ok", [(("--denoiser", "gaussian"), False),
                                       (("--denoiser", "gaussian", "--variance"), False),
                                       (("--denoiser", "oidn"), False),
                                       (("--denoiser", "oidn", "--variance"), True)])
def test_denoise_seed_only_where_it_seeds_something(tmp_path, toy_render, extra, ok):
    """`denoise --seed` seeds only OIDN's --variance probes; elsewhere it is refused like
    the other unused options (it was accepted and ignored)."""
    code, _, err = run_cli("denoise", toy_render, *extra, "--seed", 5,
                           "--out", tmp_path / "d.exr", "-q")
    if ok:
        assert code == 0, err
    else:
        assert code == 2 and "--seed has no effect" in err, err
        assert not (tmp_path / "d.exr").exists()


def test_library_keyword_stencil_reads_as_the_option():
    from statmc.cli import _cli_message
    assert _cli_message("use a smaller `stencil`.", "render") == "use a smaller --stencil."


def test_python_dash_m_statmc_runs_the_command_line():
    """`python -m statmc` failed ("No module named statmc.__main__")."""
    p = subprocess.run([sys.executable, "-m", "statmc", "--version"], capture_output=True,
                       text=True, timeout=120)
    from statmc import __version__
    assert p.returncode == 0 and p.stdout.strip() == f"statmc {__version__}", p.stderr


def test_reference_help_gives_the_seed_default_and_summary_says_1_pass(tmp_path, capsys):
    """`reference --seed` help gave no default; the summary line said "1 passes"."""
    code, out, _ = run_cli("reference", "--help")
    assert code == 0 and "default 1000003" in " ".join(out.split())
    code, out, err = run_cli("reference", "toy:constant", "--spp", 4, "--pass-spp", 4,
                             "--size", "4x4", "--out", tmp_path / "r.exr")
    assert code == 0, err
    assert out.strip().endswith("(4 spp in 1 pass)"), out
    code, out, err = run_cli("reference", "toy:constant", "--spp", 5, "--pass-spp", 4,
                             "--size", "4x4", "--out", tmp_path / "r.exr")
    assert code == 0 and out.strip().endswith("(5 spp in 2 passes)"), out + err


def test_demo_help_names_the_module_and_explains_every_option(capsys):
    """`python -m statmc.demo --help` showed "usage: demo.py" and options without help;
    --ref-spp took 0 and negative numbers."""
    from statmc.demo import main as demo_main
    with pytest.raises(SystemExit) as e:
        demo_main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert e.value.code == 0 and out.startswith("usage: python -m statmc.demo ")
    for opt, text in (("--out OUT", "output directory (default out/demo)"),
                      ("--scene SCENE", "scene rendered at 128x128"),
                      ("--ref-spp REF_SPP", "samples per pixel of the reference")):
        assert f"{opt} {text}" in out, (opt, out)
    assert "(default cornell-box)" in out and "(default 4096)" in out
    assert "demo.py" not in out
    for bad in ("0", "-3", "2.5"):
        with pytest.raises(SystemExit) as e:
            demo_main(["--ref-spp", bad])
        assert e.value.code == 2 and "positive integer" in capsys.readouterr().err


def test_demo_reports_bad_input_in_one_line(tmp_path, capsys, monkeypatch):
    """Regression: `python -m statmc.demo --scene nosuchscene` (an unknown scene, an --out
    that is a file, a corrupt cached reference) printed a Python traceback and left an
    empty --out.  It reports one line and exits 2 like the statmc commands (it shares
    statmc.cli.run_command: Ctrl-C 130, out of memory with a hint); --debug re-raises."""
    import statmc.demo as demo
    from statmc.errors import InputError
    from statmc.renderers import make_renderer
    (tmp_path / "afile").write_text("not a directory")
    (tmp_path / "cache").mkdir()
    r = make_renderer("toy:constant", width=128, height=128)
    bad = tmp_path / "cache" / f"{r.name.replace(':', '_')}-128x128-8spp.exr"
    bad.write_bytes(b"not an EXR file")
    for args, needle in ((["--scene", "nosuchscene"], "got 'nosuchscene', which is neither a "
                                                      "built-in scene nor an existing file"),
                         (["--scene", "toy:nope"], "got 'toy:nope', which is not one of the toy "
                                                   "scenes"),
                         (["--scene", "toy:constant", "--out", str(tmp_path / "afile")],
                          "is not a directory"),
                         (["--scene", "toy:constant", "--ref-spp", "8"],
                          "it is a cached reference: delete it to render it again")):
        code = demo.main(["--out", str(tmp_path / "d"), *args])
        err = capsys.readouterr().err
        assert code == 2, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("python -m statmc.demo: error: "), err
        assert needle in lines[0] and "Traceback" not in err
        if "--scene" in args and "toy:constant" not in args:   # the option, as typed
            assert lines[0].startswith("python -m statmc.demo: error: --scene must be a "
                                       "built-in scene name (cornell-box, "), err
        assert not (tmp_path / "d").exists()
    with pytest.raises(InputError, match="nosuchscene"):
        demo.main(["--scene", "nosuchscene", "--debug"])
    for exc, code, needle in ((KeyboardInterrupt(), 130, "python -m statmc.demo: interrupted"),
                              (MemoryError("Unable to allocate 9 TiB"), 2,
                               "out of memory (Unable to allocate 9 TiB); expected inputs that "
                               "fit in memory: use a smaller --ref-spp or another --scene.")):
        def fail(*a, exc=exc, **k):
            raise exc
        monkeypatch.setattr(demo, "run", fail)
        assert demo.main([]) == code
        assert needle in capsys.readouterr().err
    monkeypatch.setattr(demo, "run", lambda *a, **k: [{"relmse": 1.0}])
    assert demo.main([]) == 0


def test_demo_library_functions_refuse_a_bool_or_negative_seed():
    """Regression (session 16, review): ``render_reference(seed=True)`` and
    ``compare(seed=True)`` ran as seed 1 (pass seeds ``seed + 7919 k`` are plain ints, so
    the renderers' own seed checks never saw the bool)."""
    import statmc.demo as demo
    from statmc.errors import InputError
    from statmc.renderers import make_renderer
    r = make_renderer("toy:constant", width=4, height=4)
    for bad in (True, -1, 2.0):
        with pytest.raises(InputError, match="`seed` must be a non-negative integer"):
            demo.render_reference(r, 2, seed=bad, progress=False)
        with pytest.raises(InputError, match="`seed` must be a non-negative integer"):
            demo.compare(r, None, [4], seed=bad, quiet=True)
    assert demo.render_reference(r, 2, seed=0, progress=False).n.min() == 2


def test_python_dash_m_statmc_demo_exits_2_on_bad_input(tmp_path):
    """The module entry itself: one line on stderr, exit status 2 (was a traceback, 1)."""
    p = subprocess.run([sys.executable, "-m", "statmc.demo", "--scene", "nosuchscene",
                        "--out", str(tmp_path / "d")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and p.stderr.startswith("python -m statmc.demo: error: "), p.stderr
    assert "error: --scene must be a built-in scene name (cornell-box, " in p.stderr, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and not (tmp_path / "d").exists()


# ------------------------------------------------------------------ user Mitsuba XML scenes
def _user_xml(tmp_path, *, integrator="path", sampler_spp="$spp", rfilter="box"):
    path = tmp_path / "user.xml"
    path.write_text(f"""<scene version="3.0.0">
  <integrator type="{integrator}"/>
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="stratified"><integer name="sample_count" value="{sampler_spp}"/></sampler>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="8"/>
      <rfilter type="{rfilter}"/></film></sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>""")
    return path


@pytest.mark.mitsuba
def test_render_and_reference_define_xml_parameters(tmp_path):
    # regression: `statmc render` had no way to give a value to a $name the file uses
    # without a <default>, and the error showed Mitsuba's "[parser.cpp:451]"
    scene = _user_xml(tmp_path)
    code, _, err = run_cli("render", scene, "--spp", 4, "--out", tmp_path / "a", "-q")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "undefined parameter: $spp; give it a value with `-D spp=VALUE` or add <default" in err
    # without --spp: the file's sample_count is not the budget, and the error says so
    code, _, err = run_cli("render", scene, "-D", "spp=16", "--out", tmp_path / "a", "-q")
    assert code == 2 and "the sample_count (16) of" in err and "is not used" in err, err
    assert "params" not in err and ".cpp" not in err
    code, _, err = run_cli("render", scene, "--spp", 8, "-D", "spp=16", "--sampler", "gem",
                           "--reconstruct", "gem", "--out", tmp_path / "a", "-q")
    assert code == 0 and err == "", err
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    # the file's sample_count (16) is not the budget: --spp is
    assert rep["scene_params"] == {"spp": "16"} and rep["total_samples"] == 8 * 12 * 8
    code, _, err = run_cli("reference", scene, "--spp", 8, "--define", "spp=3",
                           "--out", tmp_path / "ref.exr", "-q")
    assert code == 0 and err == "", err
    for args, needle in ((("-D", "spp"), "expected NAME=VALUE"),
                         (("-D", "=3"), "expected NAME=VALUE"),
                         (("-D", "spp=1", "-D", "other=2"), "unused parameters")):
        code, _, err = run_cli("render", scene, "--spp", 4, *args, "--out", tmp_path / "b", "-q")
        assert code == 2 and len(err.strip().splitlines()) == 1 and needle in err, err
    for name in ("cornell-box", "toy:mixed"):
        code, _, err = run_cli("render", name, "--spp", 4, "-D", "spp=1", "--out", tmp_path / "b")
        assert code == 2 and "is a built-in scene: leave -D out" in err, err


@pytest.mark.mitsuba
def test_render_user_xml_says_what_it_does_not_use(tmp_path):
    # a Gaussian film filter: one warning line; a light tracer: one error line
    scene = _user_xml(tmp_path, sampler_spp="4", rfilter="gaussian")
    code, _, err = run_cli("render", scene, "--spp", 2, "--out", tmp_path / "a", "-q")
    assert code == 0 and err.count("\n") == 1, err
    assert err.startswith("statmc render: warning: scene ") and "GaussianFilter is not used" in err
    scene = _user_xml(tmp_path, sampler_spp="4", integrator="ptracer")
    code, _, err = run_cli("render", scene, "--spp", 2, "--out", tmp_path / "b", "-q")
    assert code == 2 and err.count("\n") == 1 and "ptracer" in err and "Traceback" not in err, err


@pytest.mark.mitsuba
def test_render_sensor_picks_a_camera_of_the_file(tmp_path):
    scene = tmp_path / "two.xml"
    cam = ('<sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, {z}" '
           'target="0, 0, 0" up="0, 1, 0"/></transform><film type="hdrfilm"><integer '
           'name="width" value="{w}"/><integer name="height" value="4"/><rfilter type="box"/>'
           '</film></sensor>')
    scene.write_text('<scene version="3.0.0"><integrator type="path"/>'
                     + cam.format(z=4, w=6) + cam.format(z=-4, w=10)
                     + '<shape type="sphere"><bsdf type="diffuse"/></shape>'
                       '<emitter type="constant"/></scene>')
    code, _, err = run_cli("render", scene, "--spp", 2, "--sensor", 1, "--out", tmp_path / "a", "-q")
    assert code == 0, err
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert (rep["width"], rep["renderer_info"]["sensor"]) == (10, 1)
    code, _, err = run_cli("reference", scene, "--spp", 2, "--sensor", 1, "--size", "5x3",
                           "--out", tmp_path / "ref.exr", "-q")
    assert code == 0, err
    from statmc.exr import read_image
    assert read_image(tmp_path / "ref.exr").shape == (3, 5, 3)
    for args, needle in ((("--sensor", 2), "--sensor must be the index of one of the 2 sensors"),
                         (("--sensor", -1), "expected a sensor index >= 0"),
                         (("-D", "1x=2"), "-D names must be XML parameter names")):
        code, _, err = run_cli("render", scene, "--spp", 2, *args, "--out", tmp_path / "b", "-q")
        assert code == 2 and err.count("\n") == 1 and needle in err, err
    code, _, err = run_cli("render", "toy:mixed", "--spp", 2, "--sensor", 0, "--out", tmp_path / "b")
    assert code == 2 and "leave --sensor out" in err, err


@pytest.mark.mitsuba
def test_render_cropped_film_with_a_sample_map_of_its_size(tmp_path):
    # regression: a sample map sets the render's size, and the crop window's own size was
    # refused as a resize, telling the user to omit a --size they had not given
    scene = _user_xml(tmp_path, sampler_spp="4")
    text = scene.read_text().replace(
        '<rfilter type="box"/>', '<rfilter type="box"/><integer name="crop_offset_x" value="2"/>'
        '<integer name="crop_width" value="5"/><integer name="crop_height" value="3"/>')
    scene.write_text(text)
    np.save(tmp_path / "map.npy", np.full((3, 5), 2.0))
    code, _, err = run_cli("render", scene, "--sample-map", tmp_path / "map.npy",
                           "--out", tmp_path / "a", "-q")
    assert code == 0 and err == "", err
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert (rep["width"], rep["height"], rep["total_samples"]) == (5, 3, 30)
    code, _, err = run_cli("render", scene, "--spp", 2, "--size", "6x3", "--out", tmp_path / "b")
    assert code == 2 and err.count("\n") == 1, err
    assert "new film size 6x3 would not resize; make the size the crop window's, 5x3, or omit --size" in err


@pytest.mark.mitsuba
def test_report_counts_the_nonfinite_samples_of_every_pass(tmp_path):
    # regression: renderer_info.nonfinite_samples of an adaptive render was its first
    # pass's count (meta of the merged passes is the first's): 192 of 960 here, where
    # every sample sees an infinite sky
    scene = tmp_path / "inf.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="path"/><sensor '
                     'type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
                     '<integer name="height" value="6"/><rfilter type="box"/></film></sensor>'
                     '<emitter type="constant"><rgb name="radiance" value="inf"/></emitter>'
                     '</scene>')
    code, _, err = run_cli("render", scene, "--spp", 20, "--sampler", "gem",
                           "--out", tmp_path / "a", "-q")
    assert code == 0 and err.count("\n") == 1 and "192 of 192 samples" in err, err
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert rep["renderer_info"]["passes"] > 1
    assert rep["renderer_info"]["nonfinite_samples"] == rep["total_samples"] == 20 * 48


# --------------------------------------------- files from other tools: windows (session 11)
def _write_windowed(path, channels, data_window, display_window):
    import OpenEXR
    (x0, y0, x1, y1), (u0, v0, u1, v1) = data_window, display_window
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "dataWindow": (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32)),
                  "displayWindow": (np.array([u0, v0], np.int32), np.array([u1, v1], np.int32))},
                 {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}).write(str(path))


def _crop_stats(rng, h=8, w=10):
    ch = {c: rng.random((h, w)) for c in "RGB"}
    ch.update({f"Variance.{c}": rng.random((h, w)) * 0.05 for c in "RGB"})
    ch["SampleCount"] = np.full((h, w), 16.0)
    return ch


CROP = ([3, 2, 12, 9], [0, 0, 19, 15])     # a 10x8 crop at (3, 2) of a 20x16 frame


# the commands whose output keeps its (first) input's windows, chromaticities and alpha
_KEEPING_COMMANDS = pytest.mark.parametrize("args", [
    ["reconstruct", "{a}"],
    ["reconstruct", "{a}", "--method", "oidn+combine"],
    ["denoise", "{a}", "--denoiser", "gaussian"],
    ["denoise", "{a}", "--denoiser", "gaussian", "--variance"],
    ["progressive", "{a}", "--denoiser", "gaussian"],
    ["combine", "{a}", "{b}", "--weights", "uniform"],
    ["combine", "{a}", "{b}", "--weights", "statistical"],
], ids=lambda a: " ".join(a[:1] + a[2:]))


@_KEEPING_COMMANDS
def test_outputs_keep_the_inputs_data_and_display_windows(tmp_path, args):
    # before: every output was written at the origin with display window = data window,
    # so the reconstruction of a crop (pbrt-v4 writes its cropwindow so) lost its place
    from statmc.exr import exr_windows, read_image
    rng = np.random.default_rng(7)
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    _write_windowed(a, _crop_stats(rng), *CROP)
    _write_windowed(b, _crop_stats(rng), *CROP)
    out = tmp_path / "out.exr"
    code, _, err = run_cli(*[x.format(a=a, b=b) for x in args], "--out", out, "-q")
    assert code == 0, err
    assert exr_windows(out) == CROP
    assert read_image(out).shape == (8, 10, 3)


def test_combine_bins_file_keeps_its_windows(tmp_path):
    from statmc.exr import bin_channels, exr_windows, write_exr
    rng = np.random.default_rng(8)
    ys = rng.random((2, 8, 10, 3))
    p = tmp_path / "bins.exr"
    write_exr(p, ys.mean(0), extra=bin_channels(ys, ys * 0.9), data_window=CROP[0],
              display_window=CROP[1])
    code, _, err = run_cli("combine", p, "--out", tmp_path / "out.exr", "-q")
    assert code == 0, err
    assert exr_windows(tmp_path / "out.exr") == CROP


@pytest.mark.parametrize("cmd", [["metrics"], ["combine", "--weights", "uniform", "--out", "{o}"]])
def test_same_size_in_different_places_is_refused(tmp_path, cmd):
    # before: `statmc metrics` compared the crop at (3, 2) with the frame's top-left corner
    # pixel by pixel and printed relmse 0.0 for two images of different parts of the frame
    rng = np.random.default_rng(9)
    ch = {c: rng.random((8, 10)) for c in "RGB"}
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    _write_windowed(a, ch, [0, 0, 9, 7], CROP[1])
    _write_windowed(b, ch, *CROP)
    out = tmp_path / "o.exr"
    code, stdout, err = run_cli(cmd[0], a, b, *[x.format(o=out) for x in cmd[1:]])
    assert code == 2 and stdout == "" and err.count("\n") == 1, err
    assert (f"has the data window [0, 0, 9, 7] but {'REFERENCE' if cmd[0] == 'metrics' else 'Z'} "
            f"{b} has [3, 2, 12, 9]") in err
    assert not out.exists()
    # the same window in both: compared as before (a different display window is fine)
    _write_windowed(a, ch, CROP[0], [0, 0, 30, 30])
    code, stdout, err = run_cli(cmd[0], a, b, *[x.format(o=out) for x in cmd[1:]])
    assert code == 0, err


@pytest.mark.parametrize("args, needle", [
    (["denoise", "--denoiser", "oidn"], "--denoiser oidn runs OIDN"),
    (["denoise", "--denoiser", "oidn", "--variance"], "--denoiser oidn runs OIDN"),
    (["progressive"], "--denoiser oidn (the default) runs OIDN"),
    (["reconstruct", "--method", "oidn+combine"], "--method oidn+combine runs OIDN"),
])
def test_a_luminance_file_is_refused_by_oidn_naming_file_and_fix(tmp_path, args, needle):
    # before: "the denoiser needs an R,G,B image; got shape (12, 10, 1)", naming neither
    # the file nor what to do
    rng = np.random.default_rng(10)
    p = tmp_path / "y.exr"
    _write_channels(p, {"Y": rng.random((6, 5)), "Variance.Y": rng.random((6, 5)) * 0.01,
                        "SampleCount": np.full((6, 5), 8.0)})
    out = tmp_path / "o.exr"
    code, _, err = run_cli(args[0], p, *args[1:], "--out", out, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert f"{p} is a one-channel (Y) image, but {needle}" in err and "write the luminance" in err
    assert not out.exists()
    # the kernel methods take it
    code, _, err = run_cli(args[0], p, *(["--denoiser", "gaussian"] if args[0] != "reconstruct"
                                         else []), "--out", out, "-q")
    assert code == 0, err


def test_render_refuses_a_reference_lying_elsewhere_in_the_frame(tmp_path):
    # before: a 10x8 reference crop at (3, 2) was scored against the render at the origin
    rng = np.random.default_rng(12)
    ref = tmp_path / "ref.exr"
    for window in (CROP[0], [0, 2, 9, 9]):          # moved in x and y, or in y only
        _write_windowed(ref, {c: rng.random((8, 10)) for c in "RGB"}, window, CROP[1])
        code, _, err = run_cli("render", "toy:constant", "--spp", 2, "--size", "10x8",
                               "--reference", ref, "--out", tmp_path / "r", "-q")
        assert code == 2 and err.count("\n") == 1, err
        assert f"reference {ref} has the data window {window}" in err
        assert not (tmp_path / "r").exists()
    # at the origin, whatever the display window: taken
    _write_windowed(ref, {c: rng.random((8, 10)) for c in "RGB"}, [0, 0, 9, 7], [0, 0, 19, 15])
    code, _, err = run_cli("render", "toy:constant", "--spp", 2, "--size", "10x8",
                           "--reference", ref, "--out", tmp_path / "r", "-q")
    assert code == 0, err


@_KEEPING_COMMANDS
def test_outputs_keep_the_inputs_alpha(tmp_path, args):
    # before: an RGBA render lost its A channel in every output (a compositor then sees an
    # opaque frame); now the input's alpha passes through, as denoisers do
    from statmc.exr import read_channels
    rng = np.random.default_rng(13)
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    alpha = (rng.random((8, 10)) > 0.3).astype(np.float64) * rng.random((8, 10))
    _write_channels(a, dict(_crop_stats(rng), A=alpha))
    _write_channels(b, _crop_stats(rng))                       # Z's alpha, if any, is not used
    out = tmp_path / "out.exr"
    code, _, err = run_cli(*[x.format(a=a, b=b) for x in args], "--out", out, "-q")
    assert code == 0, err
    np.testing.assert_array_equal(read_channels(out, ["A"])["A"], alpha.astype(np.float32))
    # an input without alpha gives an output without
    code, _, err = run_cli(*[x.format(a=b, b=a) for x in args], "--out", out, "-q")
    assert code == 0, err
    assert "A" not in read_channels(out)


@pytest.mark.parametrize("args", [
    ["reconstruct", "{a}"],
    ["denoise", "{a}", "--denoiser", "gaussian"],
    ["denoise", "{a}", "--denoiser", "gaussian", "--variance"],
    ["progressive", "{a}", "--denoiser", "gaussian"],
    ["combine", "{bins}"],
], ids=lambda a: " ".join(a[:1] + a[2:]))
def test_an_input_with_alpha_is_decoded_once(tmp_path, monkeypatch, args):
    # before: _placement read the alpha with read_channels, a second decoding of the whole
    # file (1080p with 16 channels: ~0.4 s beside read_exr's ~0.8 s); header-only reads of
    # the windows and chromaticities are not counted
    import OpenEXR

    from statmc.exr import bin_channels
    rng = np.random.default_rng(15)
    a, bins = tmp_path / "a.exr", tmp_path / "bins.exr"
    alpha = rng.random((8, 10))
    _write_channels(a, dict(_crop_stats(rng), A=alpha))
    ys = rng.random((2, 8, 10, 3))
    _write_channels(bins, dict(R=ys[..., 0].mean(0), G=ys[..., 1].mean(0), B=ys[..., 2].mean(0),
                               A=alpha, **bin_channels(ys, ys * 0.9)))
    real, reads = OpenEXR.File, []

    def counting(*x, **k):
        if isinstance(x[0], str) and not k.get("header_only", False):
            reads.append(x[0])
        return real(*x, **k)

    monkeypatch.setattr(OpenEXR, "File", counting)
    out = tmp_path / "out.exr"
    code, _, err = run_cli(*[x.format(a=a, bins=bins) for x in args], "--out", out, "-q")
    assert code == 0, err
    assert reads == [str(a if args[1] == "{a}" else bins)]
    monkeypatch.undo()
    from statmc.exr import read_channels
    np.testing.assert_array_equal(read_channels(out, ["A"])["A"], alpha.astype(np.float32))


def test_nonfinite_alpha_is_refused_before_writing(tmp_path):
    rng = np.random.default_rng(14)
    a = tmp_path / "a.exr"
    alpha = np.ones((8, 10))
    alpha[1, 2] = np.nan
    _write_channels(a, dict(_crop_stats(rng), A=alpha))
    out = tmp_path / "sub" / "out.exr"
    code, _, err = run_cli("denoise", a, "--denoiser", "gaussian", "--out", out)
    assert code == 2 and err.count("\n") == 1, err
    assert f"{a}: its alpha channel A holds 1 NaN/Inf values" in err
    assert not (tmp_path / "sub").exists()


def test_pbrt_v4_file_needs_no_spp_and_keeps_its_colour_space(tmp_path):
    # before: `statmc reconstruct pbrt.exr` asked for --spp although pbrt-v4 writes
    # samplesPerPixel in the header, and outputs dropped an ACEScg render's chromaticities
    import OpenEXR

    from statmc.exr import exr_info
    rng = np.random.default_rng(15)
    aces = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
    ch = {c: rng.random((8, 10)).astype(np.float16) for c in "RGB"}
    ch.update({f"Variance.{c}": (rng.random((8, 10)) * 0.05).astype(np.float16) for c in "RGB"})
    p = tmp_path / "pbrt.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "samplesPerPixel": 16, "chromaticities": aces}, ch).write(str(p))
    for args in (["reconstruct", p], ["denoise", p, "--denoiser", "gaussian", "--variance"],
                 ["progressive", p, "--denoiser", "gaussian"]):
        out = tmp_path / "o.exr"
        code, _, err = run_cli(*args, "--out", out, "-q")
        assert code == 0, err
        np.testing.assert_allclose(exr_info(out)["chromaticities"], aces, rtol=1e-7)
    code, _, err = run_cli("reconstruct", p, "--spp", 4, "--out", tmp_path / "x.exr")
    assert code == 2 and err.count("\n") == 1, err
    assert "--spp disagrees with the samplesPerPixel header attribute" in err
    assert "omit --spp to use the file's counts" in err


def _blender_file(path, rng, stats=False):
    """A Blender-style multilayer file: the beauty in ViewLayer.Combined.R/G/B/A (with a
    layer's own Variance.* and SampleCount when ``stats``), other passes beside it."""
    ch = {f"ViewLayer.Combined.{c}": rng.random((8, 10)) for c in "RGB"}
    ch["ViewLayer.Combined.A"] = np.ones((8, 10))
    ch["ViewLayer.Depth.Z"] = rng.random((8, 10))
    if stats:
        ch.update({f"ViewLayer.Combined.Variance.{c}": rng.random((8, 10)) * 0.05 for c in "RGB"})
        ch["ViewLayer.Combined.SampleCount"] = np.full((8, 10), 16.0)
    _write_channels(path, ch)
    return ch


def test_layer_option_reads_a_blender_layer(tmp_path):
    # before: no command could read a file whose colour is in a layer (ViewLayer.Combined.R)
    from statmc.exr import read_channels, read_image
    rng = np.random.default_rng(16)
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    ch = _blender_file(a, rng, stats=True)
    _blender_file(b, rng, stats=True)
    code, out, err = run_cli("metrics", a, a, "--layer", "ViewLayer.Combined")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    code, _, err = run_cli("metrics", a, b)                # without --layer: the hint says it
    assert code == 2 and err.count("\n") == 1, err
    assert "or give --layer 'ViewLayer.Combined'." in err and "Python" not in err
    o = tmp_path / "o.exr"
    for args in (["denoise", a, "--denoiser", "gaussian"], ["reconstruct", a],
                 ["progressive", a, "--denoiser", "gaussian"],
                 ["combine", a, b, "--weights", "uniform"], ["combine", a, b]):
        code, _, err = run_cli(*args, "--layer", "ViewLayer.Combined", "--out", o, "-q")
        assert code == 0, (args, err)
        assert set(read_channels(o)) >= {"R", "G", "B", "A"}       # unprefixed, alpha kept
    code, _, err = run_cli("denoise", a, "--denoiser", "gaussian", "--layer", "ViewLayer.Combined",
                           "--out", o, "-q")
    gauss = read_image(o)
    assert gauss.shape == (8, 10, 3)
    assert not np.array_equal(gauss[..., 0], ch["ViewLayer.Combined.R"].astype(np.float32))
    code, _, err = run_cli("reconstruct", a, "--layer", "Nope", "--out", o)
    assert code == 2 and "has no channels in layer 'Nope'" in err and err.count("\n") == 1, err


def test_layer_option_is_refused_for_a_bins_file(tmp_path):
    from statmc.exr import bin_channels, write_exr
    ys = np.random.default_rng(17).random((2, 4, 5, 3))
    p = tmp_path / "bins.exr"
    write_exr(p, ys.mean(0), extra=bin_channels(ys, ys))
    code, _, err = run_cli("combine", p, "--layer", "X", "--out", tmp_path / "o.exr")
    assert code == 2 and "--layer selects a layer of Y and Z" in err and err.count("\n") == 1, err


def test_layer_hint_of_a_command_without_layer_names_no_option(tmp_path):
    # render reads --reference without a --layer option: its hint must not offer one
    p = tmp_path / "ref.exr"
    _blender_file(p, np.random.default_rng(18))
    code, _, err = run_cli("render", "toy:constant", "--spp", 2, "--size", "10x8",
                           "--reference", p, "--out", tmp_path / "r")
    assert code == 2 and err.count("\n") == 1, err
    assert "only inside layer(s) 'ViewLayer.Combined'" in err
    assert "--layer" not in err and "Python" not in err and err.rstrip().endswith("-o OUT.exr`).")


# ------------------------------------------- session 11 review: colour spaces of paired files
ACES_CG = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
REC_709 = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)   # what no attribute means


def _write_in_colour_space(path, channels, chromaticities, windows=None):
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if chromaticities is not None:
        header["chromaticities"] = chromaticities
    if windows is not None:
        for key, (x0, y0, x1, y1) in zip(("dataWindow", "displayWindow"), windows):
            header[key] = (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))
    OpenEXR.File(header, {k: np.ascontiguousarray(v, np.float32)
                          for k, v in channels.items()}).write(str(path))


@pytest.mark.parametrize("cmd", [["metrics"], ["combine", "--weights", "uniform", "--out", "{o}"],
                                 ["combine", "--out", "{o}"]], ids=["metrics", "combine uniform",
                                                                    "combine statistical"])
def test_files_in_different_colour_spaces_are_refused(tmp_path, cmd):
    # before: `statmc metrics` scored an ACEScg image (pbrt-v4 writes its chromaticities) against
    # a Rec. 709 reference (no attribute) pixel by pixel, and `combine` mixed the two into an
    # output labelled ACEScg: R, G, B of different primaries are different colours
    rng = np.random.default_rng(19)
    ch = _crop_stats(rng)
    a, b, out = tmp_path / "a.exr", tmp_path / "b.exr", tmp_path / "o.exr"
    _write_in_colour_space(a, ch, ACES_CG)
    _write_in_colour_space(b, ch, None)
    code, stdout, err = run_cli(cmd[0], a, b, *[x.format(o=out) for x in cmd[1:]])
    assert code == 2 and stdout == "" and err.count("\n") == 1, err
    assert "has the chromaticities (0.713, 0.293, 0.165, 0.83, 0.128, 0.044, 0.3217, 0.3377)" in err
    assert f"{b} has none (Rec. 709/sRGB)" in err and "different colour spaces" in err
    assert not out.exists()
    # the same primaries, or Rec. 709 spelled out against none (also with D65 to 5 digits,
    # as some tools write it): compared as before
    precise = REC_709[:6] + (0.31271, 0.32902)
    for ca, cb in ((ACES_CG, ACES_CG), (REC_709, None), (precise, None)):
        _write_in_colour_space(a, ch, ca)
        _write_in_colour_space(b, ch, cb)
        code, stdout, err = run_cli(cmd[0], a, b, *[x.format(o=out) for x in cmd[1:]])
        assert code == 0, err


def test_render_refuses_a_reference_in_another_colour_space(tmp_path):
    # statmc renders (Mitsuba's RGB variants, the toy scenes) are linear Rec. 709/sRGB
    rng = np.random.default_rng(20)
    ref = tmp_path / "ref.exr"
    _write_in_colour_space(ref, {c: rng.random((8, 10)) for c in "RGB"}, ACES_CG)
    args = ("render", "toy:constant", "--spp", 2, "--size", "10x8", "--reference", ref,
            "--out", tmp_path / "r", "-q")
    code, _, err = run_cli(*args)
    assert code == 2 and err.count("\n") == 1, err
    assert f"reference {ref} has the chromaticities (0.713, " in err and "Rec. 709" in err
    assert not (tmp_path / "r").exists()
    _write_in_colour_space(ref, {c: rng.random((8, 10)) for c in "RGB"}, REC_709)
    code, _, err = run_cli(*args)
    assert code == 0, err


@pytest.mark.parametrize("args", [
    ["reconstruct", "{a}"],
    ["denoise", "{a}", "--denoiser", "gaussian"],
    ["progressive", "{a}", "--denoiser", "gaussian"],
    ["combine", "{a}", "{b}", "--weights", "uniform"],
], ids=lambda a: " ".join(a[:1] + a[2:]))
def test_nonfinite_alpha_is_refused_before_the_work(tmp_path, monkeypatch, args):
    # before: the alpha channel was read when the output was written, so a NaN in A was
    # refused only after the whole reconstruction (minutes at 1080p)
    from statmc import combine, pipeline, progressive
    rng = np.random.default_rng(21)
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    alpha = np.ones((8, 10))
    alpha[3, 4] = np.inf
    _write_channels(a, dict(_crop_stats(rng), A=alpha))
    _write_channels(b, _crop_stats(rng))

    def reached(*a, **k):
        raise AssertionError("the work started before the input's alpha was checked")
    monkeypatch.setattr(pipeline, "reconstruct_stats", reached)
    monkeypatch.setattr(progressive, "bind_denoiser", reached)
    monkeypatch.setattr(combine, "uniform_weights", reached)
    code, _, err = run_cli(*[x.format(a=a, b=b) for x in args], "--out", tmp_path / "o.exr")
    assert code == 2 and err.count("\n") == 1, err
    assert f"{a}: its alpha channel A holds 1 NaN/Inf values" in err


def test_too_few_samples_names_where_the_count_came_from(tmp_path):
    # a 1-spp pbrt-v4 render has no SampleCount channel: before, the refusal said
    # "(SampleCount min 1)" of a file without one
    import OpenEXR
    ch = {c: np.full((4, 5), 0.5, np.float32) for c in "RGB"}
    ch.update({f"Variance.{c}": np.zeros((4, 5), np.float32) for c in "RGB"})
    p = tmp_path / "pbrt1.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "samplesPerPixel": 1}, {k: v.copy() for k, v in ch.items()}).write(str(p))
    code, _, err = run_cli("progressive", p, "--denoiser", "gaussian", "--out", tmp_path / "o.exr")
    assert code == 2 and err.count("\n") == 1, err
    assert "(1 sample per pixel, its samplesPerPixel header attribute)" in err
    code, _, err = run_cli("progressive", p, "--denoiser", "gaussian", "--out", tmp_path / "o.exr",
                           "--spp", 1)
    assert code == 2 and "(1 sample per pixel" in err, err
    q = tmp_path / "counts.exr"
    _write_channels(q, dict(ch, SampleCount=np.full((4, 5), 1.0)))
    code, _, err = run_cli("progressive", q, "--denoiser", "gaussian", "--out", tmp_path / "o.exr")
    assert code == 2 and "(SampleCount min 1)" in err, err


def test_a_bad_layer_is_named_as_the_option(tmp_path):
    # before: "`layer` must be a layer name ..." named the Python keyword, not --layer
    p = tmp_path / "a.exr"
    _blender_file(p, np.random.default_rng(23))
    for bad in ("", "ViewLayer."):
        code, _, err = run_cli("reconstruct", p, "--layer", bad, "--out", tmp_path / "o.exr")
        assert code == 2 and err.count("\n") == 1, err
        assert f"argument --layer: expected a layer name such as 'ViewLayer.Combined' (without " \
               f"the channel's last part); got {bad!r}" in err and "`layer`" not in err


# ------------------------------------- session 12: files written by other tools (per-file options)
def _plain_copy(path, blender_channels, layer="ViewLayer.Combined"):
    """The beauty of a Blender-style file written unprefixed (R, G, B and its statistics)."""
    prefix = layer + "."
    _write_channels(path, {k[len(prefix):]: v for k, v in blender_channels.items()
                           if k.startswith(prefix)})


def test_metrics_scores_a_blender_layer_against_an_unlayered_reference(tmp_path):
    # before: --layer applied to both files, so a Blender render (ViewLayer.Combined.R) could
    # not be scored against an unlayered reference (R, G, B): no --image-layer existed
    rng = np.random.default_rng(30)
    a, ref = tmp_path / "blender.exr", tmp_path / "ref.exr"
    ch = _blender_file(a, rng)
    _plain_copy(ref, ch)
    code, out, err = run_cli("metrics", a, ref, "--image-layer", "ViewLayer.Combined")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    code, out, err = run_cli("metrics", ref, a, "--reference-layer", "ViewLayer.Combined")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    # a per-file option overrides --layer for its file only
    code, out, err = run_cli("metrics", a, ref, "--layer", "ViewLayer.Combined",
                             "--reference-layer", "Nope")
    assert code == 2 and err.count("\n") == 1 and f"{ref}' has no channels in layer 'Nope'" in err
    # --layer alone still means both files
    code, _, err = run_cli("metrics", a, ref, "--layer", "ViewLayer.Combined")
    assert code == 2 and err.count("\n") == 1 and "has no channels in layer" in err, err
    # without a layer, the error names the file's own option beside --layer
    code, _, err = run_cli("metrics", ref, a)
    assert code == 2 and err.count("\n") == 1, err
    assert (f"{a}" in err and "or give --reference-layer 'ViewLayer.Combined' for REFERENCE "
            "alone, or give --layer 'ViewLayer.Combined'." in err and "Python" not in err), err


@pytest.mark.parametrize("weights", ["uniform", "statistical"])
def test_combine_reads_a_layer_of_one_input(tmp_path, weights):
    # before: `combine Y Z --layer L` read L in both files; a Blender Z beside an unlayered Y
    # (or the reverse) could not be combined
    from statmc.exr import read_image
    rng = np.random.default_rng(31)
    y, z = tmp_path / "y.exr", tmp_path / "z.exr"
    _plain_copy(y, _blender_file(tmp_path / "yb.exr", rng, stats=True))
    zc = _blender_file(z, rng, stats=True)
    o = tmp_path / "o.exr"
    code, _, err = run_cli("combine", y, z, "--z-layer", "ViewLayer.Combined", "--weights",
                           weights, "--out", o, "-q")
    assert code == 0, err
    _plain_copy(tmp_path / "zp.exr", zc)
    code, _, err = run_cli("combine", y, tmp_path / "zp.exr", "--weights", weights,
                           "--out", tmp_path / "o2.exr", "-q")
    assert code == 0, err
    assert np.array_equal(read_image(o), read_image(tmp_path / "o2.exr"))
    # the other way round: Y in a layer (its alpha kept), Z plain
    code, _, err = run_cli("combine", z, y, "--y-layer", "ViewLayer.Combined", "--weights",
                           weights, "--out", o, "-q")
    assert code == 0, err
    from statmc.exr import read_channels
    assert "A" in read_channels(o)
    code, _, err = run_cli("combine", y, z, "--weights", weights, "--out", o, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert "or give --z-layer 'ViewLayer.Combined' for Z alone, or give --layer" in err


def test_per_file_layers_are_refused_for_a_bins_file(tmp_path):
    from statmc.exr import bin_channels, write_exr
    ys = np.random.default_rng(32).random((2, 4, 5, 3))
    p = tmp_path / "bins.exr"
    write_exr(p, ys.mean(0), extra=bin_channels(ys, ys))
    # --y-layer / --z-layer name the layer of one file: the message said "of Y and Z"
    for opt, whose in (("--y-layer", "a layer of Y;"), ("--z-layer", "a layer of Z;"),
                       ("--y-part", "a part of Y;"), ("--z-part", "a part of Z;"),
                       ("--part", "a part of Y and Z;")):
        code, _, err = run_cli("combine", p, opt, "X", "--out", tmp_path / "o.exr")
        assert code == 2 and err.count("\n") == 1, err
        assert f"{opt} selects {whose}" in err and f"leave {opt} out" in err, err


def _two_part_file(path, rng, alpha=True):
    """Part 0 'depth' (Z only, a data window one column narrower: not read with part 1),
    part 1 'beauty' with statistics (and alpha)."""
    import OpenEXR
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    ch = _crop_stats(rng)
    if alpha:
        ch["A"] = rng.random((8, 10))
    ch = {k: np.ascontiguousarray(v, np.float32) for k, v in ch.items()}
    narrow = dict(hdr, dataWindow=(np.array([0, 0], np.int32), np.array([8, 7], np.int32)),
                  displayWindow=(np.array([0, 0], np.int32), np.array([9, 7], np.int32)))
    OpenEXR.File([OpenEXR.Part(narrow, {"Z": ch["R"][:, :9].copy()}, name="depth"),
                  OpenEXR.Part(dict(hdr), {k: v.copy() for k, v in ch.items()},
                               name="beauty")]).write(str(path))
    return ch


@pytest.mark.parametrize("args", [
    ["reconstruct", "{a}"],
    ["denoise", "{a}", "--denoiser", "gaussian"],
    ["denoise", "{a}", "--denoiser", "gaussian", "--variance"],
    ["progressive", "{a}", "--denoiser", "gaussian"],
    ["combine", "{a}", "{b}", "--weights", "uniform"],
    ["combine", "{a}", "{b}"],
], ids=lambda a: " ".join(a[:1] + a[2:]))
def test_part_option_reads_another_part(tmp_path, args):
    # before: only part 0 was read; a file whose beauty is part 1 was refused by every command
    from statmc.exr import read_channels, read_image
    rng = np.random.default_rng(33)
    a, b, flat = tmp_path / "a.exr", tmp_path / "b.exr", tmp_path / "flat.exr"
    ch = _two_part_file(a, rng)
    _write_channels(flat, ch)
    _write_channels(b, _crop_stats(rng))
    o, want = tmp_path / "o.exr", tmp_path / "want.exr"
    fill = lambda first: [x.format(a=first, b=b) for x in args]
    for part in ("1", "beauty"):
        code, _, err = run_cli(*fill(a), "--part" if args[0] != "combine" else "--y-part", part,
                               "--out", o, "-q")
        assert code == 0, err
        code, _, err = run_cli(*fill(flat), "--out", want, "-q")
        assert code == 0, err
        assert np.array_equal(read_image(o), read_image(want))
        np.testing.assert_array_equal(read_channels(o, ["A"])["A"], ch["A"])   # the part's alpha
    code, _, err = run_cli(*fill(a), "--out", o, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert "only part 0 ('depth') of this 2-part file is read; part 1 ('beauty')" in err
    assert ("give --y-part INDEX|NAME for Y alone, or --part INDEX|NAME, to read another"
            if args[0] == "combine" else "give --part INDEX|NAME to read another") in err
    assert "part=" not in err
    code, _, err = run_cli(*fill(a), "--part", "7", "--out", o, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert (f"'{a}' has no part 7; it has 2 parts: part 0 ('depth'), part 1 ('beauty') (--part "
            "takes an index from 0 or a part's name)") in err


def test_a_file_split_into_parts_of_one_window_is_read_as_one(tmp_path):
    # before: R, G, B and A in part 0, Variance.* and SampleCount in part 1 of the same data
    # window (Nuke's one part per layer) was refused by every command ("only part 0 ('rgba')
    # ... is read; part 1 ('stats'): [...] — give --part INDEX|NAME to read another"), and
    # no --part could read it
    import OpenEXR

    from statmc.exr import read_channels, read_image
    rng = np.random.default_rng(38)
    ch = {k: np.ascontiguousarray(v, np.float32) for k, v in _crop_stats(rng).items()}
    ch["A"] = rng.random((8, 10)).astype(np.float32)
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    split, flat = tmp_path / "split.exr", tmp_path / "flat.exr"
    OpenEXR.File([OpenEXR.Part(dict(hdr), {c: ch[c].copy() for c in "RGBA"}, name="rgba"),
                  OpenEXR.Part(dict(hdr), {k: v.copy() for k, v in ch.items() if k not in "RGBA"},
                               name="stats")]).write(str(split))
    _write_channels(flat, ch)
    for i, src in enumerate((split, flat)):
        code, _, err = run_cli("reconstruct", src, "--out", tmp_path / f"o{i}.exr", "-q")
        assert code == 0, err
    assert np.array_equal(read_image(tmp_path / "o0.exr"), read_image(tmp_path / "o1.exr"))
    np.testing.assert_array_equal(read_channels(tmp_path / "o0.exr", ["A"])["A"], ch["A"])
    code, out, err = run_cli("info", split)
    assert code == 0, err
    info = json.loads(out)
    assert info["merged_parts"] == [1] and info["layout"]["variance"] and info["parts"] == 2


def test_metrics_combine_and_info_take_a_part_per_file(tmp_path):
    rng = np.random.default_rng(34)
    a, flat = tmp_path / "a.exr", tmp_path / "flat.exr"
    ch = _two_part_file(a, rng)
    _write_channels(flat, ch)
    code, out, err = run_cli("metrics", a, flat, "--image-part", "beauty")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    code, out, err = run_cli("metrics", flat, a, "--reference-part", "1")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    code, out, err = run_cli("metrics", a, a, "--part", "1")
    assert code == 0 and json.loads(out)["mse"] == 0.0, err
    code, _, err = run_cli("metrics", flat, a)
    assert code == 2 and err.count("\n") == 1, err
    assert "give --reference-part INDEX|NAME for REFERENCE alone, or --part" in err
    o = tmp_path / "o.exr"
    code, _, err = run_cli("combine", flat, a, "--z-part", "beauty", "--out", o, "-q")
    assert code == 0, err
    code, out, err = run_cli("info", a, "--part", "beauty")
    assert code == 0, err
    info = json.loads(out)
    assert info["part"] == {"part": 1, "name": "beauty"} and info["layout"]["color"] == "R,G,B"
    assert info["other_parts"] == [{"part": 0, "name": "depth", "channels": ["Z"]}]
    code, _, err = run_cli("info", a, "--part", "2")
    assert code == 2 and "has no part 2" in err and err.count("\n") == 1, err
    code, _, err = run_cli("info", a, "--part", "")
    assert code == 2 and "--part: expected a part's index" in err and err.count("\n") == 1, err


def test_part_options_are_refused_for_a_bins_file(tmp_path):
    from statmc.exr import bin_channels, write_exr
    ys = np.random.default_rng(35).random((2, 4, 5, 3))
    p = tmp_path / "bins.exr"
    write_exr(p, ys.mean(0), extra=bin_channels(ys, ys))
    for opt, whose in (("--part", "Y and Z"), ("--y-part", "Y"), ("--z-part", "Z")):
        code, _, err = run_cli("combine", p, opt, "1", "--out", tmp_path / "o.exr")
        assert code == 2 and err.count("\n") == 1, err
        assert f"{opt} selects a part of {whose};" in err and f"leave {opt} out" in err, err


def test_a_part_hint_of_a_command_without_part_names_no_option(tmp_path):
    p = tmp_path / "ref.exr"
    _two_part_file(p, np.random.default_rng(36))
    code, _, err = run_cli("render", "toy:constant", "--spp", 2, "--size", "10x8",
                           "--reference", p, "--out", tmp_path / "r")
    assert code == 2 and err.count("\n") == 1, err
    assert "only part 0 ('depth')" in err and "part=" not in err and "--part" not in err


@pytest.mark.parametrize("weights", ["uniform", "gaussian", "statistical"])
def test_combine_decodes_a_y_with_alpha_once(tmp_path, monkeypatch, weights):
    # before: combine read Y's colour, then (after Z's checks) decoded the whole of Y again for
    # its alpha in _placement: reads were [Y, Z, Y]; header-only reads are not counted
    import OpenEXR

    from statmc.exr import read_channels
    rng = np.random.default_rng(37)
    y, z = tmp_path / "y.exr", tmp_path / "z.exr"
    alpha = rng.random((8, 10))
    _write_channels(y, dict(_crop_stats(rng), A=alpha))
    _write_channels(z, _crop_stats(rng))
    real, reads = OpenEXR.File, []

    def counting(*x, **k):
        if isinstance(x[0], str) and not k.get("header_only", False):
            reads.append(x[0])
        return real(*x, **k)

    monkeypatch.setattr(OpenEXR, "File", counting)
    out = tmp_path / "out.exr"
    code, _, err = run_cli("combine", y, z, "--weights", weights, "--out", out, "-q")
    assert code == 0, err
    assert reads == [str(y), str(z)]
    monkeypatch.undo()
    np.testing.assert_array_equal(read_channels(out, ["A"])["A"], alpha.astype(np.float32))


def _feature_files(tmp_path, rng):
    """The same render three ways: Blender-style (statistics in ViewLayer.Combined, features
    in its Denoising Albedo/Normal passes, a plain Normal pass beside them), flat with
    statmc's Albedo.*/N.*, and flat without features."""
    st = _crop_stats(rng)
    albedo = {c: rng.random((8, 10)) for c in "RGB"}
    normal = {c: rng.random((8, 10)) * 2 - 1 for c in "XYZ"}
    blender = {f"ViewLayer.Combined.{k}": v for k, v in st.items()}
    blender.update({f"ViewLayer.Denoising Albedo.{c}": v for c, v in albedo.items()})
    blender.update({f"ViewLayer.Denoising Normal.{c}": v for c, v in normal.items()})
    blender.update({f"ViewLayer.Normal.{c}": -v for c, v in normal.items()})
    paths = {k: tmp_path / f"{k}.exr" for k in ("blender", "mitsuba", "flat", "bare")}
    _write_channels(paths["blender"], blender)
    mitsuba = dict(st, **{f"albedo.{c}": v for c, v in albedo.items()},
                   **{f"nn.{c}": v for c, v in normal.items()})
    _write_channels(paths["mitsuba"], mitsuba)
    _write_channels(paths["flat"], dict(st, **{f"Albedo.{c}": v for c, v in albedo.items()},
                                        **{f"N.{c}": v for c, v in normal.items()}))
    _write_channels(paths["bare"], st)
    return paths


@pytest.mark.parametrize("cmd", [["denoise", "--denoiser", "oidn"],
                                 ["denoise", "--denoiser", "oidn", "--variance"],
                                 ["progressive"], ["reconstruct", "--method", "oidn+combine"]],
                         ids=" ".join)
def test_oidn_takes_the_features_of_blender_and_mitsuba_files(tmp_path, cmd):
    # before: Blender's Denoising Albedo/Normal passes and Mitsuba's aov layers were extra
    # channels, so OIDN ran without features: the output was that of the bare file
    from statmc.exr import read_image
    paths = _feature_files(tmp_path, np.random.default_rng(38))
    out = {}
    for name, opts in (("flat", []), ("bare", []),
                       ("blender", ["--layer", "ViewLayer.Combined"]),
                       ("mitsuba", ["--normal-layer", "nn"]),
                       ("blender_plain_normal", ["--layer", "ViewLayer.Combined", "--normal-layer",
                                                 "ViewLayer.Normal"])):
        o = tmp_path / f"o_{name}.exr"
        src = paths[name.split("_")[0]]
        code, _, err = run_cli(cmd[0], src, *cmd[1:], *opts, "--out", o, "-q")
        assert code == 0, (name, err)
        out[name] = read_image(o)
    assert not np.array_equal(out["flat"], out["bare"])          # the features matter here
    assert np.array_equal(out["blender"], out["flat"])
    assert np.array_equal(out["mitsuba"], out["flat"])
    assert not np.array_equal(out["blender_plain_normal"], out["flat"])


def test_feature_layer_options_are_checked_and_refused_where_no_oidn_runs(tmp_path):
    paths = _feature_files(tmp_path, np.random.default_rng(39))
    o = tmp_path / "o.exr"
    for args, why in ((["reconstruct", paths["mitsuba"], "--normal-layer", "nn"],
                       "--normal-layer has no effect on --method gem"),
                      (["denoise", paths["mitsuba"], "--denoiser", "gaussian", "--albedo-layer",
                        "albedo"], "--albedo-layer has no effect with --denoiser gaussian"),
                      (["progressive", paths["mitsuba"], "--denoiser", "gem", "--albedo-layer",
                        "albedo"], "--albedo-layer has no effect with --denoiser gem"),
                      (["denoise", paths["mitsuba"], "--normal-layer", "n"],
                       "has no normal layer 'n' (channels 'n.X', 'n.Y', 'n.Z' or .R, .G, .B); "
                       "layers with X, Y, Z channels: ['nn']")):
        code, _, err = run_cli(*args, "--out", o, "-q")
        assert code == 2 and err.count("\n") == 1 and why in err, (args, err)
        assert not o.exists()
    # two albedo layers beside the colour: refused where OIDN runs, naming the option
    q = tmp_path / "two.exr"
    _write_channels(q, dict(_crop_stats(np.random.default_rng(40)),
                            **{f"{n}.{c}": np.full((8, 10), 0.5) for n in ("albedo", "Denoising Albedo")
                               for c in "RGB"}))
    code, _, err = run_cli("denoise", q, "--out", o, "-q")
    assert code == 2 and err.count("\n") == 1, err
    assert ("has 2 layers statmc would read as the albedo: ['Denoising Albedo', 'albedo']; it "
            "does not choose between them: give --albedo-layer NAME (one of them)") in err
    code, _, err = run_cli("denoise", q, "--albedo-layer", "albedo", "--out", o, "-q")
    assert code == 0, err
    # where no OIDN runs, the file reads as before
    code, _, err = run_cli("denoise", q, "--denoiser", "gaussian", "--out", o, "-q")
    assert code == 0, err
    code, out, err = run_cli("info", paths["blender"])
    assert code == 0 and json.loads(out)["features"] == {
        "albedo": ["ViewLayer.Denoising Albedo"], "normal": ["ViewLayer.Denoising Normal"]}, err


# ---------------------------------------------------------------------------- speed (session 12)
def test_commands_read_and_write_exr_files_on_all_cpus(tmp_path, monkeypatch):
    """A command decodes and encodes its EXR files with OpenEXR's thread pool sized to the
    CPUs it may use (OpenEXR's default is none: at 1920x1080 on 2 CPUs a 15-channel read
    took 2.8 s instead of 1.2 s), and puts the pool's size back when it ends."""
    import OpenEXR

    import statmc.exr as exr
    from statmc.exr import write_exr
    write_exr(tmp_path / "in.exr", np.full((6, 5, 3), 0.5))
    seen, decode = [], exr._decode

    def spy(*a, **k):
        out = decode(*a, **k)
        seen.append(OpenEXR.global_thread_count())
        return out

    monkeypatch.setattr(exr, "_decode", spy)
    before = OpenEXR.global_thread_count()
    code, out, err = run_cli("info", str(tmp_path / "in.exr"))
    assert code == 0, err
    assert seen and set(seen) == {exr._cpu_count()}
    assert OpenEXR.global_thread_count() == before


@pytest.mark.parametrize("command, absent", [
    (["info", "{y}"], ["numba", "PIL", "matplotlib", "torch", "statmc.gem"]),
    (["reconstruct", "{y}", "--out", "{o}", "-q"], ["matplotlib", "torch", "statmc.sure"]),
    (["combine", "{y}", "{z}", "--weights", "statistical", "--out", "{o}", "-q"],
     ["matplotlib", "torch", "statmc.gem"]),
    # OIDN runs no numba kernel (pyoidn itself imports torch when it is installed)
    (["denoise", "{y}", "--denoiser", "oidn", "--out", "{o}", "-q"],
     ["numba", "matplotlib", "statmc.gem", "statmc._filter_kernels"]),
])
def test_commands_do_not_import_what_they_do_not_use(tmp_path, command, absent):
    """A command imports no heavy module it does not use (torch: 2.3 s; matplotlib, numba
    and Pillow for a command that writes no picture or runs no kernel), in a fresh
    interpreter as a user runs it."""
    from statmc.exr import write_exr
    from statmc.stats import PixelStats
    rng = np.random.default_rng(0)
    for name in ("y", "z"):
        write_exr(tmp_path / f"{name}.exr", PixelStats.from_mean_var(
            rng.random((12, 10, 3)), rng.random((12, 10, 3)), np.full((12, 10), 4)))
    argv = [a.format(y=tmp_path / "y.exr", z=tmp_path / "z.exr", o=tmp_path / "o.exr")
            for a in command]
    code = ("import sys; from statmc.cli import main; rc = main(sys.argv[1:]); "
            f"print(sorted(m for m in {absent!r} if m in sys.modules)); sys.exit(rc)")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_every_seed_option_gives_its_default_in_help():
    """`progressive --seed` help gave no default (it is 0, as docs/cli.md says)."""
    for name, sub in _subparsers().items():
        for a in sub._actions:
            if "--seed" in a.option_strings:
                assert "default" in a.help, f"statmc {name} --seed: {a.help!r}"
    code, out, _ = run_cli("progressive", "--help")
    assert code == 0 and "probes (default 0)" in " ".join(out.split())
