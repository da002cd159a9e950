"""Cube files in and out (issue 24): ENVI through Spectral Python, GeoTIFF through tifffile, ``.npy`` with the
wavelength sidecar; the model's bands synthesised from hyperspectral cubes with ``bands.py``'s band response;
frames streamed in row tiles from memory-mapped files with the same mask as the detector on the whole frame;
hostile files refused in one line, with nothing written."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

spectral = pytest.importorskip("spectral")
tifffile = pytest.importorskip("tifffile")

from torchskin import cubefiles  # noqa: E402
from torchskin.cubefiles.tiff import _gdal_items  # noqa: E402
from torchskin.onboard import OnboardDetector, apply_plan, band_plan, calibrate_file, detect_file  # noqa: E402

DET = str(Path(__file__).resolve().parents[1] / "exports" / "detector.onnx")
CFG = ["--sun-zenith", "40", "--camera-zenith", "30", "--relative-azimuth", "60", "--diffuse-share", "0.2"]  # the shipped lut takes the share
CONFIG = [40.0, 30.0, 60.0, 0.2]  # the shipped lut: the angles and the diffuse share
MODEL_BANDS = [544.0, 633.0, 1080.0, 1580.0]
SKIN = np.array([0.25, 0.35, 0.55, 0.15], dtype=np.float32)


@pytest.fixture(scope="module")
def det():
    return OnboardDetector(DET, threads=2)


def _skin_cube(h=20, w=20):
    """A reflectance frame in the model's band order: a skin patch (rows 5-14, columns 5-14) on grey."""
    cube = np.full((4, h, w), 0.2, dtype=np.float32)
    cube[:, 5:15, 5:15] = SKIN[:, None, None]
    return cube


