"""Reading cubes and writing masks live in one place: ``cubefiles.open_npy`` reads every ``.npy`` cube (one frame
for ``open_cube``, frames for ``onboard.load_cube``) with the union of their checks, and ``onboard.write_mask``
writes a whole mask through the row writers a streamed frame's mask goes through (``onboard.stream._mask_writer``)."""

import json

import numpy as np
import pytest

from torchskin.cubefiles import open_cube, read_png_gray
from torchskin.onboard import load_cube, write_mask


def cut_short(path, shape) -> None:
    """A ``.npy`` whose header promises ``shape`` float32 but which holds half of the data."""
    np.save(path, np.zeros(shape, dtype=np.float32))
    data = path.read_bytes()
    path.write_bytes(data[:len(data) - 2 * int(np.prod(shape))])


@pytest.mark.parametrize("shape", [(4, 10, 12), (2, 4, 10, 12)])
def test_load_cube_refuses_a_truncated_file_from_its_header_as_open_cube_does(tmp_path, shape):
    p = tmp_path / "c.npy"
    cut_short(p, shape)
    with pytest.raises(ValueError, match=r"--cube '.*c\.npy' is truncated: .* float32 " + " x ".join(map(str, shape))):
        load_cube(p)
    if len(shape) == 3:
        with pytest.raises(ValueError, match="is truncated"):
            open_cube(p)


def test_load_cube_and_open_cube_read_the_same_values(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.random((4, 9, 7)).astype(">f8")  # big-endian float64: converted alike
    np.save(tmp_path / "c.npy", x)
    a, b = load_cube(tmp_path / "c.npy"), open_cube(tmp_path / "c.npy").read()
    assert a.dtype == b.dtype == np.float32 and np.array_equal(a, b) and np.array_equal(a, x.astype(np.float32))
    for bad, words in ((np.zeros((0, 3), np.float32), "is empty"), (np.array(["a", "b"]), "must hold numbers")):
        np.save(tmp_path / "bad.npy", bad)
        with pytest.raises(ValueError, match=words):
            load_cube(tmp_path / "bad.npy")
    np.save(tmp_path / "big.npy", np.zeros((2, 4, 30, 40), np.float32))
    with pytest.raises(ValueError, match="above the cap of 0.001"):
        load_cube(tmp_path / "big.npy", max_megapixels=0.001)


def test_write_mask_writes_png_and_geotiff_through_the_row_writers(tmp_path):
    rng = np.random.default_rng(1)
    mask = rng.random((13, 17)) > 0.5
    write_mask(tmp_path / "m.png", mask)
    assert np.array_equal(read_png_gray(tmp_path / "m.png"), mask.astype(np.uint8) * 255)
    tifffile = pytest.importorskip("tifffile")
    write_mask(tmp_path / "m.tif", mask)
    assert np.array_equal(tifffile.imread(tmp_path / "m.tif"), mask.astype(np.uint8) * 255)
    with pytest.raises(ValueError, match="must be a .png, .tif or ENVI .hdr mask"):
        write_mask(tmp_path / "m.jpg", mask)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        write_mask(tmp_path / "m.png", mask[None])
    assert sorted(f.name for f in tmp_path.iterdir()) == ["m.png", "m.tif"]


def test_a_batch_and_a_streamed_frame_write_the_same_mask(tmp_path, capsys):
    """``torchskin detect`` on a (1, 4, H, W) batch (read whole, ``write_mask_png``) and on the same frame
    (bands, H, W) streamed in row tiles (``detect_file``): the same mask file content."""
    from torchskin.cli import main

    rng = np.random.default_rng(2)
    cube = (rng.random((4, 40, 30)) * 0.6).astype(np.float32)
    import torch

    from torchskin import tissue  # the Type I/II preset's reflectance in the index bands: a skin spectrum

    skin = tissue.reflectance(tissue.preset("I-II"), torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64))
    cube[:, 10:30, 5:25] = skin.reshape(4).float().numpy()[:, None, None]
    np.save(tmp_path / "one.npy", cube)
    np.save(tmp_path / "batch.npy", cube[None])
    cfg = ["--sun-zenith", "30", "--camera-zenith", "10", "--relative-azimuth", "90", "--diffuse-share", "0.2"]
    for name in ("one", "batch"):
        assert main(["detect", "--cube", str(tmp_path / f"{name}.npy"), *cfg, "--out", str(tmp_path / f"{name}.png"),
                     "--tile-rows", "7", "--json"]) == 0
        assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["skin_pixels"] > 300
    a, b = read_png_gray(tmp_path / "one.png"), read_png_gray(tmp_path / "batch.png")
    assert a.shape == (40, 30) and np.array_equal(a, b) and (a[10:30, 5:25] == 255).all()
