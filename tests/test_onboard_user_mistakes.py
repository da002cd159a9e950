"""User mistakes ``torchskin detect`` must refuse rather than detect through (issue 43): a plausible reflectance
cube with one absurd value (1e30, 1e6: a corrupt write, a fill value) used to exit 0, admitted as a glint by the
1 % share of values allowed above ``REFLECTANCE_MAX``. No camera records more than about 16 times the white
panel's reflectance (a saturated pixel), so one value above ``REFLECTANCE_CEILING`` refuses the cube on every
path: the command line (streamed in row tiles, or a batch read whole), the detector's tiled path in memory, and
an ENVI file; exit status 2, one line naming the file and the value, nothing written. A glint (5.0) and a value
just under the bound still pass."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from torchskin.cli import main
from torchskin.onboard import REFLECTANCE_CEILING, REFLECTANCE_MAX, OnboardDetector

DET = str(Path(__file__).resolve().parents[1] / "exports" / "detector.onnx")
CFG = ["--sun-zenith", "40", "--camera-zenith", "30", "--relative-azimuth", "60", "--diffuse-share", "0.2"]  # the shipped lut takes the share
BANDS = [544.0, 633.0, 1080.0, 1580.0]
BAD = pytest.mark.parametrize("value", [1e30, 1e6], ids=["1e30", "1e6"])
GLINT = pytest.mark.parametrize("value", [5.0, 49.0], ids=["glint 5", "just under the bound"])
PLACE = (2, 60, 61)  # a value of the last rows (the last row tile) and of a tile past the first


def _cube(value=None, frames=None):
    """A plausible 4 x 64 x 64 float32 reflectance cube (values 0.05-0.6), one value set to ``value``;
    ``frames``: a (frames, 4, 64, 64) batch of it."""
    cube = np.random.default_rng(43).uniform(0.05, 0.6, (4, 64, 64)).astype(np.float32)
    if value is not None:
        cube[PLACE] = value
    return cube if frames is None else np.stack([cube] * frames)


def _save(path, cube):
    """``cube`` as ``path`` (.npy) with its wavelength sidecar, as ``render`` and ``calibrate`` write them."""
    np.save(path, cube)
    (path.parent / (path.stem + ".bands.json")).write_text(json.dumps({"bands_nm": BANDS, "units": "nm",
                                                                       "quantity": "reflectance"}))
    return path


def _refused(capsys, rc, value, name=None):
    """The one error line: status 2, nothing on stdout, the value and the bound in it (and the file's ``name``)."""
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and out == "" and len(lines) == 1, (rc, out, err)
    line = lines[0]
    assert line.startswith("torchskin detect: error:") and f"{value:.4g}" in line, line
    assert f"refused above {REFLECTANCE_CEILING:g}" in line and "no camera" in line, line
    assert name is None or name in line, line
    return line


@BAD
@pytest.mark.parametrize("tiles", [[], ["--tile-rows", "8"]], ids=["one tile", "8 row tiles"])
def test_detect_refuses_a_reflectance_cube_with_one_absurd_value(tmp_path, capsys, value, tiles):
    """One value of 1e30 (or 1e6) among 16,384 plausible ones: refused naming the file and the value, the mask
    not written, whether the frame streams as one tile or eight."""
    cube = _save(tmp_path / "refl.npy", _cube(value))
    mask = tmp_path / "mask.png"
    rc = main(["detect", "--model", DET, "--cube", str(cube), *CFG, "--out", str(mask), *tiles])
    _refused(capsys, rc, value, "refl.npy")
    assert not mask.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["refl.bands.json", "refl.npy"]  # no temporary left


@BAD
def test_detect_refuses_a_batch_with_one_absurd_value(tmp_path, capsys, value):
    """A (frames, bands, H, W) .npy is read whole and run in memory: the same refusal."""
    cube = _save(tmp_path / "batch.npy", _cube(value, frames=2))
    mask = tmp_path / "mask.png"
    _refused(capsys, main(["detect", "--model", DET, "--cube", str(cube), *CFG, "--out", str(mask)]), value)
    assert not mask.exists()


@BAD
@pytest.mark.parametrize("tile", [1024, 65536], ids=["tiled", "one call"])
def test_the_detector_refuses_one_absurd_value_in_memory(value, tile):
    """``OnboardDetector`` on the frame in memory: tile by tile in two threads (the tile's one-pass bit test
    fails, its full check finds the value) and in one call alike; with ``negative="clip"`` too."""
    det = OnboardDetector(DET, threads=2, tile=tile)
    for negative in ("error", "clip"):
        with pytest.raises(ValueError, match=re.escape(f"reads reflectance {value:.4g}, which no camera records")):
            det(_cube(value)[None], [40.0, 30.0, 60.0, 0.2], negative=negative)


@BAD
def test_detect_refuses_an_envi_cube_with_one_absurd_value(tmp_path, capsys, value):
    """The same mistake in an ENVI file (streamed from its memory map): refused, no mask written."""
    spectral = pytest.importorskip("spectral")
    hdr = tmp_path / "refl.hdr"
    spectral.envi.save_image(str(hdr), np.transpose(_cube(value), (1, 2, 0)), interleave="bsq", dtype=np.float32,
                             force=True, metadata={"wavelength": BANDS, "wavelength units": "Nanometers"})
    mask = tmp_path / "mask.png"
    rc = main(["detect", "--model", DET, "--cube", str(hdr), *CFG, "--out", str(mask), "--tile-rows", "16"])
    _refused(capsys, rc, value, str(tmp_path / "refl."))  # its data file, refl.img
    assert not mask.exists()


@GLINT
def test_a_glint_still_passes_every_path(tmp_path, capsys, value):
    """A glint of 5.0 (water, glass in the sun), or a value just under the bound, in one value of a plausible
    cube: detected on the streamed path (one tile and eight), the batch path and the detector's tiled path, its
    other pixels as without it."""
    assert REFLECTANCE_MAX < value < REFLECTANCE_CEILING
    config = [40.0, 30.0, 60.0, 0.2]
    clean = OnboardDetector(DET)(_cube()[None], config)["mask"][0]
    for tiles in ([], ["--tile-rows", "8"]):
        cube = _save(tmp_path / "refl.npy", _cube(value))
        assert main(["detect", "--model", DET, "--cube", str(cube), *CFG, "--out", str(tmp_path / "m.png"),
                     "--json", *tiles]) == 0
        assert (tmp_path / "m.png").is_file()
        assert json.loads(capsys.readouterr().out)["shape"] == [1, 64, 64]
    batch = _save(tmp_path / "batch.npy", _cube(value, frames=2))
    assert main(["detect", "--model", DET, "--cube", str(batch), *CFG, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["shape"] == [2, 64, 64]
    mask = OnboardDetector(DET, threads=2, tile=1024)(_cube(value)[None], config)["mask"][0]
    mask[PLACE[1:]] = clean[PLACE[1:]]  # the glint's own pixel may change its verdict, no other
    assert (mask == clean).all()
