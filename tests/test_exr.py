"""EXR files: bit-exact round trips, pbrt-v4 gbuffer files, every bad input, atomic writes."""

import os
import re
import struct
import tempfile

import numpy as np
import OpenEXR
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import statmc.exr as exr
from statmc.errors import FileFormatError, InputError
from statmc.exr import (capturing_openexr_output, exr_info, read_channels, read_exr, read_image,
                        to_display, write_exr, write_png_preview)
from statmc.stats import PixelStats

# Channels of pbrt-v4's GBufferFilm::GetImage (src/pbrt/film.cpp), in its order.
PBRT_V4_GBUFFER = ["R", "G", "B", "Albedo.R", "Albedo.G", "Albedo.B", "P.X", "P.Y", "P.Z",
                   "dzdx", "dzdy", "N.X", "N.Y", "N.Z", "Ns.X", "Ns.Y", "Ns.Z", "u", "v",
                   "Variance.R", "Variance.G", "Variance.B",
                   "RelativeVariance.R", "RelativeVariance.G", "RelativeVariance.B"]


def _write_raw(path, channels, dtype=np.float32):
    """Write channels straight through OpenEXR (as another program would)."""
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {k: np.ascontiguousarray(v, dtype=dtype if v.dtype.kind == "f" else v.dtype)
                  for k, v in channels.items()}).write(str(path))