def _scene(h, w, seed=0):
    """A frame of many skin-like and other pixels (random per pixel around the skin spectrum): a mask with many
    edges, and scores near 0 at some pixels."""
    rng = np.random.default_rng(seed)
    cube = SKIN[:, None, None] * rng.uniform(0.6, 1.4, (4, h, w)).astype(np.float32)
    cube[:, : h // 3] = rng.uniform(0.05, 0.9, (4, h // 3, w)).astype(np.float32)
    return cube


def _one_line(capsys, rc):
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and out == "" and len(lines) == 1, (rc, out, err)
    return lines[0]


def _save_envi(path, cube, interleave="bsq", dtype=np.float32, byteorder="little", **meta):
    """A (bands, H, W) cube as an ENVI file by Spectral Python itself (it takes (rows, columns, bands))."""
    spectral.envi.save_image(str(path), np.transpose(cube, (1, 2, 0)).astype(dtype), interleave=interleave,
                             byteorder=byteorder, dtype=dtype, force=True, metadata=meta)
    return Path(path)


def _save_npy(path, cube, bands, fwhm=None):
    np.save(path, cube)
    (path.parent / (path.stem + ".bands.json")).write_text(json.dumps(
        {"bands_nm": list(bands), "units": "nm", **({"fwhm_nm": list(fwhm)} if fwhm is not None else {})}))
    return path


# ---------------------------------------------------------------------------------------------------- ENVI
@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("byteorder", ["little", "big"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_envi_cubes_of_every_layout_read_as_written(tmp_path, interleave, byteorder, dtype):
    """Spectral Python writes the cube in each interleave, byte order and data type; ``open_cube`` reads the same
    values with the header's wavelengths, memory-mapped in the file's own layout, and rows alone as asked."""
    rng = np.random.default_rng(1)
    cube = rng.integers(0, 3000, (5, 7, 9)).astype(np.float32) if dtype == np.int16 else \
        rng.uniform(0, 1, (5, 7, 9)).astype(np.float32)
    wl = [450.0, 544.0, 633.0, 1080.0, 1580.0]
    hdr = _save_envi(tmp_path / "c.hdr", cube, interleave, dtype, byteorder, wavelength=wl, fwhm=[10] * 5,
                     **{"wavelength units": "Nanometers"})
    head = spectral.envi.read_envi_header(str(hdr))
    assert head["interleave"] == interleave and int(head["byte order"]) == (byteorder == "big")
    cf = cubefiles.open_cube(hdr)
    assert cf.format == "envi" and cf.shape == (5, 7, 9) and cf.dtype == np.dtype(dtype).newbyteorder(
        ">" if byteorder == "big" else "<")
    assert cf.bands == wl and cf.fwhm == [10.0] * 5
    np.testing.assert_array_equal(cf.read(), cube.astype(dtype).astype(np.float32))
    np.testing.assert_array_equal(cf.read_rows(2, 5), cube.astype(dtype).astype(np.float32)[:, 2:5])
    assert cubefiles.open_cube(hdr.with_suffix(".img")).shape == cf.shape  # named by its data file too


def test_written_envi_opens_in_spectral_python_with_wavelengths_fwhm_and_units(tmp_path):
    cube = np.random.default_rng(2).uniform(0, 1, (3, 4, 6)).astype(np.float32)
    p = cubefiles.write_cube(tmp_path / "r.hdr", cube, "envi", [544.0, 633.5, 1080.0], [0.0, 10.0, 20.0])
    img = spectral.open_image(str(p))
    assert img.shape == (4, 6, 3)
    assert img.bands.centers == [544.0, 633.5, 1080.0] and img.bands.bandwidths == [0.0, 10.0, 20.0]
    assert img.bands.band_unit == "Nanometers" and img.metadata["data units"] == "1"
    np.testing.assert_array_equal(np.transpose(img.load(), (2, 0, 1)), cube)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["r.hdr", "r.img"]


def test_a_header_in_micrometres_is_converted(tmp_path, capsys, det):
    from torchskin.cli import main

    cube = _skin_cube()
    hdr = _save_envi(tmp_path / "um.hdr", cube, wavelength=[0.544, 0.633, 1.08, 1.58],
                     **{"wavelength units": "Micrometers"})
    assert cubefiles.open_cube(hdr).bands == pytest.approx(MODEL_BANDS)
    assert main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == int(det(cube[None], CONFIG)["mask"].sum()) == 100


# ------------------------------------------------------------------------------------------------- GeoTIFF
def test_written_geotiff_carries_band_wavelengths_read_by_tifffile(tmp_path):
    cube = np.random.default_rng(3).uniform(0, 1, (4, 5, 6)).astype(np.float32)
    p = cubefiles.write_cube(tmp_path / "s.tif", cube, "tiff", MODEL_BANDS, [5.0] * 4, "signal")
    with tifffile.TiffFile(str(p)) as tif:
        np.testing.assert_array_equal(tif.asarray(), cube)
        xml = tif.pages[0].tags[cubefiles.GDAL_METADATA_TAG].value
    top, per = _gdal_items(xml)
    assert [float(per[i]["wavelength"]) for i in range(4)] == MODEL_BANDS
    assert {per[i]["wavelength_units"] for i in range(4)} == {"Nanometers"}
    assert [float(per[i]["fwhm"]) for i in range(4)] == [5.0] * 4 and per[0]["unittype"] == "DN"
    back = cubefiles.open_cube(p)
    assert back.bands == MODEL_BANDS and back.fwhm == [5.0] * 4 and back.streaming
    np.testing.assert_array_equal(back.read(), cube)


def _georeferenced_tiff(path, cube, bands):
    """A multi-band GeoTIFF with a pixel scale, a tie point, a GeoKey directory (EPSG:32633) and GDAL_METADATA
    wavelengths, as a camera's or GDAL's product carries them."""
    geo = [(33550, 12, 3, (0.05, 0.05, 0.0), True),
           (33922, 12, 6, (0.0, 0.0, 0.0, 500000.0, 4649776.0, 0.0), True),
           (34735, 3, 16, (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32633), True),
           (cubefiles.GDAL_METADATA_TAG, 2, 0, cubefiles.gdal_metadata_xml(bands, None), True)]
    tifffile.imwrite(str(path), cube, photometric="minisblack", planarconfig="separate", extratags=geo)
    return {c: v for c, _, _, v, _ in geo[:3]}


def _tags(path):
    with tifffile.TiffFile(str(path)) as tif:
        return {c: tif.pages[0].tags[c].value for c in (33550, 33922, 34735) if c in tif.pages[0].tags}


def test_a_georeferenced_cubes_mask_and_calibrated_cube_keep_its_transform_and_crs(tmp_path, capsys, det):
    from torchskin.cli import main

    cube = _skin_cube()
    geo = _georeferenced_tiff(tmp_path / "geo.tif", cube, MODEL_BANDS)
    assert main(["detect", "--model", DET, "--cube", str(tmp_path / "geo.tif"), *CFG, "--out",
                 str(tmp_path / "mask.tif")]) == 0
    capsys.readouterr()
    assert {c: tuple(v) for c, v in _tags(tmp_path / "mask.tif").items()} == \
        {c: tuple(v) for c, v in geo.items()}
    np.testing.assert_array_equal(tifffile.imread(str(tmp_path / "mask.tif")),
                                  det(cube[None], CONFIG)["mask"][0].astype(np.uint8) * 255)
    # a PNG would drop the georeferencing: refused, naming the remedy, nothing written
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(tmp_path / "geo.tif"), *CFG, "--out",
                                   str(tmp_path / "mask.png")]))
    assert ".tif" in line and "georeferenced" in line and not (tmp_path / "mask.png").exists()
    # calibrate --out follows the input's format and keeps its georeferencing and wavelengths
    dn = (cube * 10000 + 100).astype(np.float32)
    dn[:, :4, :4], dn[:, -4:, -4:] = 9800.0, 400.0
    _georeferenced_tiff(tmp_path / "dn.tif", dn, MODEL_BANDS)
    assert main(["calibrate", "--cube", str(tmp_path / "dn.tif"), "--panel", "0:4:0:4=0.97", "--panel",
                 "16:20:16:20=0.03", "--out", str(tmp_path / "r.tif")]) == 0
    capsys.readouterr()
    assert {c: tuple(v) for c, v in _tags(tmp_path / "r.tif").items()} == {c: tuple(v) for c, v in geo.items()}
    r = cubefiles.open_cube(tmp_path / "r.tif")
    assert r.bands == MODEL_BANDS
    gain, offset = (9800 - 400) / 0.94, 400 - 0.03 * (9800 - 400) / 0.94
    np.testing.assert_allclose(r.read(), (dn - offset) / gain, atol=1e-5)
    assert main(["calibrate", "--cube", str(tmp_path / "dn.tif"), "--panel", "0:4:0:4=0.97", "--panel",
                 "16:20:16:20=0.03", "--out", str(tmp_path / "r.npy")]) == 2  # not the input's format
    capsys.readouterr()
    assert not (tmp_path / "r.npy").exists()


