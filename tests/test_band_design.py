"""The band design's search (``evaluation.band_design``): bands synthesised from a finely sampled dataset, scored
by a proxy learner at the scene budget, chosen greedily."""

import numpy as np
import pytest

from torchskin.bands import Band
from torchskin.evaluation.band_design import candidates, fresh_pd, greedy, load_design_rows, proxy_pd, synthesis


@pytest.fixture(scope="module")
def fine_dirs(tmp_path_factory):
    """Three tiny datasets in 25 bands, 450-1650 nm by 50 nm: training, held-out, fresh."""
    from conftest import tiny_generate

    d = tmp_path_factory.mktemp("design")
    out = []
    for name, seed in (("train", 7), ("heldout", 8), ("fresh", 9)):
        (d / name).mkdir()
        out.append(tiny_generate(d / name, "450:1650:50", seed=seed))
    return out


@pytest.fixture(scope="module")
def fine(fine_dirs):
    train, heldout, fresh = fine_dirs
    return load_design_rows(train, heldout, fresh_dir=fresh)


def test_synthesised_bands_read_the_fine_samples_as_the_renderer_does():
    """A band at a sample reads that sample; a Gaussian band's weights sum to 1 and give a linear spectrum's value at
    its centre (the response is symmetric); a band between samples interpolates them linearly."""
    centres = list(np.arange(450.0, 1651.0, 10.0))
    W = synthesis(centres, [Band(550.0), Band(1080.0, 40.0), Band(555.0)])
    assert W.shape == (3, len(centres)) and np.allclose(W.sum(1), 1.0)
    assert W[0, centres.index(550.0)] == 1.0
    lin = 0.2 + 1e-4 * np.asarray(centres)
    assert abs(float(W[1] @ lin) - (0.2 + 1e-4 * 1080.0)) < 1e-9
    assert np.isclose(W[2, centres.index(550.0)], 0.5) and np.isclose(W[2, centres.index(560.0)], 0.5)


def test_candidates_keep_their_response_inside_the_range_and_the_data():
    c = candidates((900.0, 1700.0), 50.0, 20.0, (450.0, 1650.0))
    assert c[0].center_nm == 950.0 and c[-1].center_nm == 1600.0  # 900 +- 30 and 1650 +- 30 fall outside
    assert all(900 <= b.support[0] and b.support[1] <= 1650 for b in c)


def test_the_greedy_search_grows_one_set_and_is_reproducible(fine):
    """Each k's set holds the previous one; the same rows give the same choices and scores; a score's threshold
    holds the budget on the held-out non-skin rows that set it (at most floor(budget * n) of them above it); the
    fresh set is judged at that threshold."""
    cands = candidates((450.0, 1650.0), 200.0, 0.0, (450.0, 1650.0))
    a = greedy(fine, cands, 3, trees=8)
    assert [r["k"] for r in a] == [1, 2, 3]
    for prev, cur in zip(a, a[1:]):
        assert {tuple(b) for b in prev["bands"]} < {tuple(b) for b in cur["bands"]}
    assert greedy(fine, cands, 3, trees=8) == a
    assert all(0.0 <= r["pd_sunlit"] <= 1.0 for r in a)
    bands = [Band(b[0], b[1]) for b in a[-1]["bands"]]
    r = proxy_pd(fine, bands, trees=8, budget=0.2)
    n_neg = int((~fine.y_val).sum())
    assert r["pfa_scene"] * n_neg <= np.floor(0.2 * n_neg) + 1e-9 and r["threshold"] > -np.inf
    f = fresh_pd(fine, bands, trees=8, budget=0.2)
    assert f["pd_sunlit"] == r["pd_sunlit"] and 0.0 <= f["fresh_pd_sunlit"] <= 1.0


def test_a_coarse_dataset_is_refused(tmp_path):
    from conftest import tiny_generate

    ds = tiny_generate(tmp_path)
    with pytest.raises(ValueError, match="holds 4 bands; the band design synthesises bands"):
        load_design_rows(ds, ds)


