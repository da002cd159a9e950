"""``bands.BandSet``: a camera's bands as data, parsed from ``--bands``, named as columns, written as JSON."""

import json
import subprocess
import sys

import pytest

from torchskin.bands import INDEX_BANDS, INDEX_BANDS_NM, Band, BandSet, parse_bands
from torchskin.io import parse_band_list


@pytest.mark.parametrize("spec", ["544,633,1080,1580", "544/20,633.5/12.25,1580", "450:1650:10/5",
                                  "400.1:400.5:0.1,1000"])
def test_a_band_set_reads_back_from_its_json(spec):
    b = BandSet.parse(spec)
    assert BandSet.from_json(b.to_json()) == b
    assert BandSet.from_json(json.loads(b.to_json())) == b  # as a manifest holds it: the list itself
    assert b.bands == parse_bands(spec)


def test_the_index_bands_are_named_as_the_dataset_columns():
    from torchskin.detectors.features import BAND_COLUMNS

    assert INDEX_BANDS.columns == BAND_COLUMNS
    assert INDEX_BANDS.centers == INDEX_BANDS_NM and all(b.fwhm_nm == 0 for b in INDEX_BANDS)
    assert BandSet.parse("544.5,1080.25/10").columns == ("r544.5", "r1080.25")


def test_a_range_gives_one_band_per_step_stop_included():
    b = BandSet.parse("450:1650:10")
    assert len(b) == 121 and b[0] == Band(450.0) and b[-1] == Band(1650.0)
    assert [x.fwhm_nm for x in BandSet.parse("450:470:10/5")] == [5.0, 5.0, 5.0]


def test_index_finds_a_band_by_wavelength_within_the_tolerance():
    assert INDEX_BANDS.index(1580.0) == 3 and INDEX_BANDS.index(1081.5) == 2
    with pytest.raises(ValueError, match="no band within 2 nm of 700 nm"):
        INDEX_BANDS.index(700.0)
    assert INDEX_BANDS.index(700.0, tol_nm=100) == 1


@pytest.mark.parametrize("spec,needle", [
    ("544,abc", "bad band 'abc' in --bands"),
    ("544/-5", "fwhm_nm must be >= 0"),
    ("544,,633", "empty item"),
    ("450:400:10", "bad band range '450:400:10'"),
    ("450:1650", "bad band range"),
    ("1:100000:1", "more than 10000"),
    ("300", "outside the model's 400-1700 nm"),
    ("1580,544", "strictly ascending"),
    ("544,544.0001", "both written as 544 nm"),
])
def test_a_bad_band_list_fails_in_one_line_naming_the_problem(spec, needle):
    with pytest.raises(ValueError, match=needle) as e:
        BandSet.parse(spec)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("doc,needle", [
    ("not json", "does not parse"),
    ("[]", "non-empty list"),
    ('{"center_nm": 544}', "non-empty list"),
    ('[{"center_nm": 544, "fwhm_nm": 10, "response": [[540, 0.5]]}]', "band 0: response must be"),
    ('[{"center_nm": 544, "response": {"wavelengths_nm": [540, 550], "values": [0, 1]}}]', "needs its FWHM"),
    ('[{"center_nm": 544}, {"fwhm_nm": 1}]', "band 1 must be"),
    ('[{"center_nm": "544"}]', "(numbers)"),
    ('[{"center_nm": 544, "width": 1}]', "band 0 must be"),
    ('[{"center_nm": -544}]', "band 0: center_nm must be a positive"),
])
def test_bad_band_set_json_fails_in_one_line_naming_the_problem(doc, needle):
    with pytest.raises(ValueError, match=needle.replace("(", r"\(").replace(")", r"\)")) as e:
        BandSet.from_json(doc)
    assert "\n" not in str(e.value)


def test_a_cubes_band_list_goes_through_the_same_parser():
    """``detect --bands`` names a cube's bands in its own order; its items are read as ``--bands`` reads them,
    so a bad FWHM, once ignored, is refused."""
    assert parse_band_list("1580,544/20,1080:1090:10") == [1580.0, 544.0, 1080.0, 1090.0]
    with pytest.raises(ValueError, match="bad band '544/abc' in --bands"):
        parse_band_list("544/abc,633")
    with pytest.raises(ValueError, match="twice"):
        parse_band_list("544,544")


def test_the_band_module_imports_no_torch():
    code = ("import sys, torchskin.bands as b; s = b.BandSet.parse('450:1650:10'); "
            "assert b.BandSet.from_json(s.to_json()) == s and s.columns[0] == 'r450'; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
