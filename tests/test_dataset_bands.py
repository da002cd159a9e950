"""Datasets in any band set (issue 39, "bands as data"): ``generate --bands`` and the config's ``[bands]`` write one
reflectance column per band and record the set in the manifest; readers take the band columns from it (the index
bands for datasets that do not record one); detector kinds refuse a dataset without the bands they need."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from torchskin.bands import INDEX_BANDS, BandSet
from torchskin.cli import main
from torchskin.dataset.files import MANIFEST, dataset_bands, read_rows

FIVE = "500,544/10,633,1080,1300"  # the NDGRI pair, no 1580 nm: NDSI and the 1580 nm direct share are undefined


def small_toml(tmp_path, subject_obj, extra=""):
    """A config of one sun and one skin a pose group, 48 x 48 frames, 8 pixels a class: a second a group."""
    p = tmp_path / "small.toml"
    p.write_text('[camera]\nwidth = 48\nheight = 48\nrange_m = [5.0, 10.0]\n[sun]\nper_pose = 1\nzenith_deg = '
                 '[20.0, 40.0]\n[skin]\nper_pose = 1\n[confusers]\ncount = [1, 1]\n'
                 f'[subject]\nmeshes = ["{subject_obj}"]\n[sampling]\ngroups_per_shard = 1\npixels_per_class = 8\n'
                 + extra)
    return p


def generate(tmp_path, subject_obj, name, *extra, config_extra=""):
    out = tmp_path / name
    cfg = small_toml(tmp_path, subject_obj, config_extra)
    assert main(["generate", "--config", str(cfg), "--configs", "1", "--seed", "3", "--quiet", "--out", str(out),
                 *extra]) == 0
    return out


@pytest.fixture(scope="module")
def five(tmp_path_factory, subject_obj):
    return generate(tmp_path_factory.mktemp("five"), subject_obj, "five", "--bands", FIVE)


def test_a_121_band_range_writes_a_column_per_band_named_in_the_manifest(tmp_path, subject_obj):
    d = generate(tmp_path, subject_obj, "wide", "--bands", "450:1650:10")
    bands = BandSet.parse("450:1650:10")
    names = pq.read_schema(d / "shard-00000.parquet").names
    refl = [c for c in names if c.startswith("r") and c[1:].replace(".", "").isdigit()]
    assert len(bands) == 121 and tuple(refl) == bands.columns
    man = json.loads((d / MANIFEST).read_text())
    assert BandSet.from_json(man["bands"]) == bands == dataset_bands(d)
    assert [c for c in man["columns"] if c in refl] == list(bands.columns) and list(man["columns"]) == names
    assert man["config"]["panels"]["kinds"] == ["lambertian"]  # Spectralon's table covers the index bands only
    t = pq.read_table(d / "shard-00000.parquet")
    # 540 and 630 nm are not the 544 and 633 nm the columns name: undefined, never a value of other bands
    for c in ("ndgri", "sky_fraction", "atmosphere_transmittance", "direct_share_544"):
        assert np.isnan(t.column(c).to_numpy()).all(), c
        assert "NaN: the bands lack" in man["columns"][c]["description"]
    assert np.isfinite(t.column("ndsi").to_numpy()).any() and np.isfinite(t.column("direct_share_1580").to_numpy()).all()
    assert main(["dataset", "verify", str(d)]) == 0


def test_a_five_band_set_end_to_end_through_read_rows(five):
    bands = dataset_bands(five)
    assert bands == BandSet.parse(FIVE) and bands.columns == ("r500", "r544", "r633", "r1080", "r1300")
    rows = read_rows(five, [*bands.columns, "ndgri", "ndsi", "direct_share_544", "direct_share_1580", "label"],
                     frames="line")
    assert len(rows) > 0 and rows.band_set == bands
    assert rows.stack(bands.columns).shape == (len(rows), 5)
    ok = np.isfinite(rows["ndgri"])
    assert ok.any()
    np.testing.assert_allclose(rows.nd(544, 633)[ok], rows["ndgri"][ok], atol=1e-6)  # the stored one, from r544/r633
    assert np.isnan(rows["ndsi"]).all() and np.isnan(rows["direct_share_1580"]).all()
    assert np.isfinite(rows["direct_share_544"]).all()
    with pytest.raises(ValueError, match="no band within 2 nm of 1580 nm"):
        rows.nd(1080, 1580)


@pytest.mark.parametrize("command", [["train", "--method", "boxes"], ["train", "--method", "classifier"],
                                     ["evaluate", "--model", "MODEL"], ["evaluate", "--model", "static"]])
def test_a_kind_refuses_a_dataset_without_its_bands_in_one_line(five, tmp_path, tmp_path_factory, capsys, command):
    from torchskin.detectors import registry
    from torchskin.detectors.boxes import BoxModel

    model = tmp_path_factory.mktemp("model") / "untrained.pt"
    registry.save(BoxModel(), model)  # a boxes checkpoint: its kind's required_bands are the index bands
    out = tmp_path / "model.pt"
    args = [command[0], "--data", str(five), *[str(model) if a == "MODEL" else a for a in command[1:]]]
    args += ["--out", str(out)] if command[0] == "train" else ["--save", str(tmp_path / "e.json")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"torchskin {command[0]}: error: dataset {str(five)!r} lacks the 1580 nm")
    who = {"MODEL": "--model untrained.pt", "static": "the static thesis box"}.get(command[-1], f"--method {command[-1]}")
    assert f"band that {who} needs (its bands: 500, 544, 633, 1080, 1300 nm)" in err
    assert list(tmp_path.iterdir()) == []  # wrote nothing


def test_the_index_bands_by_name_by_config_or_by_default_are_the_same_bytes(tmp_path, subject_obj):
    by_default = generate(tmp_path, subject_obj, "default")
    named = generate(tmp_path, subject_obj, "named", "--bands", "544,633,1080,1580")
    configured = generate(tmp_path, subject_obj, "configured", config_extra='[bands]\nspec = "544,633,1080,1580"\n')
    for d in (named, configured):
        for f in (MANIFEST, "shard-00000.parquet"):
            assert (d / f).read_bytes() == (by_default / f).read_bytes(), (d, f)
    # a dataset whose manifest records no band set (written before --bands) is read in the index bands
    man = json.loads((by_default / MANIFEST).read_text())
    del man["bands"]
    (by_default / MANIFEST).write_text(json.dumps(man))
    assert dataset_bands(by_default) == INDEX_BANDS
    assert read_rows(by_default, INDEX_BANDS.columns).band_set == INDEX_BANDS


@pytest.mark.parametrize("extra, config_extra, message", [
    (["--bands", "544,abc"], "", "bad band 'abc' in --bands"),
    ([], '[bands]\nspec = "544,abc"\n', "bad band 'abc' in bands.spec"),
    ([], "[bands]\nspec = 544\n", "bands.spec must be a band list in the --bands syntax"),
    (["--bands", "450,544"], '[panels]\nkinds = ["spectralon"]\n', "panels.kinds ['spectralon'] with bands.spec"),
])
def test_bad_band_sets_are_refused_in_one_line(tmp_path, subject_obj, capsys, extra, config_extra, message):
    cfg = small_toml(tmp_path, subject_obj, config_extra)
    out = tmp_path / "out"
    assert main(["generate", "--config", str(cfg), "--configs", "1", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err and not out.exists()
