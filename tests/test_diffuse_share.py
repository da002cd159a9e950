"""The diffuse share, the lut kind's fourth configuration feature (issue 40, haze): what a shaded and a sunlit
horizontal panel measure, derived from the dataset's sky_fraction column, and its place in detect and evaluate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchskin.dataset.rows import sky_fraction
from torchskin.detectors.features import DIFFUSE_SHARE, diffuse_share, feature_columns, stack_features
from torchskin.render.light import light_tables
from torchskin.render.scene import Atmosphere, Sun

ZENITHS = (10.0, 40.0, 65.0, 80.0)


def _shares(aod: float) -> tuple[np.ndarray, np.ndarray]:
    """(from the dataset's columns, from the light tables directly) at 544 nm under aerosol ``aod``."""
    suns = [Sun(zenith_deg=z, atmosphere=Atmosphere(aerosol_500nm=aod)) for z in ZENITHS]
    t = light_tables("spectrl2", suns, [[544, 0]])
    direct = t.direct_horizontal[:, 0].numpy()
    diffuse = t.diffuse_horizontal[:, 0].numpy()
    return diffuse_share(sky_fraction(t, list(ZENITHS)), ZENITHS), diffuse / (diffuse + direct)


def test_the_share_from_the_columns_is_diffuse_over_global_horizontal_irradiance():
    """sky_fraction (D / B_normal) and the sun zenith give D / (D + B_normal cos z): what E_shade / E_sun of two
    horizontal panels reads, float32-exact."""
    for aod in (0.05, 0.4, 1.0):
        got, want = _shares(aod)
        np.testing.assert_allclose(got, want, rtol=2e-6)


def test_haze_and_a_low_sun_raise_the_share():
    clear, _ = _shares(0.05)
    hazy, _ = _shares(1.0)
    assert ((clear > 0) & (hazy < 1)).all()
    assert (hazy > clear + 0.05).all()  # more of the light comes from the sky under haze
    assert (np.diff(clear) > 0).all() and (np.diff(hazy) > 0).all()  # and as the sun sinks


def test_no_direct_light_is_a_share_of_one_and_an_unrecorded_share_stays_undefined():
    got = diffuse_share([0.3, 0.3, 0.0, np.nan], [90.0, 95.0, 30.0, 30.0])
    assert got[:3].tolist() == [1.0, 1.0, 0.0] and np.isnan(got[3])


def test_a_camera_without_544_nm_trains_on_the_angles_and_is_not_judged_on_a_share(tiny_dataset, tmp_path, capsys):
    """sky_fraction is recorded at 544 nm only: a five-band silicon camera's lut takes the angles (and says so);
    a model that takes the share cannot be judged on that dataset (one line, not a guess)."""
    from conftest import tiny_generate

    from torchskin.cli import main
    from torchskin.detectors import registry

    ds = tiny_generate(tmp_path, "475/32,560/27,668/14,717/12,842/57")
    assert main(["train", "--data", str(ds), "--method", "lut", "--bins", "5", "--trees", "10",
                 "--out", str(tmp_path / "cam.pt")]) == 0
    assert "no diffuse share" in capsys.readouterr().out
    model, _ = registry.load(tmp_path / "cam.pt")
    assert DIFFUSE_SHARE not in model.features and model.levels.shape[0] == 72
    from torchskin.evaluation import evaluate

    assert main(["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "5", "--trees", "10",
                 "--out", str(tmp_path / "sky.pt")]) == 0
    (tmp_path / "off").mkdir()
    off = tiny_generate(tmp_path / "off", "549,638,1085,1585")  # every filter 5 nm long: no 544 nm band
    with pytest.raises(ValueError, match="does not record diffuse_share"):
        evaluate(off, [str(tmp_path / "sky.pt")], positional_bands=True)


def test_derived_features_read_their_source_columns():
    from torchskin.dataset.schema import Rows

    assert feature_columns(["sun_zenith_deg", DIFFUSE_SHARE]) == ["sun_zenith_deg", "sky_fraction"]
    rows = Rows({"sun_zenith_deg": np.array([60.0, 0.0], np.float32), "sky_fraction": np.array([0.5, 1.0], np.float32)},
                0)
    X = stack_features(rows, [DIFFUSE_SHARE, "sun_zenith_deg"])
    np.testing.assert_allclose(X, [[0.5, 60.0], [0.5, 0.0]], rtol=1e-6)
    assert X.dtype == np.float32


def test_lut_models_take_the_share_unless_told_not_to(tiny_dataset, tmp_path):
    """The default lut table has a slice per diffuse-share bin, and evaluate judges it beside a box model (three
    features) on the same rows; --no-diffuse-share gives the sun-and-camera table."""
    from torchskin.cli import main
    from torchskin.detectors import registry
    from torchskin.evaluation import evaluate

    base = ["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "6", "--trees", "10"]
    assert main([*base, "--out", str(tmp_path / "sky.pt")]) == 0
    assert main([*base, "--no-diffuse-share", "--out", str(tmp_path / "angles.pt")]) == 0
    sky, ck = registry.load(tmp_path / "sky.pt")
    angles, _ = registry.load(tmp_path / "angles.pt")
    assert sky.features[-1] == DIFFUSE_SHARE and ck["meta"]["options"]["diffuse_share"] is True
    assert sky.levels.shape[0] == 4 * angles.levels.shape[0] and DIFFUSE_SHARE not in angles.features
    # the share picks the slice: the same pixels under a clear and a hazy sky fall in different slices
    X = torch.tensor([[30.0, 30.0, 30.0, 0.1], [30.0, 30.0, 30.0, 0.9]])
    s = sky.slices(X)
    assert int(s[1]) - int(s[0]) == 3
    res = evaluate(tiny_dataset, [str(tmp_path / "sky.pt"), str(tmp_path / "angles.pt")])
    assert [m["features"] for m in res["models"]][:2] == [list(sky.features), list(angles.features)]
    assert res["models"][-1]["kind"] == "static"


def test_detect_needs_the_share_of_a_model_that_takes_it_and_refuses_per_cent(tiny_dataset, tmp_path, capsys):
    from torchskin.cli import main

    assert main(["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "6", "--trees", "10",
                 "--out", str(tmp_path / "sky.pt")]) == 0
    assert main(["export", "--model", str(tmp_path / "sky.pt"), "--out", str(tmp_path / "ex")]) == 0
    cube = tmp_path / "cube.npy"
    np.save(cube, np.full((4, 8, 8), 0.3, np.float32))
    args = ["detect", "--model", str(tmp_path / "ex" / "detector.onnx"), "--cube", str(cube), "--sun-zenith", "30",
            "--camera-zenith", "20", "--relative-azimuth", "40", "--out", str(tmp_path / "mask.png")]
    capsys.readouterr()
    assert main(args) == 2
    assert "--diffuse-share" in capsys.readouterr().err
    assert main([*args, "--diffuse-share", "25"]) == 2
    assert "must lie in [0, 1]" in capsys.readouterr().err and not (tmp_path / "mask.png").exists()
    assert main([*args, "--diffuse-share", "0.25"]) == 0
    assert (tmp_path / "mask.png").is_file()