def test_a_missing_dataset_is_named(tmp_path):
    with pytest.raises(ValueError, match="dataset folder '.*nope' does not exist"):
        load_design_rows(tmp_path / "nope", tmp_path / "nope")


def test_band_light_follows_the_water_vapour_bands():
    """Sunlight in the 1380 nm water-vapour band is a small fraction of the 1240 nm window's, and wetter air darkens
    the water bands (940, 1380 nm) but not the visible (550 nm: by under 0.1 %)."""
    from torchskin.evaluation.band_design import band_light

    bands = [Band(550.0, 20.0), Band(940.0, 20.0), Band(1240.0, 20.0), Band(1380.0, 20.0)]
    dry, wet = band_light(bands, 0.5), band_light(bands, 4.0)
    assert wet[3] < 0.02 * wet[2] and dry[3] < 0.2 * dry[2]
    assert wet[1] < 0.8 * dry[1] and wet[3] < 0.5 * dry[3]
    assert abs(wet[0] - dry[0]) <= 1e-3 * dry[0] and 0.3 < wet[0] < 2.0  # SPECTRL2: a trace of water near 590 nm


def test_candidates_below_the_light_floor_are_left_out():
    all_ = candidates((900.0, 1700.0), 20.0, 20.0, (400.0, 1700.0))
    lit = candidates((900.0, 1700.0), 20.0, 20.0, (400.0, 1700.0), min_light=0.05, water_cm=4.0)
    centres = [b.center_nm for b in lit]
    assert 1380.0 in [b.center_nm for b in all_] and 1380.0 not in centres and 1400.0 not in centres
    assert 1240.0 in centres and 1580.0 in centres and set(centres) < {b.center_nm for b in all_}


def test_synthesis_skips_samples_outside_every_band():
    """A non-finite sample that no band weighs does not reach the bands; one that a band weighs does."""
    from torchskin.evaluation.band_design import synthesise

    centres = [500.0, 600.0, 700.0]
    R = np.array([[0.1, 0.2, np.nan]])
    assert np.isfinite(synthesise(R, synthesis(centres, [Band(500.0), Band(600.0)]))).all()
    assert np.isnan(synthesise(R, synthesis(centres, [Band(700.0)]))).all()


def test_the_kind_scores_are_the_pipelines_own(fine_dirs, tmp_path):
    """``kind_scores`` on three bands at fine samples gives what training those columns, ``calibrate_to_budget`` on the
    held-out set and ``evaluate`` on the fresh set give: the same detector, the same figures."""
    from torchskin.bands import BandSet
    from torchskin.detectors import registry
    from torchskin.detectors.features import domain_from_manifest
    from torchskin.detectors.lut.train import default_bins, learn, load_rows
    from torchskin.evaluation import evaluate
    from torchskin.evaluation.band_design import kind_scores, load_kind_rows
    from torchskin.evaluation.calibration import calibrate_to_budget

    train, heldout, fresh = fine_dirs
    bands = [Band(550.0), Band(1050.0), Band(1550.0)]
    got = kind_scores(load_kind_rows(train, heldout, fresh), bands, trees=12, scene_budget=0.02, pfa_budget=0.05)
    X, R, label, physical = load_rows(train, "line")
    cols = [int(round((b.center_nm - 450.0) / 50.0)) for b in bands]
    model, _ = learn(X, R[:, cols], label, seed=0, domain=domain_from_manifest(train), bins=default_bins(3), trees=12,
                     pfa_budget=0.05, scene_budget=0.02, physical=physical, bands=BandSet.of(bands))
    registry.save(model, tmp_path / "m.pt", {})
    calibrate_to_budget(tmp_path / "m.pt", heldout, tmp_path / "c.pt", scene_budget=0.02, pfa_budget=0.05)
    res = evaluate(fresh, tmp_path / "c.pt")["models"][0]
    o, hi = res["overall"], res["sun_zenith_ge_60"]
    assert got["threshold"] == int(registry.load(tmp_path / "c.pt")[0].threshold)
    for k, ref in (("pd_sunlit", o["pd_sunlit"]), ("pd_shadow", o["pd_shadow"]), ("pd_backlit", o["pd_backlit"]),
                   ("pfa_scene", o["pfa_scene"]), ("pfa_earthlib", o["pfa"]),
                   ("pd_sun_ge_60_mean_over_configs", hi["pd_sunlit_mean_over_configs"])):
        assert got[k] == ref or (np.isnan(got[k]) and np.isnan(ref)), k
    assert 0.0 < got["pd_sunlit"] <= 1.0


