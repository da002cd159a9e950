"""``torchskin.evaluation`` as a library: its metrics judge any per-row decision (not only regions of the
(NDGRI, NDSI) plane) over typed dataset rows, and ``evaluate`` returns the complete result, the one
``torchskin evaluate`` writes and prints (the command adds nothing)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from torchskin.dataset.schema import Rows
from torchskin.evaluation import evaluate, rates, row_rates

EXPORTS = Path(__file__).resolve().parents[1] / "exports"


def _hand_rows() -> Rows:
    """Eight rows with a feature no index plane has (a temperature), in two groups: skin rows 0-3, non-skin 4-7."""
    return Rows({"temperature_c": np.array([36.5, 35.0, 20.0, 37.0, 36.0, 15.0, 10.0, 22.0], dtype=np.float32),
                 "label": np.array([True, True, True, True, False, False, False, False]),
                 "group": np.array([0, 0, 1, 1, 0, 0, 1, 1])})


def test_metrics_take_any_decision_over_the_rows():
    """Decision: temperature above 30 °C. Skin rows 0, 1, 3 of 0-3 are above: Pd 3/4; non-skin row 4 of 4-7:
    Pfa 1/4; per group, Pd 2/2 (group 0: rows 0, 1) and 1/2 (group 1: rows 2, 3), their mean 0.75."""
    rows = _hand_rows()
    hot = rows["temperature_c"] > 30.0
    got = row_rates(rows, hot, group="group")
    assert got == {"pd": 0.75, "pfa": 0.25, "skin_pixels": 4, "nonskin_pixels": 4, "pd_mean_over_groups": 0.75}
    # a mask selects rows: group 1 only (rows 2, 3 skin; 6, 7 non-skin): Pd 1/2, Pfa 0/2
    assert rates(hot, rows["label"], rows["group"] == 1) == {"pd": 0.5, "pfa": 0.0, "skin_pixels": 2,
                                                             "nonskin_pixels": 2}
    # an uneven grouping: group 1 holds one skin row (detected), group 0 three (one detected): mean (1 + 1/3) / 2
    rows.columns["group"] = np.array([0, 0, 0, 1, 0, 0, 1, 1])
    assert row_rates(rows, hot, group="group")["pd_mean_over_groups"] == pytest.approx((1 + 2 / 3) / 2)
    # no rows selected: NaN, not an error
    none = rates(hot, rows["label"], np.zeros(8, dtype=bool))
    assert math.isnan(none["pd"]) and math.isnan(none["pfa"]) and none["skin_pixels"] == 0


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """Two configurations of the built-in dataset configuration (its default subject)."""
    from torchskin.cli import main

    d = tmp_path_factory.mktemp("evaluation") / "ds"
    assert main(["generate", "--configs", "2", "--seed", "7", "--out", str(d), "--quiet"]) == 0
    return d


@pytest.mark.slow
def test_the_library_result_is_what_the_command_writes(small_dataset, tmp_path, capsys):
    """``evaluate``'s dict is the whole ``--save`` document (provenance included) and ``--json`` prints its keys
    unchanged: the command line adds nothing."""
    from torchskin.cli import main

    model = str(EXPORTS / "boundaries.pt")
    res = evaluate(str(small_dataset), [model])
    assert {"data", "data_manifest_sha256", "model"} <= set(res) and res["model"] == model
    assert main(["evaluate", "--data", str(small_dataset), "--model", model, "--save", str(tmp_path / "r.json")]) == 0
    capsys.readouterr()
    assert (tmp_path / "r.json").read_text() == json.dumps(res, indent=1)
    assert main(["evaluate", "--data", str(small_dataset), "--model", model, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert json.dumps(printed) == json.dumps({k: res[k] for k in printed})
    assert set(printed) == {"models", "learned", "static", "bins", "sun_zenith_ge_60", "warnings"} & set(res)