def _raw_uncompressed_exr(path, channels, h, w, sampling):
    """A minimal uncompressed scanline EXR written byte by byte (OpenEXR's Python API refuses
    to write subsampled channels, which we need to test inconsistent channel sizes)."""
    names = sorted(channels)

    def attr(name, typ, data):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data

    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, *sampling.get(n, (1, 1)))
                      for n in names) + b"\0"
    header = b"".join([
        attr("channels", "chlist", chlist),
        attr("compression", "compression", b"\0"),
        attr("dataWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1)),
        attr("displayWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1)),
        attr("lineOrder", "lineOrder", b"\0"),
        attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0)),
        attr("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    ]) + b"\0"
    head = struct.pack("<ii", 20000630, 2) + header
    chunks = []
    for y in range(h):
        data = b"".join(np.asarray(channels[n], "<f4")[y // sampling.get(n, (1, 1))[1]].tobytes()
                        for n in names if y % sampling.get(n, (1, 1))[1] == 0)
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    offsets, off = [], len(head) + 8 * h
    for c in chunks:
        offsets.append(off)
        off += len(c)
    with open(path, "wb") as f:
        f.write(head + struct.pack(f"<{h}Q", *offsets) + b"".join(chunks))


def _stats(rng, h=5, w=4, c=3, features=True):
    f32 = lambda a: a.astype(np.float32).astype(np.float64)       # float32-representable
    n = rng.integers(2, 300, size=(h, w))
    s = PixelStats.from_mean_var(f32(rng.normal(size=(h, w, c))),
                                 f32(rng.exponential(size=(h, w, c))), n)
    if features:
        s = s.with_features(albedo=rng.random((h, w, 3)), normal=rng.normal(size=(h, w, 3)),
                            depth=rng.random((h, w)) * 10)
    return s


def _assert_same(a: PixelStats, b: PixelStats):
    np.testing.assert_array_equal(a.n, b.n)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.sample_var, b.sample_var)
    np.testing.assert_array_equal(a.m2, b.m2)
    for f in ("albedo", "normal", "depth"):
        fa, fb = getattr(a, f), getattr(b, f)
        assert (fa is None) == (fb is None)
        if fa is not None:
            np.testing.assert_array_equal(fa, fb)


# ---------------------------------------------------------------------------- round trips
def test_round_trip_bit_exact_with_features(tmp_path):
    s = _stats(np.random.default_rng(0))
    p = tmp_path / "s.exr"
    write_exr(p, s)
    t = read_exr(p)
    _assert_same(s, t)
    assert t.meta["sample_count_source"] == "file"
    assert t.meta["has_variance"] and t.meta["depth_channel"] == "Z"
    assert t.meta["nonfinite_replaced"] == 0 and t.meta["extra_channels"] == []


f32s = st.floats(-1e6, 1e6, width=32, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=st.integers(1, 4), w=st.integers(1, 4), c=st.sampled_from([1, 3]),
       data=st.data())
def test_round_trip_bit_exact_hypothesis(h, w, c, data):
    size = h * w * c
    mean = np.array(data.draw(st.lists(f32s, min_size=size, max_size=size))).reshape(h, w, c)
    var = np.abs(np.array(data.draw(st.lists(f32s, min_size=size, max_size=size)))).reshape(h, w, c)
    n = np.array(data.draw(st.lists(st.integers(0, 2 ** 24), min_size=h * w,
                                    max_size=h * w))).reshape(h, w)
    var[n < 2] = 0.0                                 # no spread is kept from < 2 samples
    s = PixelStats.from_mean_var(mean, var, n)
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "h.exr")
        write_exr(p, s)
        t = read_exr(p)
    _assert_same(s, t)
    assert t.shape == (h, w, c)


def test_round_trip_large_counts_use_uint32(tmp_path):
    n = np.array([[2 ** 24 + 1, 3_000_000_000]])
    s = PixelStats.from_mean_var(np.ones((1, 2, 3)), np.full((1, 2, 3), 0.5), n)
    write_exr(tmp_path / "big.exr", s)
    assert exr_info(tmp_path / "big.exr")["channels"]["SampleCount"] == "uint"
    np.testing.assert_array_equal(read_exr(tmp_path / "big.exr").n, n)


def test_plain_image_and_extra_channels(tmp_path):
    rng = np.random.default_rng(2)
    img = rng.random((6, 5, 3)).astype(np.float32)
    scale = rng.integers(0, 4, size=(6, 5)).astype(np.float32)
    write_exr(tmp_path / "img.exr", img, extra={"scale": scale})
    np.testing.assert_array_equal(read_image(tmp_path / "img.exr"), img)
    assert set(read_channels(tmp_path / "img.exr")) == {"R", "G", "B", "scale"}
    np.testing.assert_array_equal(read_channels(tmp_path / "img.exr", ["scale"])["scale"], scale)
    with pytest.raises(FileFormatError, match="no Variance.R, Variance.G, Variance.B"):
        read_exr(tmp_path / "img.exr", spp=4)
    s = read_exr(tmp_path / "img.exr", spp=4, require_variance=False)
    assert not s.meta["has_variance"] and np.all(s.m2 == 0) and np.all(s.n == 4)
    assert s.meta["extra_channels"] == ["scale"]
    grey = rng.random((3, 2)).astype(np.float32)
    write_exr(tmp_path / "grey.exr", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "grey.exr")[..., 0], grey)


# ---------------------------------------------------------------------------- pbrt-v4 files
def _pbrt_file(path, rng, h=6, w=7, dtype=np.float16):
    ch = {name: rng.random((h, w)) for name in PBRT_V4_GBUFFER}
    ch["P.Z"] = 1.0 + 5 * rng.random((h, w))                       # camera-space depth
    _write_raw(path, ch, dtype=dtype)      # pbrt-v4 writes half floats by default (savefp16)
    return {k: v.astype(dtype).astype(np.float64) for k, v in ch.items()}


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_pbrt_v4_gbuffer_file_loads_with_spp(tmp_path, dtype):
    p = tmp_path / "pbrt.exr"
    ch = _pbrt_file(p, np.random.default_rng(3), dtype=dtype)
    s = read_exr(p, spp=16)
    np.testing.assert_array_equal(s.n, 16)
    np.testing.assert_array_equal(s.mean, np.stack([ch[c] for c in "RGB"], -1))
    np.testing.assert_allclose(s.sample_var, np.stack([ch["Variance." + c] for c in "RGB"], -1),
                               rtol=1e-15)
    np.testing.assert_array_equal(s.albedo, np.stack([ch["Albedo." + c] for c in "RGB"], -1))
    np.testing.assert_array_equal(s.normal, np.stack([ch["N." + c] for c in "XYZ"], -1))
    np.testing.assert_array_equal(s.depth, ch["P.Z"].astype(np.float32))
    assert s.meta["depth_channel"] == "P.Z" and s.meta["sample_count_source"] == "spp"
    assert {"dzdx", "u", "v", "P.X", "Ns.Y", "RelativeVariance.G"} <= set(s.meta["extra_channels"])
    # a per-pixel count map works too
    counts = np.arange(42).reshape(6, 7)
    np.testing.assert_array_equal(read_exr(p, spp=counts).n, counts)


def test_pbrt_v4_file_without_spp_says_so(tmp_path):
    p = tmp_path / "pbrt.exr"
    _pbrt_file(p, np.random.default_rng(4))
    with pytest.raises(FileFormatError, match=r"no SampleCount channel and no samplesPerPixel "
                       r"header attribute.*spp=.*'dzdx'") as e:
        read_exr(p)
    assert str(p) in str(e.value)


def test_spp_conflicting_with_file_counts(tmp_path):
    p = tmp_path / "s.exr"
    write_exr(p, _stats(np.random.default_rng(5), features=False))
    with pytest.raises(InputError, match="disagrees with the SampleCount"):
        read_exr(p, spp=1)
    with pytest.raises(InputError, match="a whole number of samples per pixel"):
        read_exr(p, spp=2.5)


# ---------------------------------------------------------------------------- bad files
def test_missing_file_and_directory(tmp_path):
    with pytest.raises(FileFormatError, match="does not exist") as e:
        read_exr(tmp_path / "nope.exr", spp=1)
    assert "nope.exr" in str(e.value)
    with pytest.raises(FileFormatError, match="is a directory"):
        read_image(tmp_path)


@pytest.mark.parametrize("kind", ["random", "empty", "truncated", "truncated_header", "png"])
def test_corrupt_files(tmp_path, kind):
    good = tmp_path / "good.exr"
    write_exr(good, _stats(np.random.default_rng(6), h=32, w=40))
    data = good.read_bytes()
    bad = tmp_path / f"{kind}.exr"
    if kind == "random":
        bad.write_bytes(np.random.default_rng(7).bytes(4000))
    elif kind == "empty":
        bad.write_bytes(b"")
    elif kind == "truncated":
        bad.write_bytes(data[: len(data) * 2 // 3])
    elif kind == "truncated_header":
        bad.write_bytes(data[:60])
    else:
        write_png_preview(tmp_path / "x.png", np.ones((4, 4, 3)))
        bad.write_bytes((tmp_path / "x.png").read_bytes())
    for fn in (read_exr, read_image, exr_info, read_channels):
        with pytest.raises(FileFormatError, match="not a readable OpenEXR file") as e:
            fn(bad)
        assert str(bad) in str(e.value)


def test_missing_colour_lists_channels(tmp_path):
    p = tmp_path / "z.exr"
    _write_raw(p, {"Z": np.ones((3, 3)), "SampleCount": np.ones((3, 3))})
    with pytest.raises(FileFormatError, match=r"no colour channels R, G, B.*\['SampleCount', 'Z'\]"):
        read_exr(p)
    p2 = tmp_path / "rg.exr"
    _write_raw(p2, {"R": np.ones((3, 3)), "G": np.ones((3, 3))})
    with pytest.raises(FileFormatError, match=r"lacks colour channel\(s\) \['B'\]"):
        read_image(p2)


def test_partial_groups(tmp_path):
    base = {c: np.ones((3, 3)) for c in ["R", "G", "B", "SampleCount", "Variance.R", "Variance.G",
                                         "Variance.B"]}
    p = tmp_path / "v.exr"
    _write_raw(p, {k: v for k, v in base.items() if k != "Variance.B"})
    with pytest.raises(FileFormatError, match=r"part of the variance channels: missing \['Variance.B'\]"):
        read_exr(p)
    _write_raw(p, {**base, "N.X": np.ones((3, 3)), "N.Y": np.ones((3, 3))})
    with pytest.raises(FileFormatError, match=r"normal channels: missing \['N.Z'\]"):
        read_exr(p)


def test_inconsistent_channel_sizes(tmp_path):
    p = tmp_path / "sub.exr"
    ch = {c: np.ones((4, 6)) for c in "RGB"}
    ch["Variance.R"] = np.ones((2, 3))
    _raw_uncompressed_exr(p, ch, 4, 6, {"Variance.R": (2, 2)})
    with pytest.raises(FileFormatError, match=r"'Variance.R' has size \(2, 3\).*inconsistent sizes"):
        read_exr(p, spp=1)
    # the hand-made writer itself produces valid files
    ch.pop("Variance.R")
    _raw_uncompressed_exr(p, ch, 4, 6, {})
    np.testing.assert_array_equal(read_image(p), 1.0)


def test_negative_variance_and_bad_counts(tmp_path):
    base = {c: np.ones((3, 3)) for c in ["R", "G", "B", "Variance.R", "Variance.G", "Variance.B"]}
    p = tmp_path / "b.exr"
    neg = dict(base, **{"Variance.G": -np.ones((3, 3))})
    _write_raw(p, neg)
    with pytest.raises(FileFormatError, match="9 negative values"):
        read_exr(p, spp=4)
    sc = np.full((3, 3), 4.0)
    sc[1, 1] = -2
    _write_raw(p, dict(base, SampleCount=sc))
    with pytest.raises(FileFormatError, match="SampleCount holds 1 negative"):
        read_exr(p)
    sc[1, 1] = 2.5
    _write_raw(p, dict(base, SampleCount=sc))
    with pytest.raises(FileFormatError, match="SampleCount holds 1 non-integer values"):
        read_exr(p)


def test_nonfinite_error_and_replace(tmp_path):
    ch = {c: np.ones((4, 4)) for c in ["R", "G", "B", "Variance.R", "Variance.G", "Variance.B"]}
    ch["R"][0, 0] = np.nan
    ch["G"][1, 2] = np.inf
    ch["Variance.B"][3, 3] = -np.inf
    ch["SampleCount"] = np.full((4, 4), 8.0)
    p = tmp_path / "nan.exr"
    _write_raw(p, ch)
    with pytest.raises(FileFormatError, match=r"R\+G\+B: 1 NaN, 1 Inf; Variance: 0 NaN, 1 Inf") as e:
        read_exr(p)
    assert str(p) in str(e.value)
    s = read_exr(p, nonfinite="replace", replace_value=0.5)
    assert s.meta["nonfinite_replaced"] == 3
    assert s.meta["nonfinite_by_group"] == {"R+G+B": {"nan": 1, "inf": 1},
                                            "Variance": {"nan": 0, "inf": 1}}
    assert s.mean[0, 0, 0] == 0.5 and s.mean[1, 2, 1] == 0.5 and s.sample_var[3, 3, 2] == 0.5
    with pytest.raises(FileFormatError, match="non-finite"):
        read_image(p)
    assert np.isfinite(read_image(p, nonfinite="replace")).all()
    info = exr_info(p)
    assert info["nonfinite"] == {"R+G+B": {"nan": 1, "inf": 1}, "Variance": {"nan": 0, "inf": 1}}
    with pytest.raises(InputError, match="`nonfinite` must be 'error' or 'replace'"):
        read_exr(p, nonfinite="ignore")


def test_exr_info(tmp_path):
    s = _stats(np.random.default_rng(8), h=3, w=5)
    p = tmp_path / "i.exr"
    write_exr(p, s, extra={"scale": np.zeros((3, 5))})
    info = exr_info(p)
    assert (info["width"], info["height"]) == (5, 3)
    assert info["data_window"] == [0, 0, 4, 2] and info["parts"] == 1 and info["other_parts"] == []
    assert info["channels"]["R"] == "float" and info["channels"]["SampleCount"] == "float"
    assert info["groups"]["Variance"] == ["Variance.B", "Variance.G", "Variance.R"]
    assert info["layout"] == {"color": "R,G,B", "variance": True, "sample_count": True,
                              "albedo": True, "normal": True, "depth": "Z"}
    assert info["sample_count"] == {"min": s.n.min(), "mean": s.n.mean(), "max": s.n.max(),
                                    "total": s.n.sum()}
    assert info["nonfinite"] == {}
    import json
    json.dumps(info)                                       # JSON-ready as is


def test_exr_info_families(tmp_path):
    """``families=True`` (what ``statmc info`` prints) collapses a stencil and sample bins
    to one entry each and names them in ``layout``; the default lists every channel."""
    s = _stats(np.random.default_rng(9), h=4, w=6)
    rng = np.random.default_rng(1)
    extra = {**exr.spatial_covariance_channels(rng.uniform(0, 1, (4, 6, 3, 3, 3)), s.n),
             **exr.bin_channels(rng.uniform(0, 1, (2, 4, 6, 3)))}
    p = tmp_path / "f.exr"
    write_exr(p, s, extra=extra)
    full, fam = exr_info(p), exr_info(p, families=True)
    assert all(k in full["channels"] for k in extra) and "Bin<b>" not in full["groups"]
    assert fam["channel_count"] == len(full["channels"])
    assert fam["layout"] == {**full["layout"], "covariance": False,
                             "spatial_covariance": "stencil 3x3", "bins": 2,
                             "bins_denoised": False}
    assert fam["groups"]["Bin<b>"] == "2 bins x R,G,B = 6 channels"
    assert fam["groups"]["SpatialCovariance.<dy><dx>"].startswith("stencil 3x3: 9 offsets")
    assert not any(k in fam["channels"] for k in extra)
    assert {k: v for k, v in fam.items() if k not in ("channels", "groups", "layout",
                                                      "channel_count")} == {
        k: v for k, v in full.items() if k not in ("channels", "groups", "layout")}
    # a family stands where its first member's group stood (EXR's sorted channel order)
    assert list(fam["groups"]) == ["Albedo", "R+G+B", "Bin<b>", "N", "SampleCount",
                                   "SpatialCovariance.<dy><dx>", "Variance", "Z"]
    # a stencil missing channels says so (an offset's three channels dropped here)
    part = {k: v for k, v in extra.items() if not k.startswith("SpatialCovariance.+1+1.")}
    write_exr(p, s, extra=part)
    assert (exr_info(p, families=True)["layout"]["spatial_covariance"]
            == "stencil 3x3 (partial: 24 of 27 channels)")


# ---------------------------------------------------------------------------- atomic writes
def test_failed_write_leaves_existing_file_and_no_temp(tmp_path, monkeypatch):
    p = tmp_path / "out.exr"
    write_exr(p, np.ones((4, 4, 3)))
    before = p.read_bytes()

    def broken(tmp, channels, *rest):
        with open(tmp, "wb") as f:
            f.write(b"partial garbage")
        raise OSError("disk full")

    monkeypatch.setattr(exr, "_write_exr_file", broken)
    with pytest.raises(OSError, match="disk full"):
        write_exr(p, np.zeros((4, 4, 3)))
    assert p.read_bytes() == before
    assert os.listdir(tmp_path) == ["out.exr"]
    monkeypatch.undo()
    np.testing.assert_array_equal(read_image(p), 1.0)


def test_failed_write_removes_the_directories_it_made(tmp_path, monkeypatch):
    # before: write_exr (and write_png_preview) created a missing output directory and left
    # it behind, empty, when the write then failed (disk full, an encoder error): the
    # failure was not "nothing written". A directory that existed stays.
    def broken(tmp, channels, *rest):
        raise OSError("disk full")

    monkeypatch.setattr(exr, "_write_exr_file", broken)
    with pytest.raises(OSError, match="disk full"):
        write_exr(tmp_path / "a" / "b" / "out.exr", np.zeros((4, 4, 3)))
    assert os.listdir(tmp_path) == []
    (tmp_path / "kept").mkdir()
    with pytest.raises(OSError, match="disk full"):
        write_exr(tmp_path / "kept" / "new" / "out.exr", np.zeros((4, 4, 3)))
    assert os.listdir(tmp_path) == ["kept"] and os.listdir(tmp_path / "kept") == []
    monkeypatch.undo()
    write_exr(tmp_path / "a" / "b" / "out.exr", np.ones((4, 4, 3)))      # made when it works
    np.testing.assert_array_equal(read_image(tmp_path / "a" / "b" / "out.exr"), 1.0)


def test_a_write_failing_half_way_through_its_directories_removes_those_it_made(tmp_path):
    # os.makedirs made a/ and a/b/, then failed on a name too long for the file system: the
    # cleanup stopped at the deepest directory (never made, so not removable) and left a/b
    with pytest.raises(OSError, match="too long"):
        write_exr(tmp_path / "a" / "b" / ("x" * 300) / "out.exr", np.zeros((4, 4, 3)))
    assert os.listdir(tmp_path) == []


def test_failed_png_write_leaves_existing_file(tmp_path, monkeypatch):
    p = tmp_path / "prev.png"
    write_png_preview(p, np.ones((4, 4, 3)))
    before = p.read_bytes()
    from PIL import Image

    def broken(self, fp, *a, **k):
        raise OSError("no space")

    monkeypatch.setattr(Image.Image, "save", broken)
    with pytest.raises(OSError, match="no space"):
        write_png_preview(p, np.zeros((4, 4, 3)))
    assert p.read_bytes() == before and os.listdir(tmp_path) == ["prev.png"]


def test_invalid_data_raises_before_touching_file(tmp_path):
    p = tmp_path / "out.exr"
    write_exr(p, np.ones((2, 2, 3)))
    before = p.read_bytes()
    with pytest.raises(InputError, match="`data` holds 1 NaN"):
        bad = np.ones((2, 2, 3))
        bad[0, 0, 0] = np.nan
        write_exr(p, bad)
    with pytest.raises(InputError, match="overflows float32"):
        write_exr(p, np.full((2, 2, 3), 1e300))
    with pytest.raises(InputError, match="1 or 3 channels"):
        write_exr(p, np.ones((2, 2, 4)))
    with pytest.raises(InputError, match="must be new non-empty strings"):
        write_exr(p, np.ones((2, 2, 3)), extra={"R": np.ones((2, 2))})
    with pytest.raises(InputError, match=r"image size \(2, 2\)"):
        write_exr(p, np.ones((2, 2, 3)), extra={"s": np.ones((3, 2))})
    assert p.read_bytes() == before and os.listdir(tmp_path) == ["out.exr"]


def test_protect_refuses_inputs(tmp_path):
    inp = tmp_path / "in.exr"
    write_exr(inp, np.ones((2, 2, 3)))
    before = inp.read_bytes()
    os.symlink(inp, tmp_path / "link.exr")
    os.link(inp, tmp_path / "hard.exr")
    sub = tmp_path / "sub"
    sub.mkdir()
    for target in (inp, str(inp), sub / ".." / "in.exr", tmp_path / "link.exr",
                   tmp_path / "hard.exr"):
        with pytest.raises(InputError, match="never overwrites an input"):
            write_exr(target, np.zeros((2, 2, 3)), protect=[str(inp)])
        with pytest.raises(InputError, match="never overwrites an input"):
            write_png_preview(target, np.zeros((2, 2, 3)), protect=inp)   # a single path works
    assert inp.read_bytes() == before
    write_exr(tmp_path / "other.exr", np.zeros((2, 2, 3)), protect=[inp, None])


def test_overwrite_false_and_permissions(tmp_path):
    p = tmp_path / "o.exr"
    write_exr(p, np.ones((2, 2, 3)), overwrite=False)
    with pytest.raises(InputError, match="overwrite=False"):
        write_exr(p, np.zeros((2, 2, 3)), overwrite=False)
    mask = os.umask(0)
    os.umask(mask)
    assert os.stat(p).st_mode & 0o777 == 0o666 & ~mask      # not mkstemp's 0600
    os.chmod(p, 0o640)
    write_exr(p, np.zeros((2, 2, 3)))
    assert os.stat(p).st_mode & 0o777 == 0o640               # replacing keeps the mode
    with pytest.raises(InputError, match="is a directory"):
        write_exr(tmp_path, np.zeros((2, 2, 3)))


# ---------------------------------------------------------------------------- previews
def test_png_preview_values(tmp_path):
    from PIL import Image

    img = np.zeros((2, 3, 3))
    img[0, 0] = 0.5          # sRGB(0.5) = 1.055 * 0.5**(1/2.4) - 0.055 = 0.7354 -> 188
    img[0, 1] = 0.002        # linear segment: 12.92 * 0.002 = 0.02584 -> 7
    img[0, 2] = 4.0          # clamped -> 255
    img[1, 0] = -1.0         # clamped -> 0
    img[1, 1] = 1.0
    p = tmp_path / "p.png"
    write_png_preview(p, img)
    px = np.asarray(Image.open(p))
    assert px.shape == (2, 3, 3) and px.dtype == np.uint8
    np.testing.assert_array_equal(px[..., 0], [[188, 7, 255], [0, 255, 0]])
    write_png_preview(p, img, exposure=1.0)                       # 0.5 * 2 = 1 -> 255
    assert np.asarray(Image.open(p))[0, 0, 0] == 255
    write_png_preview(p, img[..., 0])                              # grey
    assert np.asarray(Image.open(p)).shape == (2, 3)


def test_tonemaps():
    x = np.array([[[1.0, 0.0, 10.0]]])
    r = to_display(x, tonemap="reinhard")
    srgb = lambda v: 1.055 * v ** (1 / 2.4) - 0.055
    np.testing.assert_allclose(r[0, 0], [srgb(0.5), 0.0, srgb(10 / 11)])
    a = to_display(x, tonemap="aces")
    aces1 = (2.51 + 0.03) / (2.43 + 0.59 + 0.14)
    np.testing.assert_allclose(a[0, 0, 0], srgb(aces1))
    assert np.all(np.diff(to_display(np.linspace(0, 50, 100)[None, :], tonemap="aces")) >= 0)
    with pytest.raises(InputError, match="`tonemap`"):
        to_display(x, tonemap="filmic")


@pytest.mark.parametrize("tonemap", ["srgb", "reinhard", "aces"])
@pytest.mark.parametrize("exposure", [1000.0, 1100.0])
def test_to_display_with_values_beyond_float_range(tonemap, exposure):
    """An exposure or a value that takes x past float64 shows white where x > 0 and black
    at 0, quietly: before, 2**1100 raised OverflowError, ACES squared x into inf (a
    RuntimeWarning and NaN) and Reinhard made inf/inf = NaN."""
    import warnings
    x = np.array([[[0.0, 1e-3, 5.0], [1e300, 0.0, 2.0]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = to_display(x, tonemap=tonemap, exposure=exposure)
        big = to_display(np.array([[1e300, 1e151, 0.0]]), tonemap=tonemap)
    white = to_display(np.ones((1, 1)))[0, 0]          # the sRGB curve's 1, to rounding
    np.testing.assert_array_equal(out, np.where(x > 0, white, 0.0))
    np.testing.assert_array_equal(big, [[white, white, 0.0]])
    for bad in ("2", True, [1.0]):
        with pytest.raises(InputError, match="`exposure`"):
            to_display(x, exposure=bad)


# ---------------------------------------------------------------------------- channel covariance
def _stats_with_cov(rng, h=5, w=4):
    """Statistics whose sample variances and covariances are float32-representable."""
    f32 = lambda a: a.astype(np.float32).astype(np.float64)
    n = rng.integers(0, 300, size=(h, w))
    n[0, :2] = [0, 1]
    L = rng.normal(size=(h, w, 3, 3))
    cov = f32(L @ np.swapaxes(L, -1, -2))
    var = np.diagonal(cov, axis1=2, axis2=3).copy()
    var[n < 2] = 0.0
    pairs = cov[..., [0, 0, 1], [1, 2, 2]]
    return PixelStats.from_mean_var(f32(rng.normal(size=(h, w, 3))), var, n, sample_cov=pairs)


def test_covariance_round_trip_bit_exact(tmp_path):
    s = _stats_with_cov(np.random.default_rng(3)).with_features(depth=np.ones((5, 4)))
    p = tmp_path / "cov.exr"
    write_exr(p, s)
    assert all(c in exr_info(p)["channels"] for c in ("Covariance.RG", "Covariance.RB",
                                                       "Covariance.GB"))
    assert exr_info(p)["groups"]["Covariance"] == ["Covariance.GB", "Covariance.RB",
                                                    "Covariance.RG"]
    t = read_exr(p)
    _assert_same(s, t)
    np.testing.assert_array_equal(t.m2_cross, s.m2_cross)
    np.testing.assert_array_equal(t.sample_cov, s.sample_cov)
    assert t.meta["has_covariance"] and t.meta["extra_channels"] == []
    np.testing.assert_array_equal(read_channels(p, "Covariance.RB")["Covariance.RB"],
                                  s.sample_cov[..., 0, 2].astype(np.float32))
    # the toy renderer's covariance survives a round trip to float32 precision
    from statmc.toy import ToyRenderer
    r = ToyRenderer("mixed", width=8, height=8).render_uniform(16, seed=0)
    write_exr(tmp_path / "toy.exr", r)
    np.testing.assert_allclose(read_exr(tmp_path / "toy.exr").sample_cov, r.sample_cov,
                               rtol=1e-6, atol=1e-7 * r.sample_var.max())


def test_read_without_covariance_is_the_same_but_m2_cross(tmp_path):
    """read_exr(covariance=False), what the commands that never read the channel covariance
    use (session 11: 0.3-0.5 s and 143 MiB less at 1080p): the same n, mean, m2, features
    and meta, no m2_cross; the Covariance channels are still checked (NaN/Inf refused or
    replaced and counted as with True).  Fails before: read_exr had no `covariance`."""
    s = _stats_with_cov(np.random.default_rng(3)).with_features(depth=np.ones((5, 4)))
    p = tmp_path / "cov.exr"
    write_exr(p, s)
    t, u = read_exr(p), read_exr(p, covariance=False)
    _assert_same(t, u)
    assert t.m2_cross is not None and u.m2_cross is None and not u.has_cov
    assert u.meta == t.meta and u.meta["has_covariance"] and u.meta["extra_channels"] == []
    with pytest.raises(InputError, match="`covariance` must be True or False; got 'no'"):
        read_exr(p, covariance="no")
    ch = read_channels(p)
    ch["Covariance.RB"][1, 2] = np.nan
    _write_raw(tmp_path / "nan.exr", ch)
    for cov in (True, False):
        with pytest.raises(FileFormatError, match="Covariance: 1 NaN"):
            read_exr(tmp_path / "nan.exr", covariance=cov)
    a, b = (read_exr(tmp_path / "nan.exr", nonfinite="replace", covariance=c) for c in (True, False))
    _assert_same(a, b)
    assert a.meta["nonfinite_by_group"] == b.meta["nonfinite_by_group"] == {
        "Covariance": {"nan": 1, "inf": 0}} and b.m2_cross is None
    del ch["Covariance.GB"]
    _write_raw(tmp_path / "part.exr", ch)
    with pytest.raises(FileFormatError, match="only part of the covariance channels"):
        read_exr(tmp_path / "part.exr", covariance=False)


def test_files_without_covariance_read_as_before(tmp_path):
    s = _stats(np.random.default_rng(4))
    write_exr(tmp_path / "a.exr", s)
    t = read_exr(tmp_path / "a.exr")
    assert t.m2_cross is None and not t.meta["has_covariance"]
    assert "Covariance.RG" not in exr_info(tmp_path / "a.exr")["channels"]
    # a one-channel file never has covariance channels
    y = PixelStats.from_samples(np.random.default_rng(5).normal(size=(4, 2, 3, 1)))
    write_exr(tmp_path / "y.exr", y)
    assert read_exr(tmp_path / "y.exr").m2_cross is None


def test_partial_or_nonfinite_covariance_channels(tmp_path):
    h, w = 2, 3
    base = {"R": np.ones((h, w)), "G": np.ones((h, w)), "B": np.ones((h, w)),
            "Variance.R": np.ones((h, w)), "Variance.G": np.ones((h, w)),
            "Variance.B": np.ones((h, w)), "SampleCount": np.full((h, w), 8.0)}
    _write_raw(tmp_path / "p.exr", {**base, "Covariance.RG": np.zeros((h, w))})
    with pytest.raises(FileFormatError, match="covariance channels"):
        read_exr(tmp_path / "p.exr")
    bad = np.zeros((h, w))
    bad[0, 0] = np.nan
    full = {**base, "Covariance.RG": bad, "Covariance.RB": np.zeros((h, w)),
            "Covariance.GB": np.full((h, w), 0.5)}
    _write_raw(tmp_path / "n.exr", full)
    with pytest.raises(FileFormatError, match="Covariance: 1 NaN"):
        read_exr(tmp_path / "n.exr")
    t = read_exr(tmp_path / "n.exr", nonfinite="replace")
    assert t.meta["nonfinite_replaced"] == 1 and t.sample_cov[0, 0, 0, 1] == 0
    assert t.sample_cov[1, 2, 2, 1] == 0.5
    no_var = {k: v for k, v in full.items() if not k.startswith("Variance.")}
    _write_raw(tmp_path / "v.exr", no_var)
    with pytest.raises(FileFormatError, match="no Variance"):
        read_exr(tmp_path / "v.exr", require_variance=False)


# ------------------------------------------------------------------ spatial covariance
def _stencil_stats(rng, h=5, w=6, m=3, n=8):
    mean = rng.random((h, w, 3))
    cov = rng.normal(size=(h, w, m, m, 3)) * 1e-3
    cov[:, :, m // 2, m // 2] = rng.random((h, w, 3)) * 1e-2
    st = PixelStats.from_mean_var(mean, cov[:, :, m // 2, m // 2] * n, np.full((h, w), n))
    return st, cov


def test_spatial_covariance_round_trip(tmp_path):
    """Stencil → one-sample channels (× n) → file → stencil of the means (÷ SampleCount)."""
    rng = np.random.default_rng(3)
    st, cov = _stencil_stats(rng)
    p = tmp_path / "crn.exr"
    write_exr(p, st, extra=exr.spatial_covariance_channels(cov, st.n))
    names = read_channels(p)
    assert "SpatialCovariance.-1+1.G" in names and "SpatialCovariance.+0+0.B" in names
    got = exr.read_spatial_covariance(p)
    np.testing.assert_allclose(got, cov, rtol=1e-6, atol=1e-12)
    # the centre is the variance the file holds in Variance.*
    np.testing.assert_allclose(got[:, :, 1, 1], read_exr(p).mean_var, rtol=1e-6, atol=1e-12)
    # the plain statistics read as before
    assert read_exr(p).mean.shape == (5, 6, 3)


def test_statistics_and_stencil_from_one_read(tmp_path, monkeypatch):
    """_read_exr_and_stencil (statmc combine's --crn Z, 317 MB at 1080p, ~2 s a read) gives
    read_exr's statistics and read_spatial_covariance's stencil, equal to the two reads, from
    one OpenEXR read of the file; a partial stencil is refused when the stencil is asked for;
    other files are read as before afterwards.  Fails before: no such function (cmd_combine
    read the file twice)."""
    import OpenEXR
    rng = np.random.default_rng(3)
    st, cov = _stencil_stats(rng)
    p, q = tmp_path / "crn.exr", tmp_path / "partial.exr"
    ch = exr.spatial_covariance_channels(cov, st.n)
    write_exr(p, st, extra=ch)
    del ch["SpatialCovariance.+1-1.R"]
    write_exr(q, st, extra=ch)
    want_stats, want_cov = read_exr(p, covariance=False), exr.read_spatial_covariance(p)
    real, reads = OpenEXR.File, []

    def counting(*a, **k):
        reads.append((str(a[0]), k.get("header_only", False)))
        return real(*a, **k)

    monkeypatch.setattr(OpenEXR, "File", counting)
    got, stencil = exr._read_exr_and_stencil(p, covariance=False, spp=99, spp_if_missing=True)
    _assert_same(want_stats, got)
    assert got.meta == want_stats.meta and got.m2_cross is None
    assert stencil().tobytes() == want_cov.tobytes()
    assert reads == [(str(p), False)]
    _, partial = exr._read_exr_and_stencil(q)
    with pytest.raises(FileFormatError, match=r"partial SpatialCovariance.*\+1-1\.R"):
        partial()
    reads.clear()
    assert exr.read_spatial_covariance(p).tobytes() == want_cov.tobytes()
    assert reads == [(str(p), False)]             # nothing kept beyond the call


def test_spatial_covariance_absent_partial_and_bad(tmp_path):
    rng = np.random.default_rng(4)
    st, cov = _stencil_stats(rng)
    p = tmp_path / "plain.exr"
    write_exr(p, st)
    assert exr.read_spatial_covariance(p) is None
    ch = exr.spatial_covariance_channels(cov, st.n)
    del ch["SpatialCovariance.+1-1.R"]
    q = tmp_path / "partial.exr"
    write_exr(q, st, extra=ch)
    with pytest.raises(FileFormatError, match=r"partial SpatialCovariance.*\+1-1\.R"):
        exr.read_spatial_covariance(q)
    with pytest.raises(InputError, match="odd m"):
        exr.spatial_covariance_channels(cov[:, :, :2, :2], st.n)
    with pytest.raises(InputError, match=r"\(H, W\)"):
        exr.spatial_covariance_channels(cov, st.n[:2])
    bad = cov.copy()
    bad[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(InputError, match="cov"):
        exr.spatial_covariance_channels(bad, st.n)


def test_spatial_covariance_explicit_counts(tmp_path):
    """``n=`` overrides SampleCount (same ÷ n convention); a bad ``n`` is an InputError
    naming it (a (2, 2) map was a NumPy broadcast error, n=-1 was accepted)."""
    rng = np.random.default_rng(5)
    st, cov = _stencil_stats(rng)
    p = tmp_path / "crn.exr"
    write_exr(p, st, extra=exr.spatial_covariance_channels(cov, st.n))
    np.testing.assert_allclose(exr.read_spatial_covariance(p, n=16), cov / 2, rtol=1e-6, atol=1e-12)
    for bad in (-1, 2.5, np.ones((2, 2)), "x"):
        with pytest.raises(InputError, match="`n` must"):
            exr.read_spatial_covariance(p, n=bad)


def test_bin_channels_round_trip_and_partial_bins_are_refused(tmp_path):
    """`Bin<b>.<C>` / `Bin<b>.Denoised.<C>` hold the inputs of combine_multi."""
    from statmc.errors import FileFormatError
    from statmc.exr import bin_channels, read_bins, read_channels, write_exr

    rng = np.random.default_rng(0)
    ys = rng.random((3, 5, 7, 3)).astype(np.float32)
    zs = rng.random((3, 5, 7, 3)).astype(np.float32)
    p = tmp_path / "b.exr"
    write_exr(p, ys.mean(axis=0), extra=bin_channels(ys, zs))
    y2, z2 = read_bins(p)
    np.testing.assert_array_equal(y2, ys)
    np.testing.assert_array_equal(z2, zs)
    assert "Bin2.Denoised.G" in read_channels(p)
    q = tmp_path / "y.exr"
    write_exr(q, ys.mean(axis=0), extra=bin_channels(ys))
    y3, z3 = read_bins(q)
    np.testing.assert_array_equal(y3, ys)
    assert z3 is None
    assert read_bins(tmp_path / "b.exr") is not None
    ch = bin_channels(ys, zs)
    del ch["Bin1.R"]
    r = tmp_path / "partial.exr"
    write_exr(r, ys.mean(axis=0), extra=ch)
    with pytest.raises(FileFormatError, match="Bin1.R"):
        read_bins(r)
    plain = tmp_path / "plain.exr"
    write_exr(plain, ys.mean(axis=0))
    assert read_bins(plain) is None
    with pytest.raises(InputError, match="zs"):
        bin_channels(ys, zs[:2])


def test_read_bins_refuses_a_bin_gap_without_listing_every_missing_channel(tmp_path):
    """A corrupt or foreign `Bin<huge>.R` channel made read_bins build the names of every
    bin up to that number (1e7 took 12 s; larger ones run out of memory); the gap is now
    named at once, without that list."""
    from statmc.errors import FileFormatError
    from statmc.exr import bin_channels, read_bins, write_exr

    ys = np.zeros((2, 4, 5, 3), np.float32)
    ch = bin_channels(ys)
    ch["Bin100000.R"] = ys[0, ..., 0]
    p = tmp_path / "gap.exr"
    write_exr(p, ys[0], extra=ch)
    with pytest.raises(FileFormatError, match="up to 100000 but none for bin 2 "):
        read_bins(p)


def test_corrupt_chunk_is_one_error_without_openexr_chatter(tmp_path, capfd):
    """A damaged chunk made OpenEXR print two lines on stderr and a warning on stdout (after
    the command's JSON), and the error said only "file has 0 parts"; now, within
    ``capturing_openexr_output`` (the command line), the error carries OpenEXR's diagnosis
    and nothing else reaches the terminal; outside it (library reads, which leave the
    process's stdout/stderr alone) the error says what "0 parts" meant."""
    y, x = np.mgrid[0:256, 0:64]
    img = np.repeat((np.sin(x / 7.0) * np.cos(y / 9.0))[..., None], 3, axis=2)
    good = tmp_path / "good.exr"
    write_exr(good, img)
    data = bytearray(good.read_bytes())
    for k, name in ((len(data) // 2, "corrupt"), (len(data) - 100, "tail")):
        bad = tmp_path / f"{name}.exr"
        d = bytearray(data)
        d[k:k + 16] = b"\x55" * 16
        bad.write_bytes(bytes(d))
        capfd.readouterr()
        for fn in (read_exr, read_image, exr_info, read_channels):
            with capturing_openexr_output():
                with pytest.raises(FileFormatError, match=r"not a readable OpenEXR.*EXR_ERR") as e:
                    fn(bad)
            assert "0 parts" not in str(e.value) and str(bad) in str(e.value)
        out, err = capfd.readouterr()
        assert out == "" and err == ""
        with pytest.raises(FileFormatError, match="could not decode its image part") as e:
            read_image(bad)
        assert "0 parts" not in str(e.value)
        assert "EXR_ERR" in capfd.readouterr().err        # OpenEXR's own lines, not captured
    assert read_image(good).shape == (256, 64, 3)      # descriptors restored: reads still work
    print("still printing")
    assert capfd.readouterr().out == "still printing\n"


@pytest.mark.parametrize("head, what", [(b"", "empty (0 bytes)"),
                                        (b"\x89PNG\r\n\x1a\n" + b"\0" * 40, "a PNG file"),
                                        (b"\x93NUMPY" + b"\0" * 40, "a NumPy .npy file"),
                                        (b"#?RADIANCE\n" + b"\0" * 40, "a Radiance HDR file"),
                                        (b"hello world" * 5, "another format")])
def test_foreign_file_is_named(tmp_path, head, what):
    """An empty file, or another format renamed .exr, is named as such (it was "Unable to
    open ... for read")."""
    p = tmp_path / "x.exr"
    p.write_bytes(head)
    with pytest.raises(FileFormatError, match="not a readable OpenEXR file") as e:
        read_exr(p)
    assert what in str(e.value)


def test_concurrent_reads_leave_stdout_and_stderr_as_they_were(tmp_path):
    """Regression: every read redirects file descriptors 1 and 2 and ``sys.stdout`` /
    ``sys.stderr`` while OpenEXR runs (to catch its diagnosis of a corrupt file).  Reads
    from several threads restored each other's redirections, so fd 1 and 2 were left
    pointing at a deleted temporary file: everything the process printed afterwards was
    lost (4 threads x 300 reads: 3 of 3 runs).  The capture is now one at a time."""
    import sys
    import threading

    p = tmp_path / "a.exr"
    write_exr(p, np.random.default_rng(0).random((8, 8, 3)))
    before = [os.fstat(fd).st_ino for fd in (1, 2)] + [sys.stdout, sys.stderr]
    errors = []

    def work():
        try:
            for _ in range(150):
                read_image(p)
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(4)]
    with capturing_openexr_output():
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    after = [os.fstat(fd).st_ino for fd in (1, 2)] + [sys.stdout, sys.stderr]
    assert not errors
    assert after == before


def test_spp_if_missing_keeps_a_files_own_counts(tmp_path):
    """``spp_if_missing``: ``spp`` fills in a file without SampleCount and leaves a file's
    own counts alone (without it, a disagreeing ``spp`` is an error)."""
    rng = np.random.default_rng(2)
    mean, var = rng.random((2, 4, 5, 3))
    with_n, without = tmp_path / "n.exr", tmp_path / "no_n.exr"
    write_exr(with_n, PixelStats.from_mean_var(mean, var, np.full((4, 5), 8)))
    write_exr(without, mean, extra={f"Variance.{c}": var[..., k] for k, c in enumerate("RGB")})
    assert np.all(read_exr(with_n, spp=16, spp_if_missing=True).n == 8)
    assert np.all(read_exr(without, spp=16, spp_if_missing=True).n == 16)
    with pytest.raises(InputError, match="disagrees"):
        read_exr(with_n, spp=16)


# ------------------------------------------------- files as other tools write them (session 11)
_LOSSLESS = ("NO", "RLE", "ZIPS", "ZIP", "PIZ") + tuple(    # and the newer ones (docs say so)
    c for c in ("ZSTD", "HTJ2K32", "HTJ2K256") if hasattr(OpenEXR, c + "_COMPRESSION"))
_LOSSY_CODECS = ("PXR24", "B44", "B44A", "DWAA", "DWAB")


def _write_with(path, channels, *, compression="ZIP", tiled=False, windows=None):
    """Write ``channels`` as another program would: any compression, scanline or tiled
    (4x4 tiles), optional ``windows = (data_window, display_window)``."""
    header = {"compression": getattr(OpenEXR, compression + "_COMPRESSION"),
              "type": OpenEXR.tiledimage if tiled else OpenEXR.scanlineimage}
    if tiled:
        td = OpenEXR.TileDescription()
        td.xSize, td.ySize, td.mode = 4, 4, OpenEXR.ONE_LEVEL
        header["tiles"] = td
    if windows is not None:
        for key, (x0, y0, x1, y1) in zip(("dataWindow", "displayWindow"), windows):
            header[key] = (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))
    OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))


@pytest.mark.parametrize("tiled", [False, True], ids=["scanline", "tiled"])
@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.uint32])
@pytest.mark.parametrize("compression", _LOSSLESS + _LOSSY_CODECS)
def test_every_compression_pixel_type_and_layout_reads_what_the_file_holds(tmp_path, compression,
                                                                          dtype, tiled):
    rng = np.random.default_rng(11)
    h, w = 6, 5
    scale = 100 if dtype == np.uint32 else 1
    ch = {c: (rng.random((h, w)) * scale).astype(dtype) for c in ("R", "G", "B")}
    ch.update({f"Variance.{c}": (rng.random((h, w)) * scale).astype(dtype) for c in "RGB"})
    p = tmp_path / "a.exr"
    _write_with(p, dict(ch), compression=compression, tiled=tiled)
    # what OpenEXR itself decodes (lossy codecs change the values, as they should)
    held = {k: v.pixels.astype(np.float64)
            for k, v in OpenEXR.File(str(p), separate_channels=True).channels().items()}
    if compression in _LOSSLESS:
        assert all(np.array_equal(held[k], ch[k].astype(np.float64)) for k in ch)
    s = read_exr(p, spp=4)              # values in [0, 1) (or 0-99): no lossy value below 0
    np.testing.assert_array_equal(s.mean, np.stack([held[c] for c in "RGB"], -1))
    np.testing.assert_array_equal(s.sample_var, np.stack([held["Variance." + c] for c in "RGB"], -1))
    img = read_image(p)
    np.testing.assert_array_equal(img, np.stack([held[c] for c in "RGB"], -1).astype(np.float32))
    assert exr_info(p)["compression"] == compression + "_COMPRESSION"
    assert exr_info(p)["lossy_compression"] == (compression in _LOSSY_CODECS)


def _stats_channels_for(h, w, rng, n=16):
    ch = {c: rng.random((h, w)).astype(np.float32) for c in "RGB"}
    ch.update({f"Variance.{c}": (rng.random((h, w)) * 0.1).astype(np.float32) for c in "RGB"})
    ch["SampleCount"] = np.full((h, w), n, np.float32)
    return ch


@pytest.mark.parametrize("windows", [
    ([3, 2, 12, 9], [0, 0, 19, 15]),       # a crop inside the frame (pbrt-v4 cropwindow/pixelbounds)
    ([-2, -1, 7, 6], [0, 0, 5, 4]),        # overscan: data beyond the frame, negative origin
])
def test_data_and_display_windows_are_read_and_written_back(tmp_path, windows):
    # before session 11 read_exr did not report where the pixels lie and write_exr put every
    # image at the origin with display = data window: a reconstructed crop landed in the
    # frame's corner in a compositor
    rng = np.random.default_rng(3)
    (x0, y0, x1, y1), disp = windows
    ch = _stats_channels_for(y1 - y0 + 1, x1 - x0 + 1, rng)
    p = tmp_path / "crop.exr"
    _write_with(p, dict(ch), windows=windows)
    s = read_exr(p)
    assert s.shape == (y1 - y0 + 1, x1 - x0 + 1, 3)
    np.testing.assert_array_equal(s.mean[..., 0], ch["R"])
    assert (s.meta["data_window"], s.meta["display_window"]) == (list(windows[0]), disp)
    assert exr.exr_windows(p) == (list(windows[0]), disp)
    q = tmp_path / "out.exr"
    write_exr(q, s, data_window=s.meta["data_window"], display_window=s.meta["display_window"])
    assert exr.exr_windows(q) == (list(windows[0]), disp)
    t = read_exr(q)
    np.testing.assert_array_equal(t.mean, s.mean)
    np.testing.assert_array_equal(t.sample_var, s.sample_var)
    # the display window defaults to the data window; without either, the origin
    write_exr(q, s.mean, data_window=windows[0])
    assert exr.exr_windows(q) == (list(windows[0]), list(windows[0]))
    write_exr(q, s.mean)
    h, w = s.shape[:2]
    assert exr.exr_windows(q) == ([0, 0, w - 1, h - 1], [0, 0, w - 1, h - 1])


def test_write_exr_of_read_stats_keeps_their_windows_and_chromaticities(tmp_path):
    # before: write_exr(path, read_exr(crop)) put the image at the origin with display =
    # data window and wrote no chromaticities unless the caller passed them again, so a
    # read -> write round trip of a pbrt-v4 crop (or an ACEScg render) lost both silently
    rng = np.random.default_rng(5)
    windows = ([3, 2, 12, 9], [0, 0, 19, 15])
    ch = _stats_channels_for(8, 10, rng)
    p = tmp_path / "crop.exr"
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
           "chromaticities": ACESCG,
           "dataWindow": (np.array([3, 2], np.int32), np.array([12, 9], np.int32)),
           "displayWindow": (np.array([0, 0], np.int32), np.array([19, 15], np.int32))}
    OpenEXR.File(hdr, {k: v.copy() for k, v in ch.items()}).write(str(p))
    s = read_exr(p)
    q = tmp_path / "out.exr"
    write_exr(q, s)
    t = read_exr(q)
    assert exr.exr_windows(q) == tuple(list(w) for w in windows)
    assert t.meta["chromaticities"] == s.meta["chromaticities"]
    np.testing.assert_allclose(t.meta["chromaticities"], ACESCG, rtol=1e-7)
    np.testing.assert_array_equal(t.mean, s.mean)
    np.testing.assert_array_equal(t.sample_var, s.sample_var)
    # explicit arguments win; a window passed alone places the image as before (display
    # window = data window), the chromaticities still from meta
    write_exr(q, s, data_window=[0, 0, 9, 7])
    assert exr.exr_windows(q) == ([0, 0, 9, 7], [0, 0, 9, 7])
    np.testing.assert_allclose(exr_info(q)["chromaticities"], ACESCG, rtol=1e-7)
    rec709 = (0.64, 0.33, 0.3, 0.6, 0.15, 0.06, 0.3127, 0.329)
    write_exr(q, s, display_window=[0, 0, 29, 29], chromaticities=rec709)
    assert exr.exr_windows(q) == ([0, 0, 9, 7], [0, 0, 29, 29])
    np.testing.assert_allclose(exr_info(q)["chromaticities"], rec709, rtol=1e-6)
    # meta is the state: entries set to None (or absent) mean none / the origin
    plain = PixelStats(s.n, s.mean, s.m2, meta={**s.meta, "chromaticities": None,
                                                 "data_window": None, "display_window": None})
    write_exr(q, plain)
    assert exr_info(q)["chromaticities"] is None
    assert exr.exr_windows(q) == ([0, 0, 9, 7], [0, 0, 9, 7])
    # a plain array carries no meta: the origin, no chromaticities, as before
    write_exr(q, s.mean)
    assert exr.exr_windows(q) == ([0, 0, 9, 7], [0, 0, 9, 7])
    assert exr_info(q)["chromaticities"] is None
    # a meta window that no longer fits the image (statistics cut out of a read file with
    # its meta) is refused by name before anything is written, not silently dropped
    cut = PixelStats(s.n[:4], s.mean[:4], s.m2[:4], meta=dict(s.meta))
    r = tmp_path / "cut.exr"
    with pytest.raises(InputError, match=r"`data.meta\['data_window'\]` \[3, 2, 12, 9\] is 10x8 "
                       r"\(W x H\) but the image is 10x4.*pass data_window="):
        write_exr(r, cut)
    assert not r.exists()
    write_exr(r, cut, data_window=[3, 2, 12, 5], display_window=[0, 0, 19, 15])
    assert exr.exr_windows(r) == ([3, 2, 12, 5], [0, 0, 19, 15])


@pytest.mark.parametrize("spp", [2 ** 63, 10 ** 23, -(2 ** 70)])
def test_an_spp_beyond_int64_is_named_as_too_large(tmp_path, spp):
    # before: "`spp` must be a whole number of samples per pixel; got 1180591620717411303424"
    # for a whole number too large for the int64 counts (NumPy holds it as an object array)
    p = tmp_path / "nocount.exr"
    ch = _stats_channels_for(3, 4, np.random.default_rng(0))
    del ch["SampleCount"]
    _write_with(p, ch)
    with pytest.raises(InputError, match=rf"`spp` must be a whole number of samples per pixel "
                       rf"from 0 to 2\*\*63 - 1, or a \(3, 4\) map of them; got {spp}\."):
        read_exr(p, spp=spp)


@pytest.mark.parametrize("spp", [2 ** 63 - 1, 2 ** 53 + 1, np.int64(2 ** 63 - 1),
                                 np.uint64(2 ** 63 - 1), "map"])
def test_every_spp_the_message_allows_is_read_exactly(tmp_path, spp):
    # before: 2**63 - 1 was refused as "must be ... from 0 to 2**63 - 1; got
    # 9223372036854775807" (spp was held as float64, where it rounds up to 2**63), and
    # 2**53 + 1 was silently read as 2**53
    p = tmp_path / "nocount.exr"
    ch = _stats_channels_for(3, 4, np.random.default_rng(0))
    del ch["SampleCount"]
    _write_with(p, ch)
    want = np.arange(12, dtype=np.int64).reshape(3, 4) + (2 ** 63 - 12) if spp == "map" else spp
    s = read_exr(p, spp=want)
    assert s.n.dtype == np.int64 and s.meta["sample_count_source"] == "spp"
    assert np.all(s.n == np.broadcast_to(np.asarray(want, dtype=np.int64), (3, 4)))
    assert read_exr(p, spp=np.float64(2 ** 62)).n[0, 0] == 2 ** 62     # a whole float, exact


@pytest.mark.parametrize("spp, got", [
    (-1, "got -1"), (2.5, "got 2.5"), (np.nan, "got nan"), (1 + 2j, r"got \(1\+2j\)"),
    (True, "got True"), ("8", "got '8'"), (np.full((3, 4), -2), r"got a map with 12 other "
                                                               r"values \(e.g. -2\)"),
    (np.full((3, 4), 2.0 ** 63), "got a map with 12 other values"),
    (np.zeros((4, 3)), r"got shape \(4, 3\)"), (np.ones((3, 4), complex), "got an array of dtype complex128"),
    (np.full((3, 4), np.timedelta64(4, "s")), "got an array of dtype timedelta64"),
])
def test_a_bad_spp_is_refused_in_one_wording(tmp_path, spp, got):
    # before: two wordings ("must hold whole numbers >= 0", "must be a whole number of samples
    # per pixel from 0 to 2**63 - 1", "must be a number or an (3, 4) count map") for one rule
    p = tmp_path / "nocount.exr"
    ch = _stats_channels_for(3, 4, np.random.default_rng(0))
    del ch["SampleCount"]
    _write_with(p, ch)
    with pytest.raises(InputError, match=r"^`spp` must be a whole number of samples per pixel "
                       r"from 0 to 2\*\*63 - 1, or a \(3, 4\) map of them; " + got):
        read_exr(p, spp=spp)


@pytest.mark.parametrize("kw, needle", [
    ({"data_window": [0, 0, 3, 3]}, r"`data_window` \[0, 0, 3, 3\] is 4x4 \(W x H\) but the image is 5x6"),
    ({"data_window": [0, 0, 4]}, r"`data_window` must be \[x0, y0, x1, y1\]"),
    ({"data_window": [0.5, 0, 4.5, 5]}, r"`data_window` must be \[x0, y0, x1, y1\], four whole"),
    ({"data_window": "abcd"}, r"`data_window` must be"),
    ({"display_window": [4, 0, 0, 5]}, r"`display_window` must have x1 >= x0"),
    ({"display_window": [0, 5, 4, 0]}, r"`display_window` must have x1 >= x0 and y1 >= y0"),
    ({"display_window": [0, 0, 2 ** 31, 5]}, r"within \+-2\*\*30"),
])
def test_write_exr_refuses_bad_windows_before_writing(tmp_path, kw, needle):
    p = tmp_path / "a.exr"
    with pytest.raises(InputError, match=needle):
        write_exr(p, np.zeros((6, 5, 3)), **kw)
    assert not p.exists() and os.listdir(tmp_path) == []


def _part_header(window=None, view=None):
    """A Part's header (a Part keeps, and names, its header): ``window`` ``[x0, y0, x1, y1]``
    in a 10x10 display window (the parts of a file share one), ``view`` its view."""
    h = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if window is not None:
        h["dataWindow"] = (np.array(window[:2], np.int32), np.array(window[2:], np.int32))
        h["displayWindow"] = (np.array([0, 0], np.int32), np.array([9, 9], np.int32))
    if view is not None:
        h["view"] = view
    return h


def test_channels_split_across_parts_of_one_window_are_read_together(tmp_path):
    # before: a file with R, G, B in part 0 and Variance.* (and SampleCount) in parts 1, 2 of
    # the same data window, as Nuke writes one part per layer, was refused: "has no
    # Variance.R, ... (only part 0 ('beauty') of this 3-part file is read; part 1
    # ('variance'): [...]) — pass part=INDEX or part='NAME' to read another", and no part
    # held both colour and variance, so no part= could read it
    rng = np.random.default_rng(4)
    ch = _stats_channels_for(4, 3, rng)
    flat = tmp_path / "flat.exr"
    _write_with(flat, ch)
    p = tmp_path / "parts.exr"
    OpenEXR.File([OpenEXR.Part(_part_header(), {c: ch[c] for c in "RGB"}, name="beauty"),
                  OpenEXR.Part(_part_header(), {f"Variance.{c}": ch[f"Variance.{c}"]
                                                for c in "RGB"}, name="variance"),
                  OpenEXR.Part(_part_header(), {"SampleCount": ch["SampleCount"]},
                               name="count")]).write(str(p))
    for part, index, merged in ((0, 0, [1, 2]), ("variance", 1, [0, 2]), (2, 2, [0, 1])):
        s = read_exr(p, part=part)
        _assert_same(read_exr(flat), s)
        assert s.meta["part"] == index and s.meta["merged_parts"] == merged
        assert s.meta["extra_channels"] == []
    assert read_exr(flat).meta["merged_parts"] == []
    info = exr_info(p, families=True)
    assert info["parts"] == 3 and info["merged_parts"] == [1, 2]
    assert info["layout"]["variance"] and info["layout"]["sample_count"]
    assert info["channels"] == exr_info(flat)["channels"]
    assert sorted(exr._header_summary(p)["channels"]) == sorted(ch)      # header only, too
    np.testing.assert_array_equal(read_channels(p, ["Variance.G"])["Variance.G"],
                                  ch["Variance.G"])


@pytest.mark.parametrize("second, why", [
    ({"window": [1, 1, 3, 4]}, r"data window \[1, 1, 3, 4\], not \[0, 0, 2, 3\]"),
    ({"view": "right"}, r"view 'right', not 'left'"),
    ({"also_rgb": True}, r"channel names also in another part: another image"),
])
def test_parts_that_are_not_one_image_are_not_read_together(tmp_path, second, why):
    # another data window, another view of a stereo file, or a second R, G, B (another
    # image): the variance of part 1 is not paired with part 0's colour, and the error says why
    rng = np.random.default_rng(5)
    ch = _stats_channels_for(4, 3, rng)
    var = {f"Variance.{c}": ch[f"Variance.{c}"] for c in "RGB"}
    if second.get("also_rgb"):
        var.update({c: ch[c] for c in "RGB"})
    view = "left" if "view" in second else None
    p = tmp_path / "parts.exr"
    OpenEXR.File([OpenEXR.Part(_part_header([0, 0, 2, 3], view), {c: ch[c] for c in "RGB"},
                               name="beauty"),
                  OpenEXR.Part(_part_header(second.get("window", [0, 0, 2, 3]),
                                            second.get("view")), var,
                               name="variance")]).write(str(p))
    with pytest.raises(FileFormatError, match=r"has no Variance.R, Variance.G, Variance.B "
                       r"channels.*\(only part 0 \('beauty'\) of this 2-part file is read; part 1 "
                       r"\('variance'\): \[.*'Variance.R'\], not read with it \(" + why + r"\)\) — "
                       r"pass part=INDEX or part='NAME' to read another"):
        read_exr(p, spp=4)
    np.testing.assert_array_equal(read_image(p)[..., 1], ch["G"])     # part 0's colour
    assert exr_info(p)["merged_parts"] == [] and exr_info(p)["parts"] == 2


def test_a_window_holding_two_images_merges_no_part(tmp_path):
    # parts 0 and 1 are two renders of one window (each its own R, G, B) and part 2 holds
    # Variance.* of one of them: before, part 2 was read with part 0 whichever render it
    # belonged to (here part 1's); now no part of the window is read with another
    rng = np.random.default_rng(6)
    a, b = _stats_channels_for(4, 3, rng), _stats_channels_for(4, 3, rng)
    p = tmp_path / "two.exr"
    w = [0, 0, 2, 3]
    OpenEXR.File([OpenEXR.Part(_part_header(w), {c: a[c] for c in "RGB"}, name="noisy"),
                  OpenEXR.Part(_part_header(w), {c: b[c] for c in "RGB"}, name="reference"),
                  OpenEXR.Part(_part_header(w), {f"Variance.{c}": b[f"Variance.{c}"] for c in "RGB"},
                               name="reference_var")]).write(str(p))
    for part in (0, 1, 2):
        assert exr_info(p, part=part)["merged_parts"] == []
    with pytest.raises(FileFormatError, match=r"part 2 \('reference_var'\): \[.*\], not read "
                       r"with it \(part 1 of this window repeats channel names, so it holds more "
                       r"than one image"):
        read_exr(p, spp=4)
    np.testing.assert_array_equal(read_image(p, part=1)[..., 0], b["R"])


def test_multipart_file_errors_name_what_the_other_parts_hold(tmp_path):
    # before: "has no Variance.R, ... Channels present: ['B', 'G', 'R']" although part 1 of
    # the file held them; the error did not say that only part 0 is read
    rng = np.random.default_rng(4)
    ch = _stats_channels_for(4, 3, rng)
    hdr = _part_header
    q = tmp_path / "second.exr"
    OpenEXR.File([OpenEXR.Part(hdr([0, 0, 2, 3]), {"Z": ch["R"]}, name="depth"),
                  OpenEXR.Part(hdr([1, 0, 3, 3]), {c: ch[c] for c in "RGB"},
                               name="beauty")]).write(str(q))
    with pytest.raises(FileFormatError, match=r"no colour channels.*\['Z'\] \(only part 0 "
                       r"\('depth'\).*part 1 \('beauty'\): \['B', 'G', 'R'\]"):
        read_image(q)
    with pytest.raises(FileFormatError, match=r"lacks channel\(s\) \['B'\].*part 1 \('beauty'\)"):
        read_channels(q, ["B"])
    assert exr_info(q, families=True)["other_parts"] == [
        {"part": 1, "name": "beauty", "channels": ["B", "G", "R"]}]
    r = tmp_path / "three.exr"                        # every other part is listed
    OpenEXR.File([OpenEXR.Part(hdr([0, 0, 2, 3]), {"Z": ch["R"]}, name="depth"),
                  OpenEXR.Part(hdr([1, 0, 3, 3]), {c: ch[c] for c in "RGB"}, name="beauty"),
                  OpenEXR.Part(hdr([0, 0, 2, 3]), {"R": ch["G"]}, name="red")]).write(str(r))
    with pytest.raises(FileFormatError, match=r"only part 0 \('depth'\), with part 2 \('red'\), "
                       r"of this 3-part file is read; part 1 \('beauty'\): \['B', 'G', 'R'\], "
                       r"not read with it \(data window \[1, 0, 3, 3\], not \[0, 0, 2, 3\]\)\)"):
        read_image(r)


@pytest.mark.parametrize("names, needle", [
    (["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B",
      "ViewLayer.Combined.A", "ViewLayer.Depth.Z"],
     r"R, G, B are only inside layer\(s\) 'ViewLayer.Combined' .*--ch "
     r"R=ViewLayer.Combined.R,G=ViewLayer.Combined.G,B=ViewLayer.Combined.B"),
    (["diffuse.R", "diffuse.G", "diffuse.B", "Variance.R", "Variance.G", "Variance.B"],
     r"only inside layer\(s\) 'diffuse' \(e.g. 'diffuse.R'\)"),
    (["r", "g", "b"], r"lowercase r, g, b: EXR channel names are case-sensitive"),
])
def test_missing_colour_names_the_layer_or_lowercase_channels_instead(tmp_path, names, needle):
    # before: only "has no colour channels R, G, B (or Y); channels present: [...]"
    p = tmp_path / "a.exr"
    _write_raw(p, {n: np.ones((2, 3)) for n in names})
    for read in (read_image, lambda q: read_exr(q, spp=2)):
        with pytest.raises(FileFormatError, match=needle):
            read(p)


def test_no_layer_hint_for_statmc_feature_layers(tmp_path):
    p = tmp_path / "a.exr"
    _write_raw(p, {n: np.ones((2, 3)) for n in ("Albedo.R", "Albedo.G", "Albedo.B",
                                                "Variance.R", "Variance.G", "Variance.B")})
    with pytest.raises(FileFormatError) as e:
        read_image(p)
    assert str(e.value).endswith("'Variance.R'].")


@pytest.mark.parametrize("compression", ["B44", "DWAA"])
def test_negative_variance_from_a_lossy_codec_names_the_compression(tmp_path, compression):
    # before: "Variance channels hold 75 negative values (min -7.8e-06); a variance is >= 0."
    # with no word on why (DWAA is a common default of compositing tools)
    rng = np.random.default_rng(3)
    h = w = 32
    ch = {c: rng.random((h, w)).astype(np.float16) for c in "RGB"}
    ch.update({f"Variance.{c}": (rng.exponential(1, (h, w)) ** 3 * 1e-3).astype(np.float16)
               for c in "RGB"})
    p = tmp_path / "lossy.exr"
    _write_with(p, ch, compression=compression)
    with pytest.raises(FileFormatError, match=rf"negative values .*The file is {compression}-"
                       r"compressed, a lossy codec.*lossless compression \(ZIP, PIZ"):
        read_exr(p, spp=4)
    q = tmp_path / "lossless.exr"                     # a lossless file says nothing of codecs
    ch["Variance.R"][0, 0] = -1
    _write_with(q, ch, compression="ZIP")
    with pytest.raises(FileFormatError, match=r"a variance is >= 0\.$"):
        read_exr(q, spp=4)


@pytest.mark.parametrize("name", ["out.png", "out.JPG", "out.hdr", "out.tiff", "out.npy"])
def test_write_exr_refuses_another_formats_extension(tmp_path, name):
    # before: write_exr("out.png", img) wrote an OpenEXR file named .png (no PNG viewer opens
    # it), and write_png_preview("x.exr", img) a PNG named .exr
    with pytest.raises(InputError, match=rf"ends in {os.path.splitext(name)[1].lower()}, but this "
                       r"writes EXR; name it \.exr \(write_png_preview"):
        write_exr(tmp_path / name, np.ones((2, 2, 3)))
    assert os.listdir(tmp_path) == []
    write_exr(tmp_path / "noext", np.ones((2, 2, 3)))            # no extension: as asked
    assert read_image(tmp_path / "noext").shape == (2, 2, 3)


@pytest.mark.parametrize("name", ["x.exr", "x.jpeg", "x.HDR"])
def test_write_png_preview_refuses_another_formats_extension(tmp_path, name):
    with pytest.raises(InputError, match=r"but this writes PNG; name it \.png \(write_exr"):
        write_png_preview(tmp_path / name, np.ones((2, 2, 3)))
    assert os.listdir(tmp_path) == []


def test_inf_in_half_channels_is_named_as_an_overflow(tmp_path):
    # pbrt-v4's default savefp16 clamps R, G, B at 65504 but not Variance: a firefly's
    # variance above 65504 becomes half Inf.  Before, the error only counted it.
    ch = {n: np.full((3, 4), 0.5, np.float16) for n in PBRT_V4_GBUFFER}
    ch["Variance.G"][1, 1] = np.float16(np.inf)           # what float -> half makes of 1e5
    p = tmp_path / "pbrt.exr"
    _write_raw(p, ch, dtype=np.float16)
    with pytest.raises(FileFormatError, match=r"Variance: 0 NaN, 1 Inf\) \(the Inf of Variance is "
                       r"likely an overflow: half floats end at 65504.*savefp16\\?\" false\); pass"):
        read_exr(p, spp=4)
    # float channels, or a NaN: no such guess
    q = tmp_path / "float.exr"
    _write_raw(q, {k: v.astype(np.float32) for k, v in ch.items()})
    with pytest.raises(FileFormatError) as e:
        read_exr(q, spp=4)
    assert "overflow" not in str(e.value)
    ch["Variance.G"][1, 1] = np.float16(np.nan)
    _write_raw(p, ch, dtype=np.float16)
    with pytest.raises(FileFormatError) as e:
        read_exr(p, spp=4)
    assert "overflow" not in str(e.value)
    ch["Variance.G"][1, 1] = 0
    ch["R"][0, 0] = np.float16(np.inf)                     # another tool's unclamped half colour
    _write_raw(p, ch, dtype=np.float16)
    with pytest.raises(FileFormatError, match=r"the Inf of R\+G\+B is likely an overflow"):
        read_image(p)


def test_layer_hint_puts_blenders_combined_first_and_quotes_spaces(tmp_path):
    # ViewLayer.AO sorts before ViewLayer.Combined: the beauty comes first all the same
    names = [f"ViewLayer.{layer}.{c}" for layer in ("Noisy Image", "DiffCol", "Combined", "AO",
                                                    "Denoising Albedo") for c in "RGB"]
    p = tmp_path / "blender.exr"
    _write_raw(p, {n: np.ones((2, 3)) for n in names})
    with pytest.raises(FileFormatError, match=r"layer\(s\) 'ViewLayer.Combined', 'ViewLayer.AO', "
                       r"'ViewLayer.Denoising Albedo', 'ViewLayer.DiffCol', ... \(e.g. "
                       r"'ViewLayer.Combined.R'\)") as e:
        read_image(p)
    assert "--ch R=ViewLayer.Combined.R,G=ViewLayer.Combined.G,B=ViewLayer.Combined.B -o" in str(e.value)
    q = tmp_path / "noisy.exr"
    _write_raw(q, {n: np.ones((2, 3)) for n in names if "Noisy" in n})
    with pytest.raises(FileFormatError, match=r"--ch 'R=ViewLayer.Noisy Image.R,G=ViewLayer.Noisy "
                       r"Image.G,B=ViewLayer.Noisy Image.B' -o OUT.exr"):
        read_image(q)


def _pbrt_file_with_header(path, *, spp=64, chromaticities=None, dtype=np.float16):
    """A pbrt-v4 gbuffer file as pbrt-v4 writes it: its channels, and the header attribute
    samplesPerPixel (Image::WriteEXR, from the integrator's metadata), chromaticities for a
    colour space other than sRGB."""
    rng = np.random.default_rng(21)
    ch = {n: rng.random((4, 5)).astype(dtype) for n in PBRT_V4_GBUFFER}
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
           "renderTimeSeconds": 1.5}
    if spp is not None:
        hdr["samplesPerPixel"] = spp
    if chromaticities is not None:
        hdr["chromaticities"] = chromaticities
    OpenEXR.File(hdr, {k: v.copy() for k, v in ch.items()}).write(str(path))
    return ch


ACESCG = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)


def test_pbrt_v4_samples_per_pixel_attribute_gives_the_counts(tmp_path):
    # before: a pbrt-v4 file needed spp= although pbrt-v4 writes its count in the header
    p = tmp_path / "pbrt.exr"
    ch = _pbrt_file_with_header(p, spp=64)
    s = read_exr(p)
    assert (s.n == 64).all() and s.meta["sample_count_source"] == "header"
    np.testing.assert_array_equal(s.sample_var[..., 1], ch["Variance.G"].astype(np.float64))
    np.testing.assert_array_equal(s.mean_var[..., 1], ch["Variance.G"].astype(np.float64) / 64)
    assert exr_info(p)["samples_per_pixel"] == 64
    assert (read_exr(p, spp=64).n == 64).all()                   # agreeing spp: fine
    with pytest.raises(InputError, match=r"`spp` disagrees with the samplesPerPixel header "
                       r"attribute of .*, 64 \(the count pbrt-v4 rendered\)"):
        read_exr(p, spp=16)
    assert (read_exr(p, spp=16, spp_if_missing=True).n == 64).all()   # the file's own count
    q = tmp_path / "nospp.exr"
    _pbrt_file_with_header(q, spp=None)
    assert exr_info(q)["samples_per_pixel"] is None
    with pytest.raises(FileFormatError, match="no SampleCount channel and no samplesPerPixel "
                       "header attribute"):
        read_exr(q)
    assert (read_exr(q, spp=8).n == 8).all()


def test_chromaticities_are_read_and_written(tmp_path):
    # before: the attribute was neither reported nor writable, so an ACEScg render's
    # reconstruction was shown with Rec. 709 primaries
    p = tmp_path / "aces.exr"
    _pbrt_file_with_header(p, chromaticities=ACESCG)
    s = read_exr(p)
    np.testing.assert_allclose(s.meta["chromaticities"], ACESCG, rtol=1e-7)
    np.testing.assert_allclose(exr_info(p)["chromaticities"], ACESCG, rtol=1e-7)
    q = tmp_path / "out.exr"
    write_exr(q, s.mean, chromaticities=s.meta["chromaticities"])
    assert read_exr(q, spp=1, require_variance=False).meta["chromaticities"] == s.meta["chromaticities"]
    write_exr(q, s.mean)
    assert exr_info(q)["chromaticities"] is None
    for bad in ((0.1,) * 7, (0.1,) * 7 + (np.nan,), "abc"):
        with pytest.raises(InputError, match="`chromaticities` must be 8 finite numbers"):
            write_exr(tmp_path / "bad.exr", s.mean, chromaticities=bad)
    assert not (tmp_path / "bad.exr").exists()


def test_an_uncreatable_output_names_the_target_not_the_temporary_file(tmp_path, monkeypatch):
    # before: "[Errno 17] File exists: '.../file.txt'" for a path under a file, and
    # "[Errno 2] No such file or directory: '/proc/.statmc-j25ujoo4.exr'" (the hidden
    # temporary file) where the directory takes no new files
    import errno
    import tempfile as tf
    f = tmp_path / "file.txt"
    f.write_text("x")
    with pytest.raises(NotADirectoryError, match=rf"cannot write '{f}/sub/a.exr': '{f}' is not "
                       "a directory"):
        write_exr(f / "sub" / "a.exr", np.ones((2, 2, 3)))
    ro = tmp_path / "ro"
    ro.mkdir()
    real = tf.mkstemp

    def refuse(*a, dir=None, **k):
        if dir == str(ro):
            raise PermissionError(errno.EACCES, "Permission denied", os.path.join(dir, ".statmc-x"))
        return real(*a, dir=dir, **k)

    monkeypatch.setattr(tf, "mkstemp", refuse)
    for write in (lambda p: write_exr(p, np.ones((2, 2, 3))),
                  lambda p: write_png_preview(p.with_suffix(".png"), np.ones((2, 2, 3)))):
        with pytest.raises(PermissionError, match=rf"cannot write '{ro}/a\.(exr|png)': cannot "
                           rf"create a file in '{ro}' \(Permission denied\)") as e:
            write(ro / "a.exr")
        assert ".statmc-" not in str(e.value)
    assert os.listdir(ro) == []


def test_layer_reads_a_layers_channels_without_their_prefix(tmp_path):
    rng = np.random.default_rng(22)
    ch = {f"ViewLayer.Combined.{c}": rng.random((3, 4)) for c in "RGBA"}
    ch.update({f"ViewLayer.Combined.Variance.{c}": rng.random((3, 4)) * 0.1 for c in "RGB"})
    ch["ViewLayer.Combined.SampleCount"] = np.full((3, 4), 8.0)
    ch.update({f"ViewLayer.Denoising Albedo.{c}": rng.random((3, 4)) for c in "RGB"})
    ch["R"] = np.zeros((3, 4))                  # outside the layer: not read with layer=
    p = tmp_path / "blender.exr"
    _write_raw(p, ch)
    f32 = {k: v.astype(np.float32).astype(np.float64) for k, v in ch.items()}
    s = read_exr(p, layer="ViewLayer.Combined")
    np.testing.assert_array_equal(s.mean[..., 2], f32["ViewLayer.Combined.B"])
    np.testing.assert_array_equal(s.sample_var[..., 0], f32["ViewLayer.Combined.Variance.R"])
    assert (s.n == 8).all() and s.meta["layer"] == "ViewLayer.Combined"
    assert s.meta["extra_channels"] == ["A"]
    img = read_image(p, layer="ViewLayer.Denoising Albedo")
    np.testing.assert_array_equal(img[..., 1], f32["ViewLayer.Denoising Albedo.G"].astype(np.float32))
    with pytest.raises(FileFormatError, match=r"no channels in layer 'Nope'.*its layers: "
                       r"\['ViewLayer.Combined', 'ViewLayer.Combined.Variance', "
                       r"'ViewLayer.Denoising Albedo'\]"):
        read_image(p, layer="Nope")
    for bad in ("", "ViewLayer.", 3):
        with pytest.raises(InputError, match="`layer` must be a layer name"):
            read_image(p, layer=bad)
    q = tmp_path / "only_layer.exr"
    _write_raw(q, {k: v for k, v in ch.items() if k.startswith("ViewLayer.Combined.")})
    with pytest.raises(FileFormatError, match=r"read_image\(path, layer='ViewLayer.Combined'\)"):
        read_image(q)


def test_layer_hint_leaves_out_a_layers_own_variance_and_albedo(tmp_path):
    # before: a layer with its statistics was offered twice, "layer(s) 'ViewLayer.Combined',
    # 'ViewLayer.Combined.Variance'": the layers statmc reads as statistics were recognised
    # only at the top level ('Variance.R'), not as the last part of a layer's name
    names = [f"ViewLayer.Combined.{g}{c}" for g in ("", "Variance.", "Albedo.") for c in "RGB"]
    p = tmp_path / "blender.exr"
    _write_raw(p, {n: np.ones((2, 3)) for n in names})
    with pytest.raises(FileFormatError, match=r"only inside layer\(s\) 'ViewLayer.Combined' \(e.g."):
        read_image(p)


@pytest.mark.parametrize("value, n", [(64.0, 64), (-3, None), (2.5, None), ("64", None)])
def test_a_samples_per_pixel_attribute_of_another_type(tmp_path, value, n):
    # before: a float 64.0 (another tool's writer) was ignored, and every unusable value
    # was reported as "no SampleCount channel and no samplesPerPixel header attribute",
    # although the file has one
    p = tmp_path / "a.exr"
    _pbrt_file_with_header(p, spp=value)
    if n is not None:
        assert (read_exr(p).n == n).all() and exr_info(p)["samples_per_pixel"] == n
        return
    with pytest.raises(FileFormatError, match=rf"its samplesPerPixel header attribute, "
                       rf"{re.escape(repr(value))}, is not a whole number >= 0.*pass the render's "
                       "uniform spp="):
        read_exr(p)
    assert (read_exr(p, spp=8).n == 8).all() and exr_info(p)["samples_per_pixel"] is None


def test_a_layer_in_another_part_is_named(tmp_path):
    # Nuke writes one part per layer ('diffuse' with diffuse.R, ...): before, layer='diffuse'
    # said only "its layers: []" of part 0, not that part 1 holds them.  A part of the same
    # data window is now read with part 0 (session 15); one of another window is named
    def hdr(window):
        return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                "dataWindow": (np.array(window[:2], np.int32), np.array(window[2:], np.int32)),
                "displayWindow": (np.array([0, 0], np.int32), np.array([9, 9], np.int32))}
    ones = np.ones((2, 3), np.float32)
    p = tmp_path / "parts.exr"
    OpenEXR.File([OpenEXR.Part(hdr([0, 0, 2, 1]), {c: ones.copy() for c in "RGB"}, name="rgba"),
                  OpenEXR.Part(hdr([1, 0, 3, 1]), {f"diffuse.{c}": ones.copy() for c in "RGB"},
                               name="diffuse")]).write(str(p))
    with pytest.raises(FileFormatError, match=r"no channels in layer 'diffuse'.*only part 0 "
                       r"\('rgba'\) of this 2-part file is read; part 1 \('diffuse'\): "
                       r"\['diffuse.B', 'diffuse.G', 'diffuse.R'\], not read with it \(data "
                       r"window \[1, 0, 3, 1\], not \[0, 0, 2, 1\]\)"):
        read_image(p, layer="diffuse")
    OpenEXR.File([OpenEXR.Part(hdr([0, 0, 2, 1]), {c: ones.copy() for c in "RGB"}, name="rgba"),
                  OpenEXR.Part(hdr([0, 0, 2, 1]), {f"diffuse.{c}": 2 * ones for c in "RGB"},
                               name="diffuse")]).write(str(p))
    assert (read_image(p, layer="diffuse") == 2).all() and (read_image(p) == 1).all()


def test_layer_reads_keep_the_pixel_types_for_the_overflow_hint(tmp_path):
    # the half-float overflow hint looks at the pixel types of the channels read, which a
    # layer read renames ('ViewLayer.Combined.R' -> 'R')
    ch = {f"ViewLayer.Combined.{c}": np.full((2, 3), 0.5, np.float16) for c in "RGB"}
    ch["ViewLayer.Combined.G"][0, 1] = np.float16(np.inf)
    p = tmp_path / "blender.exr"
    _write_raw(p, ch, dtype=np.float16)
    with pytest.raises(FileFormatError, match=r"the Inf of R\+G\+B is likely an overflow"):
        read_image(p, layer="ViewLayer.Combined")


def test_nonfinite_chromaticities_are_not_taken(tmp_path):
    # an attribute with NaN is no colour space: reported as None, so no output carries it
    p = tmp_path / "a.exr"
    _pbrt_file_with_header(p, chromaticities=(0.64, 0.33, 0.3, 0.6, 0.15, np.nan, 0.3127, 0.329))
    assert read_exr(p).meta["chromaticities"] is None and exr_info(p)["chromaticities"] is None


def test_a_sample_count_channel_takes_precedence_over_the_attribute(tmp_path):
    # a file with both (another tool's per-pixel counts under a copied pbrt-v4 header):
    # the per-pixel channel is the more specific, and spp= is checked against it
    ch = {c: np.full((3, 4), 0.5, np.float32) for c in ("R", "G", "B")}
    ch.update({f"Variance.{c}": np.full((3, 4), 0.1, np.float32) for c in "RGB"})
    counts = np.arange(12, dtype=np.float32).reshape(3, 4) + 2
    ch["SampleCount"] = counts
    p = tmp_path / "both.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "samplesPerPixel": 64}, ch).write(str(p))
    s = read_exr(p)
    np.testing.assert_array_equal(s.n, counts)
    assert s.meta["sample_count_source"] == "file"
    with pytest.raises(InputError, match="disagrees with the SampleCount channel"):
        read_exr(p, spp=64)
    assert exr_info(p)["samples_per_pixel"] == 64 and exr_info(p)["sample_count"]["max"] == 13


def test_srgb_encoding_in_place_equals_both_branches_formula():
    """to_display's sRGB curve is computed in one array in place (session 11: 80 -> 47 ms
    at 1920x1080); bit for bit the two-branch formula (IEC 61966-2-1) it replaced, at the
    threshold, 0, 1, subnormals and beyond, for every tone curve; the caller's image is
    not modified."""
    rng = np.random.default_rng(2)
    t = 0.0031308
    edge = [0.0, t, np.nextafter(t, 1), np.nextafter(t, 0), 1.0, np.nextafter(1, 2), 5e-324,
            1e-300, 1e150, 0.5, -1.0, 3.0]
    img = np.concatenate([edge, np.abs(rng.standard_cauchy(300)) * 0.01]).reshape(-1, 4, 3)
    keep = img.copy()
    for tonemap in ("srgb", "reinhard", "aces"):
        for exposure in (0.0, 3.0):
            x = np.maximum(img * 2.0 ** exposure, 0.0)
            if tonemap == "reinhard":
                x = x / (1.0 + x)
            elif tonemap == "aces":
                x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
            x = np.clip(x, 0.0, 1.0)
            want = np.where(x <= t, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
            got = exr.to_display(img, exposure=exposure, tonemap=tonemap)
            assert got.tobytes() == want.tobytes(), (tonemap, exposure)
    assert img.tobytes() == keep.tobytes()


# ------------------------------------------------ session 12: multi-part files, part=
def _two_part_file(path, rng, h=4, w=3):
    """Part 0 'depth' (Z only, at the origin); part 1 'beauty' with statistics and alpha in
    another data window: what a compositor's multi-part file holds."""
    def hdr(window=None):
        h_ = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        if window is not None:
            (x0, y0, x1, y1), disp = window
            h_["dataWindow"] = (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))
            h_["displayWindow"] = (np.array(disp[:2], np.int32), np.array(disp[2:], np.int32))
        return h_
    ch = _stats_channels_for(h, w, rng)
    ch["A"] = rng.random((h, w)).astype(np.float32)
    windows = ([2, 1, 2 + w - 1, 1 + h - 1], [0, 0, 9, 9])
    # the parts of a file share one display window (OpenEXR refuses others)
    OpenEXR.File([OpenEXR.Part(hdr(([0, 0, w - 1, h - 1], windows[1])), {"Z": ch["R"].copy()},
                               name="depth"),
                  OpenEXR.Part(hdr(windows), {k: v.copy() for k, v in ch.items()},
                               name="beauty")]).write(str(path))
    return ch, windows


def test_part_reads_another_part_by_index_or_name(tmp_path):
    # before: only part 0 was read (read_exr had no part=): a multi-part file whose beauty is
    # not the first part could not be read at all
    rng = np.random.default_rng(40)
    p = tmp_path / "parts.exr"
    ch, windows = _two_part_file(p, rng)
    for part in (1, "beauty", np.int64(1)):
        s = read_exr(p, part=part)
        np.testing.assert_array_equal(s.mean[..., 1], ch["G"])
        np.testing.assert_array_equal(s.sample_var[..., 2], ch["Variance.B"])
        assert (s.n == 16).all() and s.meta["part"] == 1 and s.meta["extra_channels"] == ["A"]
        assert (s.meta["data_window"], s.meta["display_window"]) == windows
        np.testing.assert_array_equal(read_image(p, part=part)[..., 0], ch["R"])
        np.testing.assert_array_equal(read_channels(p, ["A"], part=part)["A"], ch["A"])
        assert exr.exr_windows(p, part=part) == windows
        info = exr_info(p, part=part, families=True)
        assert info["part"] == {"part": 1, "name": "beauty"} and info["layout"]["variance"]
        assert info["other_parts"] == [{"part": 0, "name": "depth", "channels": ["Z"]}]
    assert read_exr(p, part=1, layer=None).meta["layer"] is None
    # part 0 as before, its error now naming part= and the other part's channels
    assert exr_info(p)["part"] == {"part": 0, "name": "depth"}
    assert read_channels(p, part="depth")["Z"].shape == (4, 3)
    with pytest.raises(FileFormatError, match=r"only part 0 \('depth'\) of this 2-part file is "
                       r"read; part 1 \('beauty'\): \['A', 'B', .*\) — pass part=INDEX or "
                       r"part='NAME' to read another"):
        read_image(p)
    # a missing channel in part 1 lists part 0's
    with pytest.raises(FileFormatError, match=r"lacks channel\(s\) \['Z'\].*only part 1 "
                       r"\('beauty'\) of this 2-part file is read; part 0 \('depth'\): \['Z'\], not read with "
                       r"it \(data window \[0, 0, 2, 3\], not \[2, 1, 4, 4\]\)\)"):
        read_channels(p, ["Z"], part="beauty")


def test_a_missing_part_is_refused_naming_the_parts(tmp_path):
    rng = np.random.default_rng(41)
    p = tmp_path / "parts.exr"
    _two_part_file(p, rng)
    for read in (read_exr, read_image, read_channels, exr_info, exr.exr_windows):
        with pytest.raises(FileFormatError, match=r"has no part 2; it has 2 parts: part 0 "
                           r"\('depth'\), part 1 \('beauty'\) \(`part` takes an index"):
            read(p, part=2)
        with pytest.raises(FileFormatError, match=r"has no part named 'Beauty'; it has 2 parts: "
                           r"part 0 \('depth'\), part 1 \('beauty'\)"):
            read(p, part="Beauty")
    for bad in (-1, True, "", 1.0, None):
        with pytest.raises(InputError, match=r"`part` must be a part's index \(0, 1, ...\) or its "
                           rf"name; got {re.escape(repr(bad))}"):
            read_exr(p, part=bad)
    q = tmp_path / "one.exr"                           # a single-part file: part 0 only
    _write_raw(q, {c: np.ones((2, 3)) for c in "RGB"})
    assert read_image(q, part=0).shape == (2, 3, 3)
    with pytest.raises(FileFormatError, match=r"has no part 1; it has 1 part: part 0 \(`part`"):
        read_image(q, part=1)


def test_statistics_and_stencil_of_another_part_from_one_read(tmp_path, monkeypatch):
    # the --crn Z of `statmc combine --z-part`: statistics and stencil of part 1, one read
    rng = np.random.default_rng(42)
    st, cov = _stencil_stats(rng)
    single = tmp_path / "crn.exr"
    write_exr(single, st, extra=exr.spatial_covariance_channels(cov, st.n))
    chans = read_channels(single)
    p = tmp_path / "parts.exr"
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    h, w = chans["R"].shape                  # a depth of another window: not read with "crn"
    small = dict(hdr, dataWindow=(np.array([0, 0], np.int32), np.array([w - 2, h - 1], np.int32)),
                 displayWindow=(np.array([0, 0], np.int32), np.array([w - 1, h - 1], np.int32)))
    OpenEXR.File([OpenEXR.Part(small, {"Z": chans["R"][:, 1:].copy()}, name="depth"),
                  OpenEXR.Part(dict(hdr), {k: v.copy() for k, v in chans.items()},
                               name="crn")]).write(str(p))
    real, reads = OpenEXR.File, []

    def counting(*a, **k):
        reads.append(str(a[0]))
        return real(*a, **k)

    monkeypatch.setattr(OpenEXR, "File", counting)
    got, stencil = exr._read_exr_and_stencil(p, part="crn", covariance=False)
    assert stencil().tobytes() == exr.read_spatial_covariance(single).tobytes()
    _assert_same(read_exr(single, covariance=False), got)
    assert reads == [str(p), str(single), str(single)]


# ------------------------------- session 12: feature layers of other tools (albedo, normal)
def _blender_denoising_file(path, rng, view_layers=("ViewLayer",), dtype=np.float32):
    """A Blender (Cycles) multilayer file with Denoising Data passes, per view layer: the
    beauty in '<vl>.Combined', 'Denoising Albedo.R/G/B', 'Denoising Normal.X/Y/Z' (camera
    space), and the plain 'Normal' pass (world space), which is not a denoising feature."""
    ch = {}
    for vl in view_layers:
        ch.update({f"{vl}.Combined.{c}": rng.random((3, 4)) for c in "RGBA"})
        ch.update({f"{vl}.Denoising Albedo.{c}": rng.random((3, 4)) for c in "RGB"})
        ch.update({f"{vl}.Denoising Normal.{c}": rng.random((3, 4)) * 2 - 1 for c in "XYZ"})
        ch.update({f"{vl}.Normal.{c}": rng.random((3, 4)) * 2 - 1 for c in "XYZ"})
        ch[f"{vl}.Depth.Z"] = rng.random((3, 4))
    _write_raw(path, ch, dtype=dtype)
    return {k: v.astype(dtype).astype(np.float64) for k, v in ch.items()}


def test_blender_denoising_passes_are_read_as_albedo_and_normal(tmp_path):
    # before: a Blender render's Denoising Albedo/Normal passes were left out (channels
    # outside --layer), so OIDN ran on it without features
    rng = np.random.default_rng(50)
    p = tmp_path / "blender.exr"
    ch = _blender_denoising_file(p, rng, view_layers=("ViewLayer", "Other"))
    for vl in ("ViewLayer", "Other"):              # the view layer of the colour read
        s = read_exr(p, layer=f"{vl}.Combined", spp=4, require_variance=False)
        for k, c in enumerate("RGB"):
            np.testing.assert_array_equal(s.albedo[..., k], ch[f"{vl}.Denoising Albedo.{c}"])
        for k, c in enumerate("XYZ"):               # as stored, not normalised or rotated
            np.testing.assert_array_equal(s.normal[..., k], ch[f"{vl}.Denoising Normal.{c}"])
        assert s.meta["albedo_layer"] == f"{vl}.Denoising Albedo"
        assert s.meta["normal_layer"] == f"{vl}.Denoising Normal"
        assert s.meta["extra_channels"] == ["A"]
    # explicit layers: Blender's plain Normal pass, or none of another tool (False)
    s = read_exr(p, layer="ViewLayer.Combined", spp=4, require_variance=False,
                 normal="ViewLayer.Normal", albedo=False)
    np.testing.assert_array_equal(s.normal[..., 2], ch["ViewLayer.Normal.Z"])
    assert s.albedo is None and s.meta["albedo_layer"] is None
    info = exr_info(p, families=True)
    assert info["features"] == {"albedo": ["Other.Denoising Albedo", "ViewLayer.Denoising Albedo"],
                                "normal": ["Other.Denoising Normal", "ViewLayer.Denoising Normal"]}


def _mitsuba_aov_file(path, rng, aovs=("albedo", "nn")):
    """Channels as Mitsuba 3.9.1's aov integrator writes them (film bitmap of
    aovs="albedo:albedo,nn:sh_normal,dd:depth" with a nested 'img' path integrator, checked
    by rendering): R, G, B, img.R/G/B/A, albedo.R/G/B, nn.X/Y/Z, dd.T."""
    ch = {c: rng.random((3, 4)) for c in "RGB"}
    ch.update({f"img.{c}": rng.random((3, 4)) for c in "RGBA"})
    ch["dd.T"] = rng.random((3, 4))
    for name in aovs:
        comps = "RGB" if "albedo" in name.lower() else "XYZ"
        ch.update({f"{name}.{c}": rng.random((3, 4)) for c in comps})
    _write_raw(path, ch)
    return {k: v.astype(np.float32).astype(np.float64) for k, v in ch.items()}


def test_mitsuba_aov_layers_are_recognised_by_well_known_names_only(tmp_path):
    rng = np.random.default_rng(51)
    p = tmp_path / "mitsuba.exr"
    ch = _mitsuba_aov_file(p, rng)
    s = read_exr(p, spp=4, require_variance=False)
    np.testing.assert_array_equal(s.albedo[..., 1], ch["albedo.G"])
    assert s.normal is None and s.meta["normal_layer"] is None      # 'nn' is not guessed
    assert s.meta["extra_channels"] == ["dd.T", "img.A", "img.B", "img.G", "img.R",
                                        "nn.X", "nn.Y", "nn.Z"]
    s = read_exr(p, spp=4, require_variance=False, normal="nn")
    np.testing.assert_array_equal(s.normal[..., 0], ch["nn.X"])
    assert "nn.X" not in s.meta["extra_channels"] and s.meta["normal_layer"] == "nn"
    q = tmp_path / "sh.exr"
    ch = _mitsuba_aov_file(q, rng, aovs=("albedo", "sh_normal"))
    s = read_exr(q, spp=4, require_variance=False)
    np.testing.assert_array_equal(s.normal[..., 2], ch["sh_normal.Z"])
    assert exr_info(q)["features"] == {"albedo": ["albedo"], "normal": ["sh_normal"]}


def test_ambiguous_feature_layers_are_refused_listing_them(tmp_path):
    rng = np.random.default_rng(52)
    p = tmp_path / "two.exr"
    ch = _mitsuba_aov_file(p, rng, aovs=("albedo", "Denoising Albedo", "normal"))
    with pytest.raises(FileFormatError, match=r"has 2 layers statmc would read as the albedo: "
                       r"\['Denoising Albedo', 'albedo'\]; it does not choose between them: "
                       r"pass albedo='NAME'"):
        read_exr(p, spp=4, require_variance=False)
    s = read_exr(p, spp=4, require_variance=False, albedo="Denoising Albedo")
    np.testing.assert_array_equal(s.albedo[..., 0], ch["Denoising Albedo.R"])
    np.testing.assert_array_equal(s.normal[..., 0], ch["normal.X"])
    assert read_exr(p, spp=4, require_variance=False, albedo=False).albedo is None
    # statmc's own Albedo.* comes first: no ambiguity with another tool's layer
    q = tmp_path / "own.exr"
    _write_raw(q, dict({k: v for k, v in ch.items()},
                       **{f"Albedo.{c}": np.full((3, 4), 0.25) for c in "RGB"}))
    s = read_exr(q, spp=4, require_variance=False)
    assert (s.albedo == 0.25).all() and s.meta["albedo_layer"] == "Albedo"
    assert "albedo.R" in s.meta["extra_channels"]
    assert exr_info(q)["features"]["albedo"] == ["Albedo", "Denoising Albedo", "albedo"]


def test_explicit_feature_layers_are_checked(tmp_path):
    rng = np.random.default_rng(53)
    p = tmp_path / "m.exr"
    ch = _mitsuba_aov_file(p, rng)
    with pytest.raises(FileFormatError, match=r"has no normal layer 'n' \(channels 'n.X', 'n.Y', "
                       r"'n.Z' or .R, .G, .B\); layers with X, Y, Z channels: \['nn'\]"):
        read_exr(p, spp=4, require_variance=False, normal="n")
    with pytest.raises(FileFormatError, match=r"has no albedo layer 'img.A'"):
        read_exr(p, spp=4, require_variance=False, albedo="img.A")
    # a normal stored as R, G, B (as some tools write it)
    s = read_exr(p, spp=4, require_variance=False, normal="img")
    np.testing.assert_array_equal(s.normal[..., 1], ch["img.G"])
    for bad in ("", "nn.", 3, True):
        with pytest.raises(InputError, match=r"`normal` must be the name of the layer holding "
                           r"the normal"):
            read_exr(p, spp=4, require_variance=False, normal=bad)


def test_nonfinite_values_of_another_tools_feature_layer_are_counted(tmp_path):
    rng = np.random.default_rng(54)
    p = tmp_path / "b.exr"
    ch = {f"ViewLayer.Combined.{c}": np.full((3, 4), 0.5) for c in "RGB"}
    ch.update({f"ViewLayer.Denoising Albedo.{c}": np.full((3, 4), 0.5) for c in "RGB"})
    ch["ViewLayer.Denoising Albedo.G"][1, 1] = np.inf
    _write_raw(p, ch, dtype=np.float16)
    with pytest.raises(FileFormatError, match=r"non-finite values \(Albedo: 0 NaN, 1 Inf\) \(the "
                       r"Inf of Albedo is likely an overflow"):
        read_exr(p, layer="ViewLayer.Combined", spp=2, require_variance=False)
    s = read_exr(p, layer="ViewLayer.Combined", spp=2, require_variance=False,
                 nonfinite="replace")
    assert s.albedo[1, 1, 1] == 0 and s.meta["nonfinite_by_group"] == {"Albedo": {"nan": 0, "inf": 1}}
    del rng


# ---------------------------------------------------------------------------- I/O speed (session 12)
def test_to_display_matches_the_plain_formula_and_leaves_its_input_alone():
    """to_display works in place on one float64 temporary (no copies of a 1080p image per
    step): bit for bit the plain formula ``sRGB(min(max(x · 2**e, 0), 1e150))``, and the
    caller's array (float64, which as_float_array does not copy) unchanged."""
    rng = np.random.default_rng(3)
    x = rng.normal(0.4, 0.8, (17, 23, 3))
    x[0, :3, 0] = [0.0, -0.0, 1e-300]
    keep = x.copy()

    def plain(v, e):
        v = np.minimum(np.maximum(v.astype(np.float64) * 2.0 ** e, 0.0), 1e150)
        v = np.clip(v, 0.0, 1.0)
        return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)

    for e in (0.0, 1.5, -3.0):
        np.testing.assert_array_equal(to_display(x, exposure=e), plain(x, e))
        np.testing.assert_array_equal(to_display(x.astype(np.float32), exposure=e),
                                      plain(x.astype(np.float32), e))
    np.testing.assert_array_equal(x, keep)


def _zlib_levels(png: bytes) -> set:
    """The FLEVEL field (0 fastest .. 3 maximum) of the zlib stream in a PNG's IDAT chunks."""
    levels, pos, idat = set(), 8, b""
    while pos < len(png):
        length, kind = struct.unpack(">I4s", png[pos:pos + 8])
        if kind == b"IDAT":
            idat += png[pos + 8:pos + 8 + length]
        pos += 12 + length
    levels.add(idat[1] >> 6)
    return levels


def test_png_preview_is_encoded_fast_and_exactly(tmp_path):
    """The preview is written with zlib's fastest level (FLEVEL 0: Pillow's compress_level
    1), not Pillow's default 6 (FLEVEL 2), 2-3x slower at 1080p (0.39-0.54 against
    0.16-0.28 s) for files within 8 % of the size; its pixels are round(255 · to_display)."""
    from PIL import Image

    rng = np.random.default_rng(4)
    img = rng.gamma(1.0, 0.5, (40, 60, 3))
    p = tmp_path / "p.png"
    write_png_preview(p, img)
    assert _zlib_levels(p.read_bytes()) == {0}
    np.testing.assert_array_equal(np.asarray(Image.open(p)),
                                  np.round(to_display(img) * 255.0).astype(np.uint8))


def test_using_io_threads_writes_the_same_bytes_and_restores_the_pool(tmp_path):
    """With OpenEXR's thread pool (the command line's using_io_threads), files are the same
    bytes and decode to the same pixels; the pool's size is put back afterwards."""
    rng = np.random.default_rng(5)
    s = PixelStats.from_mean_var(rng.random((70, 33, 3)), rng.random((70, 33, 3)),
                                 rng.integers(2, 9, (70, 33)))
    before = OpenEXR.global_thread_count()
    write_exr(tmp_path / "a.exr", s)
    with exr.using_io_threads(3):
        write_exr(tmp_path / "b.exr", s)
        assert OpenEXR.global_thread_count() == 3
        threaded = read_channels(tmp_path / "a.exr")
    assert OpenEXR.global_thread_count() == before
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    plain = read_channels(tmp_path / "a.exr")
    assert threaded.keys() == plain.keys()
    for k in plain:
        np.testing.assert_array_equal(threaded[k], plain[k])


def test_reads_do_not_share_memory(tmp_path):
    """Each read owns its arrays (the decoder's own, not copied again): changing one read
    changes neither the file's next read nor another read of the same decoding."""
    write_exr(tmp_path / "a.exr", np.ones((4, 5, 3)))
    a, b = read_channels(tmp_path / "a.exr"), read_channels(tmp_path / "a.exr")
    assert not np.shares_memory(a["R"], b["R"]) and a["R"].flags.writeable
    a["R"][:] = 7.0
    assert float(read_channels(tmp_path / "a.exr")["R"].max()) == 1.0
    with exr._reading_once(tmp_path / "a.exr"):
        s = read_exr(tmp_path / "a.exr", spp=1, require_variance=False)
        s.mean[:] = 3.0
        assert float(read_image(tmp_path / "a.exr").max()) == 1.0


@pytest.mark.parametrize("call, needle", [
    (lambda p, q: read_exr(None), r"`path` must be a file path \(a str or os.PathLike\); got "
                                  r"NoneType None"),
    (lambda p, q: write_exr(3, np.ones((2, 2, 3))), r"`path` must be a file path .*; got int 3"),
    (lambda p, q: read_exr(p, nonfinite="replace", replace_value="a"),
     r"`replace_value` must be a finite number; got 'a'"),
    (lambda p, q: read_exr(p, require_variance="no"), r"`require_variance` must be True or False"),
    (lambda p, q: read_exr(p, spp=4, spp_if_missing="yes"),
     r"`spp_if_missing` must be True or False; got 'yes'"),
    (lambda p, q: exr_info(p, families="yes"), r"`families` must be True or False; got 'yes'"),
    (lambda p, q: read_channels(p, 3), r"`names` must be a channel name or a list of them; got 3"),
    (lambda p, q: write_exr(q, np.ones((2, 2, 3)), extra=[1]),
     r"`extra` must be a dict of channel name to \(H, W\) array; got list"),
    (lambda p, q: write_exr(q, np.ones((0, 2, 3))), r"`data` must have pixels; got an image of "
                                                    r"\(H, W\) = \(0, 2\)"),
    (lambda p, q: write_exr(q, PixelStats.empty(2, 0)), r"`data` must have pixels"),
    (lambda p, q: write_exr(q, np.ones((2, 2, 4))), r"`data` must be a PixelStats or an image "
                                                    r"with 1 or 3 channels"),
    (lambda p, q: write_png_preview(str(q)[:-4] + ".png", np.ones((0, 2, 3))),
     r"`image` must have pixels for a PNG preview; got shape \(0, 2, 3\)"),
    (lambda p, q: exr.using_io_threads(-1).__enter__(), r"`threads` must be a non-negative "
                                                        r"integer; got -1"),
])
def test_io_arguments_of_the_wrong_type_are_named(tmp_path, call, needle):
    # before: read_exr(None) and write_exr(3, ...) were os.fspath's TypeError, replace_value
    # 'a' numpy's "ufunc 'isfinite' not supported", flags such as require_variance='no' were
    # taken as True, read_channels(p, 3) "'int' object is not iterable", extra=[1] an
    # AttributeError, an empty image OpenEXR's "Invalid display window in image header",
    # write_exr's messages named `image` (its parameter is `data`), an empty PNG Pillow's
    # ValueError, and using_io_threads(-1) sized OpenEXR's pool -1
    p, q = tmp_path / "a.exr", tmp_path / "b.exr"
    write_exr(p, PixelStats.from_mean_var(np.ones((2, 2, 3)), np.ones((2, 2, 3)),
                                          np.full((2, 2), 4)))
    with pytest.raises(InputError, match=needle):
        call(p, q)
    assert not q.exists()


def test_overwrite_must_be_a_boolean(tmp_path):
    # before: write_exr(p, x, overwrite="no") replaced p (a non-empty string is true)
    p = tmp_path / "a.exr"
    write_exr(p, np.ones((2, 2, 3)))
    before = p.read_bytes()
    with pytest.raises(InputError, match=r"`overwrite` must be True or False; got 'no'"):
        write_exr(p, np.zeros((2, 2, 3)), overwrite="no")
    with pytest.raises(InputError, match=r"`overwrite` must be True or False; got None"):
        write_png_preview(tmp_path / "a.png", np.zeros((2, 2, 3)), overwrite=None)
    assert p.read_bytes() == before and sorted(os.listdir(tmp_path)) == ["a.exr"]