def test_design_bands_command_writes_the_table_figure_and_json(fine_dirs, tmp_path, capsys):
    """The command end to end on tiny data: a set per k and range, the lut's fresh scores from k = 2, the thesis's
    four bands by the same procedure, and the files; a second range reuses nothing of the first."""
    import json

    from torchskin.cli import main

    train, heldout, fresh = fine_dirs
    out = tmp_path / "design"
    assert main(["design-bands", "--data", str(train), "--heldout", str(heldout), "--fresh", str(fresh), "--out",
                 str(out), "--ranges", "silicon,ingaas", "--k-max", "2", "--step", "200", "--fwhm", "0", "--trees", "5",
                 "--kind-trees", "8", "--budget", "0.05", "--min-light", "0", "--compare", "edge=560/27,668/14",
                 "--compare", "mine=600/40,1200/40", "--quiet", "--json"]) == 0
    res = json.loads((out / "design.json").read_text())
    assert json.loads(capsys.readouterr().out) == res
    assert list(res["ranges"]) == ["silicon", "ingaas"]
    for r, (lo, hi) in (("silicon", (400, 1000)), ("ingaas", (900, 1700))):
        steps = res["ranges"][r]
        assert [e["k"] for e in steps] == [1, 2] and steps[0]["kind"] is None
        assert all(lo <= c <= hi for c, _ in steps[1]["bands"]) and 0.0 <= steps[1]["kind"]["pd_sunlit"] <= 1.0
    assert [c for c, _ in res["thesis"]["bands"]] == [544.0, 633.0, 1080.0, 1580.0] and res["thesis"]["kind"]
    assert res["compare"]["edge"]["bands"][0] == [560.0, 27.0] and res["compare"]["mine"]["k"] == 2
    md = (out / "design.md").read_text()
    assert md.count("\n") == 2 + 4 + 3 and "| thesis | 4 | 544, 633, 1080, 1580 |" in md
    assert "| mine | 2 | 600/40, 1200/40 |" in md
    assert (out / "design.png").stat().st_size > 10_000


