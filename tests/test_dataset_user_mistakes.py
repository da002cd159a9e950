"""Datasets and training: wrong answers that exited 0 (issue 43). Each test is a user's mistake, or a user
trusting the output, that used to pass without a word; now it gets the right answer or one line naming the
parameter or file (exit status 2 for bad input, 1 for a failure of the work), and nothing is written."""

import json
import shutil

import numpy as np
import pytest
from conftest import rows_with_pixels  # a row's frame pixel

from torchskin.cli import main
from torchskin.dataset.config import resolve_config

pytestmark = pytest.mark.slow  # the module's dataset takes seconds to render


@pytest.fixture(scope="module")
def dataset(subject_obj, tmp_path_factory):
    """A small dataset with its cubes (``--images``) and the sensor's noise on (the default): 2 pose groups of
    3 suns x 2 skins, 16 skin and 16 other pixels each, 64 x 48 frames."""
    from torchskin.dataset.generate import generate

    cfg = resolve_config({"camera": {"width": 64, "height": 48, "range_m": [5.0, 20.0]}, "sun": {"per_pose": 3},
                          "skin": {"per_pose": 2}, "subject": {"meshes": [str(subject_obj)]},
                          "sampling": {"groups_per_shard": 1, "pixels_per_class": 16},
                          "confusers": {"count": [2, 3]}})
    assert cfg["sensor"]["noise"]
    d = tmp_path_factory.mktemp("ds") / "data"
    generate(cfg, 12, 3, d, quiet=True, images=True)
    return d, cfg


def _line(capsys, status, want):
    """The command's one line on stderr (nothing on stdout), after checking its exit status."""
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert status == want and out == "" and len(lines) == 1, (status, out, err)
    return lines[0]


READERS = {
    "evaluate": lambda d, w: main(["evaluate", "--data", str(d), "--model", "static", "--save", str(w / "r.json")]),
    "train": lambda d, w: main(["train", "--data", str(d), "--out", str(w / "m.pt"), "--steps", "5"]),
    "dataset verify": lambda d, w: main(["dataset", "verify", str(d)]),
    # what examples/dataset_with_pandas.py reads the folder with (its pandas read follows the same check)
    "open_dataset": None,
}


@pytest.mark.parametrize("reader", list(READERS))
def test_a_dataset_of_a_newer_schema_is_refused_by_every_reader(dataset, tmp_path, capsys, reader):
    """A manifest that says ``schema_version: 99`` (a newer torchskin's dataset) was read as if it were this
    schema: evaluated, trained on and verified ok without a word."""
    from torchskin.dataset.files import open_dataset
    from torchskin.dataset.generate import MANIFEST, SCHEMA_VERSION

    d = tmp_path / "newer"
    shutil.copytree(dataset[0], d)
    man = json.loads((d / MANIFEST).read_text())
    man["schema_version"] = 99
    (d / MANIFEST).write_text(json.dumps(man))
    work = tmp_path / "out"
    work.mkdir()
    want = f"{str(d / MANIFEST)!r} has schema_version 99; this torchskin reads schema versions 1 to {SCHEMA_VERSION}"
    if READERS[reader] is None:
        with pytest.raises(ValueError) as e:
            open_dataset(d, ["label", "ndsi"])
        assert want in str(e.value)
        return
    line = _line(capsys, READERS[reader](d, work), 2)
    assert line.startswith(f"torchskin {reader.split()[0]}: error: dataset manifest ") and want in line, line
    assert "upgrade torchskin" in line
    assert list(work.iterdir()) == []  # no model, no result


def test_scene_budget_with_no_scene_is_refused_not_ignored(dataset, tmp_path, capsys):
    """``train --no-scene --scene-budget 0.01`` trained without any scene budget: the budget the user asked for
    was silently dropped."""
    out = tmp_path / "m.pt"
    status = main(["train", "--data", str(dataset[0]), "--out", str(out), "--no-scene", "--scene-budget", "0.01",
                   "--steps", "20"])
    line = _line(capsys, status, 2)
    assert line.startswith("torchskin train: error: --scene-budget 0.01 and --no-scene exclude each other"), line
    assert not out.exists()
    # --no-scene alone is no conflict: the budget's default is not a budget the user gave
    assert main(["train", "--data", str(dataset[0]), "--out", str(out), "--no-scene", "--steps", "5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["scene_budget"] is None and out.is_file()


def test_a_cube_pixel_is_its_row_with_sensor_noise_on(dataset):
    """``generate --images`` with the sensor's noise on (the default) stored cubes whose pixels were not the rows
    of the same pixels: the cubes drew their own exposure and noise. Each row's reflectance must be its cube's
    value at its pixel (float16 storage aside).

    The rows record no pixel index: a row's pixel is found by its local angles (θi, θr, Δφ, float32) and its
    material, recomputed from the group's G-buffer with the generator's own angle function."""
    import pandas as pd

    import torchskin.dataset.generate as gen
    from torchskin.dataset.schema import BAND_COLUMNS

    d, cfg = dataset
    man = json.loads((d / gen.MANIFEST).read_text())
    assert man["config"]["sensor"]["noise"]
    for shard in man["shards"]:  # one pose group a shard
        cube = np.load(d / shard["images"]["name"])[0]  # (skins, suns, bands, H, W) float16
        df = pd.read_parquet(d / shard["name"])
        for k, s, rows, px in rows_with_pixels(cfg, man["master_seed"], df):  # each row's pixel
            stored = cube[k, s].reshape(len(BAND_COLUMNS), -1).T[px]  # (rows, bands)
            row = rows[list(BAND_COLUMNS)].to_numpy(np.float32)
            assert np.isfinite(row).all()
            assert np.array_equal(stored, row.astype(np.float16)), (k, s, np.abs(stored - row).max())


def test_a_training_that_failed_exits_1_not_2(dataset, tmp_path, capsys):
    """A training whose boxes left the data ("boxes hold only ... of the skin") exited 2, the status of bad input:
    a script could not tell it from a typo. It is a failure of the work: status 1, one line, no model. (Provoked by
    a prohibitive width cost, which shrinks every box to nothing.)"""
    out = tmp_path / "m.pt"
    status = main(["train", "--data", str(dataset[0]), "--out", str(out), "--steps", "15", "--width-cost", "1000"])
    line = _line(capsys, status, 1)
    assert line.startswith("torchskin train: error: training failed: the learned boxes hold only "), line
    assert not out.exists()
