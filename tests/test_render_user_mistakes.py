"""Wrong answers that exited 0 (issue 43), each phrased as the user's mistake: the right answer now, or one line
``torchskin <command>: error: ...`` naming the parameter, exit status 2, nothing written."""

import json

import numpy as np
import pytest

from torchskin.bands import INDEX_BANDS_NM, as_bands
from torchskin.cli import main


@pytest.fixture
def ball(tmp_path):
    """A small sphere subject (all skin) 1 m above the ground: a frame renders in a fraction of a second."""
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.3, 2)
    p = tmp_path / "ball.obj"
    write_obj(p, v + [0.0, 0.0, 1.0], f)
    return p


def frame(ball, out, *extra):
    return ["render", "--mesh", str(ball), "--out", str(out), "--width", "16", "--height", "16", "--no-ground",
            *extra]


def test_four_bands_other_than_the_index_bands_take_the_builtin_spectra_by_wavelength():
    """`torchskin render --bands 450,550,650,750`: the clothing, ground and sensor spectra built in at 544, 633,
    1080 and 1580 nm were handed out in order, so the 750 nm band got the 1580 nm values (clothing 0.30 where
    it is 0.17 between 633 and 1080 nm). Each is interpolated in wavelength now, whatever the number of bands."""
    import torch

    from torchskin.render.materials import compile_materials
    from torchskin.render.scene import default_scene
    from torchskin.render.sensor import Sensor

    bands = [[450.0, 0.0], [550.0, 0.0], [650.0, 0.0], [750.0, 0.0]]
    centres = [b[0] for b in bands]
    sc = default_scene(subject="file", mesh_path="ball.obj", illumination="thesis")
    tables = compile_materials(sc.materials, bands, sc.suns, dtype=torch.float64)
    at_index = compile_materials(sc.materials, [[c, 0.0] for c in INDEX_BANDS_NM], sc.suns, dtype=torch.float64)
    for name in ("clothing", "ground"):
        k = tables.names.index(name)
        index_values = at_index.reference[k].tolist()  # the spectrum as written, at the index bands
        assert tables.reference[k].tolist() == pytest.approx(np.interp(centres, INDEX_BANDS_NM, index_values)), name
    sensor = Sensor()
    got = sensor.tables(as_bands(bands), torch.float64, "cpu")
    at_index_sensor = sensor.tables(as_bands(INDEX_BANDS_NM), torch.float64, "cpu")
    for key in ("qe", "tau", "path"):
        want = np.interp(centres, INDEX_BANDS_NM, at_index_sensor[key].tolist())
        assert got[key].tolist() == pytest.approx(want), key


def test_rendering_into_a_folder_that_is_not_empty_needs_overwrite(tmp_path, ball, capsys):
    """`torchskin render --out DIR` into a DIR that already holds a render replaced it without a word, where
    `generate` refuses; now it is one line naming --out, exit 2, the folder untouched. With --overwrite the new
    render replaces the earlier one's files (here its .npy cubes, for ENVI ones) and keeps the user's own."""
    out = tmp_path / "frame"
    assert main(frame(ball, out, "--illumination", "thesis")) == 0
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(frame(ball, out, "--illumination", "thesis", "--source-zenith", "20")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchskin render: error: --out") and "--overwrite" in err[0], err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main(frame(ball, out, "--illumination", "thesis", "--format", "envi", "--overwrite")) == 0
    names = {p.name for p in out.iterdir()}
    assert {"reflectance.hdr", "signal.img", "render.json", "notes.txt"} <= names
    assert not names & {"reflectance.npy", "signal.npy", "reflectance.bands.json"}  # the earlier render's cubes
    assert json.loads((out / "render.json").read_text())["cubes"]["format"] == "envi"


def test_an_empty_band_list_is_an_error_not_the_default_bands(tmp_path, monkeypatch, capsys):
    """`--bands ""` (an unset shell variable, say) silently meant the default bands; every command that takes
    --bands now refuses it in one line naming --bands, exit 2, before anything is written."""
    import argparse

    from torchskin.cli.parser import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    commands = [n for n, p in sub.choices.items() if any("--bands" in a.option_strings for a in p._actions)]
    assert {"render", "light", "spectra", "detect"} <= set(commands)
    monkeypatch.chdir(tmp_path)
    for name in commands:
        for argv in ([name, "--bands", ""], [name, "--bands=  "]):
            assert main(argv) == 2, argv
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith(f"torchskin {name}: error:") and "--bands" in err[0], (argv, err)
    assert list(tmp_path.iterdir()) == []


def test_the_thesis_lamp_records_no_atmosphere_it_did_not_use(tmp_path, ball, subject_obj):
    """Under `--illumination thesis` (a blackbody lamp and a grey sky: no atmosphere), render.json and the
    dataset's rows recorded an aerosol, water, ozone, pressure and day of year that shaped nothing. They are
    empty now (render.json: null; rows: NaN, day_of_year 0) and recorded as used under spectrl2."""
    for model in ("thesis", "spectrl2"):
        out = tmp_path / model
        assert main(frame(ball, out, "--illumination", model, "--aerosol", "0.3", "--day-of-year", "40")) == 0
        atm = [s["atmosphere"] for s in json.loads((out / "render.json").read_text())["scene"]["suns"]]
        if model == "thesis":
            assert atm == [None]
        else:
            assert atm[0]["aerosol_500nm"] == 0.3 and atm[0]["day_of_year"] == 40
    from torchskin.dataset.config import LIGHT_ATMOSPHERE, resolve_config, sample_group
    from torchskin.dataset.generate import group_rows

    for model in ("thesis", "spectrl2"):
        cfg = resolve_config({"camera": {"width": 16, "height": 16}, "subject": {"meshes": [str(subject_obj)]},
                              "sun": {"per_pose": 1}, "skin": {"per_pose": 1}, "confusers": {"count": [0, 0]},
                              "sampling": {"pixels_per_class": 4}, "light": {"model": model}})
        g = sample_group(cfg, 0, 0)
        rows = {k: np.concatenate(v) for k, v in group_rows(g, 4).items() if k in LIGHT_ATMOSPHERE}
        assert len(rows["day_of_year"]) > 0
        if model == "thesis":
            assert all(np.isnan(rows[k]).all() for k in LIGHT_ATMOSPHERE if k != "day_of_year")
            assert (rows["day_of_year"] == 0).all()  # no day of year (generate.NO_DAY_OF_YEAR)
        else:  # the drawn atmosphere, as the light used it
            assert all(np.allclose(rows[k], g.light[k]) for k in LIGHT_ATMOSPHERE)