@pytest.mark.parametrize("args, says", [
    (["--ranges", "silicon,uv"], "--ranges must name one or more of silicon, ingaas, both"),
    (["--k-max", "0"], "--k-max must lie in 1..10"),
    (["--min-light", "nan"], "--min-light must be an irradiance"),
    (["--budget", "5"], "--budget must be a false-alarm probability"),
    (["--out", "/proc/nope/design"], "--out"),
    (["--compare", "rededge-mx"], "--compare 'rededge-mx': its 475 nm band's response spans 427..523 nm, beyond the "
                                  "datasets' 450..1650 nm"),
    (["--compare", "cam=633"], "--compare 'cam': a camera of two or more bands"),
    (["--compare", "=560/27,668/14"], "NAME=BANDS with a name of its own"),
    (["--fwhm", "40"], "the datasets sample every 50 nm, too coarse to synthesise bands of --fwhm 40 nm"),
    (["--compare", "cam=1000,633"], "--compare must list band centres in strictly ascending order"),
])
def test_design_bands_refuses_bad_options_in_one_line(fine_dirs, tmp_path, capsys, args, says):
    from torchskin.cli import main

    train, heldout, fresh = fine_dirs
    base = {"--data": str(train), "--heldout": str(heldout), "--fresh": str(fresh), "--out": str(tmp_path / "o"),
            "--fwhm": "0"}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v
    assert main(["design-bands", *[x for kv in base.items() for x in kv], "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_design_bands_names_a_coarse_dataset(tmp_path, capsys):
    from conftest import tiny_generate

    from torchskin.cli import main

    ds = tiny_generate(tmp_path)
    assert main(["design-bands", "--data", str(ds), "--heldout", str(ds), "--fresh", str(ds), "--out",
                 str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "holds 4 bands; the band design synthesises bands" in err and not (tmp_path / "o").exists()


def test_the_proxy_never_calls_skin_where_the_table_would_not(fine):
    """The proxy scores a pixel as the baked table would: a grey pixel (every normalized difference 0, far from the
    training skin's cells) and a black one (no coordinates) are never skin, whatever the trees say; a training
    skin pixel gets a finite score; the threshold is never below even odds."""
    from torchskin.evaluation.band_design import _proxy

    bands = [Band(550.0), Band(1050.0), Band(1550.0)]
    score, s, thr = _proxy(fine, bands, trees=8, budget=0.2, seed=0)
    m = len(fine.centres)
    X = fine.X[:3]
    got = score(np.stack([np.full(m, 0.5), np.zeros(m), fine.R[np.flatnonzero(fine.y)[0]]]), X)
    assert got[0] == -np.inf and got[1] == -np.inf and np.isfinite(got[2])
    assert thr >= 0.0 and s.shape == (len(fine.R_val),)


def test_design_bands_checks_every_range_before_any_search(fine_dirs, tmp_path, capsys, monkeypatch):
    """A range with too few candidates is refused before the search of the ranges before it (minutes of work)."""
    import torchskin.evaluation.band_design as bd
    from torchskin.cli import main

    def no_search(*a, **k):
        raise AssertionError("searched before every range was checked")

    monkeypatch.setattr(bd, "greedy", no_search)
    train, heldout, fresh = fine_dirs
    assert main(["design-bands", "--data", str(train), "--heldout", str(heldout), "--fresh", str(fresh), "--out",
                 str(tmp_path / "o"), "--ranges", "both,silicon", "--k-max", "6", "--step", "200", "--fwhm", "0", "--min-light", "0",
                 "--quiet"]) == 2
    assert "range silicon: 3 candidate bands" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_design_bands_without_the_thesis_bands_or_the_kind(tmp_path, capsys):
    """Data that stop short of 1580 nm: the thesis's bands are not scored (said once); --kind-trees 0 gives the
    proxy's columns only."""
    import json

    from conftest import tiny_generate

    from torchskin.cli import main

    dirs = []
    for name, seed in (("train", 7), ("heldout", 8), ("fresh", 9)):
        (tmp_path / name).mkdir()
        dirs.append(tiny_generate(tmp_path / name, "450:1000:50", seed=seed))
    out = tmp_path / "design"
    assert main(["design-bands", "--data", str(dirs[0]), "--heldout", str(dirs[1]), "--fresh", str(dirs[2]), "--out",
                 str(out), "--ranges", "silicon,silicon", "--k-max", "2", "--step", "200", "--fwhm", "0", "--trees", "4",
                 "--kind-trees", "0", "--budget", "0.05", "--min-light", "0"]) == 0
    captured = capsys.readouterr()
    assert "warning: the datasets span 450..1000 nm: the thesis's bands" in captured.err
    res = json.loads((out / "design.json").read_text())
    assert res["thesis"] is None and list(res["ranges"]) == ["silicon"] and "kind" not in res["ranges"]["silicon"][1]
    md = (out / "design.md").read_text()
    assert "thesis" not in md and "lut fresh" not in md and md.count("\n") == 2 + 2
    assert (out / "design.png").is_file() and not (out / "design.tmp.png").exists()
