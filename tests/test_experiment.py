"""The thesis experiment on an anny subject (small frames) and the anny subject itself."""

import json

import numpy as np
import pytest

from torchskin import experiment
from torchskin.render import Sensor
from torchskin.scene import anny_body


@pytest.fixture(scope="module")
def small_experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    return out, experiment.run(out, width=192, height=192, sensor=Sensor(seed=1))


def test_anny_subject_has_skin_on_head_and_hands_and_stands_facing_x():
    v, f, skin = anny_body()
    assert v[:, 2].min() == pytest.approx(0.0, abs=1e-6) and 1.4 < v[:, 2].max() < 2.0
    centroids = v[f].mean(1)
    head = centroids[:, 2] > v[:, 2].max() - 0.2
    assert skin[head].mean() > 0.9  # the head is skin
    torso = (centroids[:, 2] > 0.9) & (centroids[:, 2] < 1.2) & (np.abs(centroids[:, 1]) < 0.12)
    assert skin[torso].mean() < 0.05  # the clothed torso is not
    nose = v[np.argmax(np.where(v[:, 2] > v[:, 2].max() - 0.2, v[:, 0], -np.inf))]
    assert nose[0] > 0.05  # the face points to +x
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert 0.03 < area[skin].sum() / area.sum() < 0.25  # head, neck and hands: a small part of the body


def test_experiment_detection_and_calibration(small_experiment):
    out, res = small_experiment
    assert res["angles_deg"] == [10.0, 30.0, 60.0, 85.0]
    assert res["detected_fraction_diffuse"][0] >= 0.9  # the diffuse model sits in its own box
    assert res["detected_fraction_combined"][-1] < 0.2  # nearly every pixel rejected at 85 degrees
    assert abs(res["appendix_c_middle_reflectance"] - 0.40) <= 0.02
    assert all(0.0 <= b <= 1.0 for b in res["bhattacharyya"])
    assert min(res["sunlit_skin_pixels"]) > 50
    saved = json.loads((out / "experiment.json").read_text())
    assert saved["detected_fraction_combined"] == res["detected_fraction_combined"]
    for name in ("reflectance_combined.png", "rules_scatter.png", "histograms.png", "detection_vs_angle.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"


def test_experiment_spectralon_switch_reports_lambertian_panel_error(tmp_path):
    res = experiment.run(tmp_path, angles=(10.0, 60.0), width=128, height=128, sensor=Sensor(noise=False),
                         panels="spectralon-brdf")
    err = np.array(res["lambertian_panel_error"])
    assert err.shape == (2, 4)
    assert err[0].max() < 0.005  # near-normal illumination: the panels are Lambertian enough
    assert err[1].max() > 0.01 and err[1, 2:].mean() > err[1, :2].mean()  # larger off normal, larger in the NIR