# -------------------------------------------------------------------------------------------- .npy + sidecar
def test_npy_with_its_sidecar_in_any_band_order(tmp_path, capsys, det):
    from torchskin.cli import main

    cube = _skin_cube()
    order = [3, 0, 2, 1]
    p = _save_npy(tmp_path / "c.npy", cube[order], [MODEL_BANDS[i] for i in order])
    cf = cubefiles.open_cube(p)
    assert cf.format == "npy" and cf.bands == [1580.0, 544.0, 1080.0, 633.0]
    assert main(["detect", "--model", DET, "--cube", str(p), *CFG, "--out", str(tmp_path / "m.png"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100
    np.testing.assert_array_equal(cubefiles.read_png_gray(tmp_path / "m.png"),
                                  det(cube[None], CONFIG)["mask"][0].astype(np.uint8) * 255)


# -------------------------------------------------------------------------------------------- band synthesis
def _smooth(lam):
    """A smooth reflectance spectrum (nm -> value) and the largest |second derivative| it has (per nm^2)."""
    a, b, p = 0.35, 0.15, 180.0
    return a + b * np.sin(lam / p) + 1e-4 * (lam - 1000.0), b / p ** 2


def _d2max(y, x):
    """max |y''| on the grid x (finite differences)."""
    return float(np.abs(np.gradient(np.gradient(y, x), x)).max())


@pytest.mark.parametrize("fwhm", [None, [20.0, 20.0, 40.0, 40.0]], ids=["monochromatic", "gaussian"])
def test_synthesised_bands_equal_the_band_response_of_the_spectrum(fwhm):
    """A 121-band cube (450..1650 nm by 10) of a smooth spectrum, synthesised to the model's bands, equals
    ``bands.response_matrix`` of the renderer applied to the spectrum on a fine grid, within the error of
    linear interpolation between samples 10 nm apart (h^2 / 8 max|S''|) and of the trapezoid rule on the
    band's grid of at most 1 nm (for a normalised band mean: (L d^2 / 12) (max|(gS)''| + max|S| max|g''|) / D),
    plus float32 rounding."""
    import torch

    from torchskin.bands import FWHM_TO_SIGMA, SUPPORT_FWHM, Band, response_matrix

    lam = np.arange(450.0, 1651.0, 10.0)
    assert len(lam) == 121
    spec, s2 = _smooth(lam)
    cube = np.broadcast_to(spec.astype(np.float32)[:, None, None], (121, 3, 5)).copy()
    plan = band_plan(lam.tolist(), None, MODEL_BANDS, fwhm)
    assert plan["kind"] == "synthesis" and plan["matrix"].shape == (4, 121)
    np.testing.assert_allclose(plan["matrix"].sum(1), 1.0, atol=1e-12)
    got = apply_plan(plan, cube)
    assert got.shape == (4, 3, 5) and got.dtype == np.float32
    fine = np.arange(400.0, 1700.0 + 1e-9, 0.01)
    bands = [Band(c, 0.0 if fwhm is None else f) for c, f in zip(MODEL_BANDS, fwhm or [0.0] * 4)]
    ref = (torch.as_tensor(_smooth(fine)[0]) @ response_matrix(torch.as_tensor(fine), bands)).numpy()
    tol = np.full(4, 10.0 ** 2 / 8 * s2)
    if fwhm is not None:
        for k, (c, f) in enumerate(zip(MODEL_BANDS, fwhm)):
            sig, L = f * FWHM_TO_SIGMA, 2 * SUPPORT_FWHM * f
            x = np.linspace(c - L / 2, c + L / 2, 20001)
            g = np.exp(-0.5 * ((x - c) / sig) ** 2)
            S = _smooth(x)[0]
            tol[k] += L * 1.0 ** 2 / 12 * (_d2max(g * S, x) + np.abs(S).max() * _d2max(g, x)) / np.trapezoid(g, x)
    tol += 4 * np.finfo(np.float32).eps * np.abs(ref)
    err = np.abs(got[:, 0, 0].astype(np.float64) - ref)
    assert np.all(err <= tol), (err, tol)
    assert np.all(got == got[:, :1, :1])  # every pixel alike


def test_four_bands_that_match_the_model_are_used_as_they_are(tmp_path, det):
    """Wavelengths within ``BAND_MATCH_NM`` of the model's: the cube's own values, reordered, bit for bit (no
    weights applied), and the mask of the in-memory detector on them."""
    cube = _scene(30, 40)
    order = [2, 0, 3, 1]
    bands = [MODEL_BANDS[i] + d for i, d in zip(order, (0.5, -1.0, 0.0, 1.5))]
    plan = band_plan(bands, None, MODEL_BANDS)
    assert plan == {"kind": "reorder", "order": [1, 3, 0, 2]}
    got = apply_plan(plan, cube[order])
    assert got.dtype == np.float32 and got.tobytes() == cube.tobytes()
    same = apply_plan({"kind": "reorder", "order": [0, 1, 2, 3]}, cube)
    assert same is cube
    p = _save_npy(tmp_path / "c.npy", cube[order], bands)
    res = detect_file(det, p, CONFIG, tmp_path / "m.png", negative="clip")
    assert res["plan"] == "reorder"
    want = det(cube[None], CONFIG, negative="clip")["mask"][0]
    np.testing.assert_array_equal(cubefiles.read_png_gray(tmp_path / "m.png") == 255, want)


def test_a_121_band_envi_cube_runs_through_detect_with_synthesised_bands(tmp_path, capsys):
    """The skin patch's spectrum smooth through the skin values at the model's bands: detect synthesises the
    four bands from the 121 and finds the patch."""
    from torchskin.cli import main

    lam = np.arange(450.0, 1651.0, 10.0)
    spec_skin = np.interp(lam, MODEL_BANDS, SKIN)
    cube = np.full((121, 20, 20), 0.2, dtype=np.float32)
    cube[:, 5:15, 5:15] = spec_skin.astype(np.float32)[:, None, None]
    hdr = _save_envi(tmp_path / "h.hdr", cube, "bil", wavelength=lam.tolist(), **{"wavelength units": "nm"})
    assert main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--json", "--tile-rows", "6"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100


# -------------------------------------------------------------------------------------------------- streaming
@pytest.mark.parametrize("tile_rows", [1, 7, 200, None])
def test_streaming_a_memory_mapped_cube_gives_the_in_memory_mask_exactly(tmp_path, det, tile_rows):
    """Row tiles of 1 and 7 rows (each call below the detector's tile: the whole graph), 200 rows (80000 pixels:
    the detector's own tiles and per-tile head) and the default, on a 300 x 400 frame the detector runs in tiles
    in memory: the same mask bit for bit, and the same skin count."""
    cube = _scene(300, 400)
    p = tmp_path / "c.npy"
    np.save(p, cube)
    want = det(cube[None], CONFIG, negative="clip")["mask"][0]
    assert 1000 < want.sum() < want.size - 1000
    res = detect_file(det, p, CONFIG, tmp_path / "m.png", tile_rows=tile_rows, negative="clip")
    got = cubefiles.read_png_gray(tmp_path / "m.png") == 255
    np.testing.assert_array_equal(got, want)
    assert res["skin_pixels"] == int(want.sum()) and res["pixels"] == want.size


def test_streaming_peak_memory_is_bounded_by_the_tile_not_the_frame(tmp_path, det):
    """A 4 x 2000 x 1000 float32 frame (32 MB) memory-mapped, detected and calibrated in 16-row tiles: the
    largest numpy allocation at any time (tracemalloc) stays under 4 MB, an eighth of the frame; the results are
    the whole frame's."""
    import tracemalloc

    H, W = 2000, 1000
    mm = np.lib.format.open_memmap(tmp_path / "big.npy", mode="w+", dtype=np.float32, shape=(4, H, W))
    for r0 in range(0, H, 250):
        mm[:, r0:r0 + 250] = 0.2
    mm[:, 100:140, 100:300] = SKIN[:, None, None]
    mm.flush()
    del mm
    frame = 4 * H * W * 4
    tracemalloc.start()
    try:
        res = detect_file(det, tmp_path / "big.npy", CONFIG, tmp_path / "m.png", tile_rows=16)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        cal = calibrate_file(tmp_path / "big.npy", tmp_path / "r.npy", coefficients=([2.0] * 4, [0.0] * 4),
                             tile_rows=16)
        _, peak_cal = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert res["skin_pixels"] == 40 * 200 and cal["shape"] == [4, H, W]
    assert peak < frame / 8 and peak_cal < frame / 8, (peak, peak_cal, frame)
    assert np.load(tmp_path / "r.npy", mmap_mode="r")[:, 120, 200].tolist() == (SKIN / 2).tolist()


# ---------------------------------------------------------------------------------------------------- hostile
def _envi_by_hand(folder, header, data_bytes):
    (folder / "x.hdr").write_text(header)
    (folder / "x.img").write_bytes(data_bytes)
    return folder / "x.hdr"


HEADER = ("ENVI\nsamples = 20\nlines = 20\nbands = 4\nheader offset = 0\ndata type = 4\ninterleave = {il}\n"
          "byte order = 0\n{wl}")
WL_NM = "wavelength units = Nanometers\nwavelength = {544, 633, 1080, 1580}\n"


@pytest.mark.parametrize("case,header,nbytes,expect", [
    ("no wavelengths", HEADER.format(il="bsq", wl=""), 6400, "no 'wavelength'"),
    ("truncated raw file", HEADER.format(il="bsq", wl=WL_NM), 6000, "truncated"),
    ("interleave not matching the size", HEADER.format(il="bil", wl=WL_NM).replace("bands = 4", "bands = 5"),
     6400, "truncated"),
    ("unknown interleave", HEADER.format(il="bsx", wl=WL_NM), 6400, "interleave 'bsx'"),
    ("wavelengths in um without units", HEADER.format(
        il="bip", wl="wavelength = {0.544, 0.633, 1.08, 1.58}\n"), 6400, "look like micrometres"),
    ("a band the cube does not cover", HEADER.format(
        il="bsq", wl="wavelength units = nm\nwavelength = {520, 560, 600, 640}\n"), 6400, "1080 nm band"),
])
@pytest.mark.parametrize("command", ["detect", "calibrate"])
def test_hostile_envi_files_get_one_line_and_nothing_written(tmp_path, capsys, case, header, nbytes, expect,
                                                             command):
    from torchskin.cli import main

    data = (tmp_path / "data")
    data.mkdir()
    hdr = _envi_by_hand(data, header, np.full(nbytes // 4, 0.2, "<f4").tobytes())
    out = tmp_path / "out"
    out.mkdir()
    if command == "calibrate" and case == "a band the cube does not cover":
        pytest.skip("calibrate needs no model band")
    argv = (["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(out / "m.png")] if command == "detect"
            else ["calibrate", "--cube", str(hdr), "--panel", "0:4:0:4=0.97", "--panel", "16:20:16:20=0.03",
                  "--out", str(out / "r.hdr")])
    line = _one_line(capsys, main(argv))
    assert expect in line and ("x.hdr" in line or "x.img" in line), line
    if case == "a band the cube does not cover":
        assert "520..640 nm" in line, line
    assert list(out.iterdir()) == []


def test_a_band_the_121_band_cube_does_not_cover_is_named_with_the_cubes_range(tmp_path, capsys):
    from torchskin.cli import main

    lam = np.arange(450.0, 1451.0, 10.0)  # stops short of 1580 nm
    cube = np.full((len(lam), 8, 8), 0.2, dtype=np.float32)
    hdr = _save_envi(tmp_path / "h.hdr", cube, wavelength=lam.tolist(), **{"wavelength units": "Nanometers"})
    out = tmp_path / "out"
    out.mkdir()
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(out / "m.png")]))
    assert "1580 nm band" in line and "450..1450 nm" in line, line
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("command", ["detect", "calibrate"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_streamed_cube_with_nan_or_inf_in_a_late_tile_is_refused_with_nothing_written(tmp_path, capsys,
                                                                                         command, bad):
    """The value sits in the last tile, after earlier tiles' mask rows went to the temporary file."""
    from torchskin.cli import main

    cube = _skin_cube()
    cube[:, 0:4, 0:4] = 0.9  # a bright panel for calibrate
    cube[2, 18, 3] = bad
    hdr = _save_envi(tmp_path / "c.hdr", cube, wavelength=MODEL_BANDS, **{"wavelength units": "Nanometers"})
    out = tmp_path / "out"
    out.mkdir()
    argv = (["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(out / "m.png")] if command == "detect"
            else ["calibrate", "--cube", str(hdr), "--panel", "0:4:0:4=0.97", "--panel", "5:15:5:15=0.03",
                  "--out", str(out / "r.hdr")])
    line = _one_line(capsys, main([*argv, "--tile-rows", "4"]))
    assert "NaN or infinite" in line and ("c.hdr" in line or "c.img" in line), line
    assert list(out.iterdir()) == []


def test_a_header_declaring_a_unit_that_is_not_a_length_is_refused(tmp_path, capsys):
    from torchskin.cli import main

    hdr = _envi_by_hand(tmp_path, HEADER.format(il="bsq", wl="wavelength units = Index\n"
                                                "wavelength = {1, 2, 3, 4}\n"), np.zeros(1600, "<f4").tobytes())
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(hdr), *CFG]))
    assert "'Index'" in line, line


def test_band_ranges_on_the_command_line():
    from torchskin.bands import expand_band_items, parse_bands
    from torchskin.io import parse_band_list

    b = parse_bands("450:1650:10")
    assert len(b) == 121 and b[0].center_nm == 450 and b[-1].center_nm == 1650 and b[60].center_nm == 1050
    assert [(x.center_nm, x.fwhm_nm) for x in parse_bands("544,1000:1020:10/5")] == \
        [(544.0, 0.0), (1000.0, 5.0), (1010.0, 5.0), (1020.0, 5.0)]
    assert parse_band_list("1580,544:548:2") == [1580.0, 544.0, 546.0, 548.0]
    assert expand_band_items("400:405:2") == ["400", "402", "404"]  # STOP off the step: not passed
    for bad in ("450:1650:0", "1650:450:10", "450:1650", "a:b:c"):
        with pytest.raises(ValueError, match="bad band range"):
            parse_bands(bad)
    with pytest.raises(ValueError, match="strictly ascending"):  # render's checks still apply
        parse_bands("450:500:10,480")
    fine = parse_bands("450.1:450.5:0.1")  # steps that are not exact in binary: STOP still reached, rounded
    assert len(fine) == 5 and math.isclose(fine[-1].center_nm, 450.5, abs_tol=1e-12)


# ---------------------------------------------------------------------------------------------------- render
@pytest.mark.parametrize("fmt", ["envi", "tiff"])
def test_render_writes_its_cubes_in_the_format_asked_and_calibrate_detect_read_them(tmp_path, capsys, fmt):
    """``render --format``: the reflectance and signal cubes with wavelengths, FWHM and units, listed in
    render.json; ``calibrate`` on the signal cube through render.json's panel regions writes the input's
    format, and ``detect`` on it finds what it finds on render's own reflectance cube."""
    pytest.importorskip("open3d")
    from torchskin.cli import main

    out = tmp_path / "r"
    assert main(["render", "--out", str(out), "--width", "48", "--height", "48", "--bands",
                 "544,633,1000:1100:40/20,1580", "--format", fmt]) == 0
    capsys.readouterr()
    doc = json.loads((out / "render.json").read_text())
    ext = {"envi": ["hdr", "img"], "tiff": ["tif"]}[fmt]
    assert doc["cubes"] == {"format": fmt, **{q: {"files": [f"{q}.{e}" for e in ext], "units": u}
                                              for q, u in (("reflectance", "1"), ("signal", "DN"))}}
    assert not (out / "reflectance.npy").exists() and all((out / f).is_file() for q in ("reflectance", "signal")
                                                          for f in doc["cubes"][q]["files"])
    bands, fwhm = [544.0, 633.0, 1000.0, 1040.0, 1080.0, 1580.0], [0.0, 0.0, 20.0, 20.0, 20.0, 0.0]
    for q in ("reflectance", "signal"):
        cf = cubefiles.open_cube(out / doc["cubes"][q]["files"][0])
        assert cf.bands == bands and cf.fwhm == fwhm and cf.shape == (6, 48, 48)
    if fmt == "envi":
        img = spectral.open_image(str(out / "signal.hdr"))
        assert img.bands.centers == bands and img.metadata["data units"] == "DN"
    regions = [doc["panels"][p]["region"] for p in ("panel_white", "panel_dark")]
    cal = tmp_path / f"cal.{ext[0]}"
    assert main(["calibrate", "--cube", str(out / doc["cubes"]["signal"]["files"][0]),
                 "--panel", "{}:{}:{}:{}=0.97".format(*regions[0]), "--panel", "{}:{}:{}:{}=0.03".format(*regions[1]),
                 "--out", str(cal)]) == 0
    capsys.readouterr()
    counts = []
    for cube in (cal, out / doc["cubes"]["reflectance"]["files"][0]):
        assert main(["detect", "--model", DET, "--cube", str(cube), "--sun-zenith", "45", "--camera-zenith", "90",
                     "--relative-azimuth", "20", "--diffuse-share", "0.17", "--clip-negative", "--json"]) == 0
        counts.append(json.loads(capsys.readouterr().out)["skin_pixels"])
    assert counts[0] > 0 and abs(counts[0] - counts[1]) <= 0.02 * counts[1] + 1, counts


def test_a_memory_mapped_frame_streamed_does_not_stay_resident(tmp_path):
    """Pages of a memory-mapped file count in the resident memory of the process that touched them: a 256 MB
    frame read and written tile by tile would end up resident whole. ``detect`` and ``calibrate`` release each
    tile's pages (``cubefiles.release_pages``): their peak resident memory on it (measured in a fresh process,
    ``ru_maxrss``) exceeds the same command's on a 1-row frame by less than a quarter of the frame."""
    import subprocess
    import sys

    H, W = 4000, 4000
    for name, h in (("big", H), ("small", 1)):
        mm = np.lib.format.open_memmap(tmp_path / f"{name}.npy", mode="w+", dtype=np.float32, shape=(4, h, W))
        for r0 in range(0, h, 500):
            mm[:, r0:r0 + 500] = 0.2
        mm.flush()
        del mm
    (tmp_path / "one.json").write_text(json.dumps({"gain": [2.0] * 4, "offset": [0.0] * 4}))
    code = ("import resource, sys; from torchskin.cli import main; rc = main(sys.argv[1:]); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024); sys.exit(rc)")

    def peak(*argv):
        r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=300,
                           cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        return int(r.stdout.split()[-1])

    frame = 4 * H * W * 4
    for name in ("detect", "calibrate"):
        def argv(cube, name=name):
            return (["detect", "--model", DET, "--cube", f"{cube}.npy", *CFG, "--out", f"{cube}.png"]
                    if name == "detect" else
                    ["calibrate", "--cube", f"{cube}.npy", "--coefficients", "one.json", "--out", f"{cube}_r.npy"])
        grown = peak(*argv("big")) - peak(*argv("small"))
        assert grown < frame / 4, (name, grown, frame)
    assert np.load(tmp_path / "big_r.npy", mmap_mode="r")[:, -1, -1].tolist() == pytest.approx([0.1] * 4, rel=1e-6)


# ------------------------------------------------------------------ review of issue 24: what the field's files hold
def test_scaled_integer_reflectance_reads_as_the_reflectance_factor(tmp_path, capsys, det):
    """An int16 product storing 10000 x the reflectance factor (ENVI 'reflectance scale factor', GDAL's per-band
    SCALE/OFFSET) gives the mask of the float cube (it was refused as 'per cent')."""
    from torchskin.cli import main

    cube = _skin_cube()
    want = int(det(cube[None], CONFIG)["mask"].sum())
    stored = np.round(cube * 10000).astype(np.int16)
    hdr = _save_envi(tmp_path / "i.hdr", stored.astype(np.float32), dtype=np.int16, wavelength=MODEL_BANDS,
                     **{"wavelength units": "nm", "reflectance scale factor": 10000})
    np.testing.assert_allclose(cubefiles.open_cube(hdr).read(), stored / 10000.0, rtol=1e-6)
    xml = cubefiles.gdal_metadata_xml(MODEL_BANDS, None).replace(
        "</GDALMetadata>", "".join(f'<Item name="SCALE" sample="{i}" role="scale">0.0001</Item>'
                                   f'<Item name="OFFSET" sample="{i}" role="offset">0.01</Item>' for i in range(4))
        + "</GDALMetadata>")
    tifffile.imwrite(str(tmp_path / "i.tif"), stored - 100, photometric="minisblack", planarconfig="separate",
                     extratags=[(cubefiles.GDAL_METADATA_TAG, 2, 0, xml, True)])
    np.testing.assert_allclose(cubefiles.open_cube(tmp_path / "i.tif").read(), (stored - 100) * 1e-4 + 0.01,
                               rtol=1e-5)
    for p in (hdr, tmp_path / "i.tif"):
        assert main(["detect", "--model", DET, "--cube", str(p), *CFG, "--json"]) == 0, capsys.readouterr()
        assert json.loads(capsys.readouterr().out)["skin_pixels"] == want == 100


def test_bands_given_on_the_command_line_stand_in_for_a_header_without_wavelengths(tmp_path, capsys, det):
    from torchskin.cli import main

    cube = _skin_cube()
    order = [2, 0, 3, 1]
    hdr = _envi_by_hand(tmp_path, HEADER.format(il="bsq", wl=""), cube[order].astype("<f4").tobytes())
    argv = ["detect", "--model", DET, "--cube", str(hdr), *CFG, "--json"]
    assert "no 'wavelength'" in _one_line(capsys, main(argv))
    assert main([*argv, "--bands", ",".join(f"{MODEL_BANDS[i]:g}" for i in order)]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100
    tifffile.imwrite(str(tmp_path / "n.tif"), cube, photometric="minisblack", planarconfig="separate")
    argv = ["detect", "--model", DET, "--cube", str(tmp_path / "n.tif"), *CFG, "--json"]
    assert "no band wavelengths" in _one_line(capsys, main(argv))
    assert main([*argv, "--bands", "544,633,1080,1580"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100


def test_an_envi_cubes_map_info_is_kept_by_an_envi_mask_and_refused_in_a_png(tmp_path, capsys, det):
    from torchskin.cli import main

    cube = _skin_cube()
    info = ["UTM", "1", "1", "500000", "4649776", "0.05", "0.05", "33", "North", "WGS-84"]
    hdr = _save_envi(tmp_path / "g.hdr", cube, wavelength=MODEL_BANDS, **{"wavelength units": "nm", "map info": info})
    out = tmp_path / "out"
    out.mkdir()
    for name in ("m.png", "m.tif"):
        line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(out / name)]))
        assert "map info" in line and ".hdr" in line, line
    assert list(out.iterdir()) == []
    assert main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(out / "m.hdr")]) == 0
    capsys.readouterr()
    img = spectral.open_image(str(out / "m.hdr"))
    assert img.metadata["map info"] == info and img.shape == (20, 20, 1) and np.dtype(img.dtype) == np.uint8
    np.testing.assert_array_equal(np.asarray(img.load())[:, :, 0], det(cube[None], CONFIG)["mask"][0].astype(np.uint8) * 255)


def test_a_data_file_a_reader_would_find_first_is_refused_as_an_envi_output(tmp_path, capsys):
    """``S.hdr`` over ``S`` (no suffix: a reader's first choice), calibrated onto ``S.hdr``, wrote ``S.img`` and a
    reflectance header that readers paired with the old signal in ``S``."""
    from torchskin.cli import main

    dn = np.full((4, 20, 20), 500.0, np.float32)
    dn[:, :4, :4], dn[:, -4:, -4:] = 9700.0, 300.0
    (tmp_path / "S.hdr").write_text(HEADER.format(il="bsq", wl=WL_NM))
    (tmp_path / "S").write_bytes(dn.astype("<f4").tobytes())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    line = _one_line(capsys, main(["calibrate", "--cube", str(tmp_path / "S.hdr"), "--panel", "0:4:0:4=0.97",
                                   "--panel", "16:20:16:20=0.03", "--out", str(tmp_path / "S.hdr")]))
    assert "would be read as its data file" in line, line
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


@pytest.mark.parametrize("fmt", ["envi", "npy"])
def test_an_interrupted_header_write_leaves_the_old_cube_and_header_paired(tmp_path, monkeypatch, fmt):
    import pathlib

    old = np.zeros((4, 3, 5), np.float32)
    p = cubefiles.write_cube(tmp_path / ("r.hdr" if fmt == "envi" else "r.npy"), old, fmt, MODEL_BANDS)
    before = {f.name: f.read_bytes() for f in tmp_path.iterdir()}
    real = pathlib.Path.write_text

    def interrupted(self, *a, **k):
        if self.name.startswith("."):  # the header's or sidecar's temporary file
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(pathlib.Path, "write_text", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cubefiles.write_cube(p, np.ones((4, 3, 5), np.float32), fmt, [500.0, 600.0, 700.0, 800.0])
    assert {f.name: f.read_bytes() for f in tmp_path.iterdir()} == before


def test_a_batch_of_npy_frames_synthesises_the_models_bands_as_one_frame_does(tmp_path, capsys):
    from torchskin.cli import main

    lam = np.arange(450.0, 1651.0, 10.0)
    spec = np.interp(lam, MODEL_BANDS, SKIN).astype(np.float32)
    one = np.broadcast_to(spec[:, None, None], (len(lam), 6, 6)).copy()
    one[:, :2] = 0.2
    res = []
    for name, arr in (("one.npy", one), ("batch.npy", np.stack([one, one]))):
        _save_npy(tmp_path / name, arr, lam)
        assert main(["detect", "--model", DET, "--cube", str(tmp_path / name), *CFG, "--json"]) == 0
        res.append(json.loads(capsys.readouterr().out))
    assert res[1]["skin_pixels"] == 2 * res[0]["skin_pixels"] > 0


@pytest.mark.parametrize("units,ok", [("Nanometre", True), ("Micrometres", True), ("Millimetres", True),
                                      ("Wavenumber", False)])
def test_british_spellings_of_the_wavelength_units_are_read(units, ok):
    scale = {"Nanometre": 1.0, "Micrometres": 1e3, "Millimetres": 1e6}
    if ok:
        assert cubefiles.units_scale(units, "x") == scale[units]
        assert cubefiles.to_nm([400.0], units, "x") == [400.0 * scale[units]]
    else:
        with pytest.raises(ValueError, match="Wavenumber"):
            cubefiles.units_scale(units, "x")


@pytest.mark.parametrize("fwhm", ["{nan, 10, 10, 10}", "{-1, 10, 10, 10}"])
def test_a_header_fwhm_that_is_not_a_width_is_refused(tmp_path, capsys, fwhm):
    from torchskin.cli import main

    hdr = _envi_by_hand(tmp_path, HEADER.format(il="bsq", wl=WL_NM + f"fwhm = {fwhm}\n"),
                        _skin_cube().astype("<f4").tobytes())
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(hdr), *CFG]))
    assert "fwhm" in line, line


def test_max_megapixels_caps_a_compressed_geotiff_and_must_be_positive(tmp_path, capsys):
    from torchskin.cli import main

    tifffile.imwrite(str(tmp_path / "z.tif"), _skin_cube(), photometric="minisblack", planarconfig="separate",
                     compression="zlib", extratags=[(cubefiles.GDAL_METADATA_TAG, 2, 0,
                                                     cubefiles.gdal_metadata_xml(MODEL_BANDS, None), True)])
    argv = ["detect", "--model", DET, "--cube", str(tmp_path / "z.tif"), *CFG]
    assert main(argv) == 0
    capsys.readouterr()
    assert "above the cap of 0.0001" in _one_line(capsys, main([*argv, "--max-megapixels", "0.0001"]))
    for bad in ("0", "-1", "nan"):
        assert "--max-megapixels" in _one_line(capsys, main([*argv, "--max-megapixels", bad]))
