"""The band design's search (``evaluation.band_design``): bands synthesised from a finely sampled dataset, scored
by a proxy learner at the scene budget, chosen greedily."""

import numpy as np
import pytest

from torchskin.bands import Band
from torchskin.evaluation.band_design import candidates, fresh_pd, greedy, load_design_rows, proxy_pd, synthesis


@pytest.fixture(scope="module")
def fine(tmp_path_factory):
    from conftest import tiny_generate

    d = tmp_path_factory.mktemp("design")
    for name in ("train", "heldout", "fresh"):
        (d / name).mkdir()
    return load_design_rows(tiny_generate(d / "train", "450:1650:50", seed=7),
                            tiny_generate(d / "heldout", "450:1650:50", seed=8),
                            fresh_dir=tiny_generate(d / "fresh", "450:1650:50", seed=9))


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
