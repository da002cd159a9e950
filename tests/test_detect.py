"""Indices, the rules detector and the Bhattacharyya coefficient (``detect``)."""

import math

import pytest
import torch

from torchskin import detect as D
from torchskin.bands import Band

DT = torch.float64


def test_index_signs_follow_design():
    # skin is redder than green and brighter at 1080 than at 1580: both indices as in the box's signs
    R = torch.tensor([0.3, 0.6, 0.6, 0.1], dtype=DT)
    g, s = D.indices(R)
    assert abs(float(g) - (0.3 - 0.6) / 0.9) < 1e-15 and float(g) < 0
    assert abs(float(s) - 0.5 / 0.7) < 1e-15 and float(s) > 0


def test_indices_find_bands_by_centre_and_axis():
    cube = torch.rand(2, 4, 5, 6, dtype=DT)  # (batch, bands, H, W)
    bands = [Band(1580), Band(544), Band(1080), Band(633)]
    g, s = D.indices(cube, bands, band_dim=1)
    torch.testing.assert_close(g, D.ndgri(cube[:, 1], cube[:, 3]))
    torch.testing.assert_close(s, D.ndsi(cube[:, 2], cube[:, 0]))
    with pytest.raises(ValueError, match="no band within"):
        D.indices(torch.rand(4), [Band(450), Band(633), Band(1080), Band(1580)])
    with pytest.raises(ValueError, match="3 bands"):
        D.indices(torch.rand(3))


def test_rules_detector_box_edges_and_tensor_box():
    b = D.DEFAULT_BOX
    g = torch.tensor([b.b1, b.b2, b.b1 - 1e-9, -0.3, -0.3, float("nan")], dtype=DT)
    s = torch.tensor([b.c1, b.c2, 0.7, b.c2 + 1e-9, 0.7, 0.7], dtype=DT)
    assert D.rules_detector(g, s).tolist() == [True, True, False, False, True, False]
    box = torch.tensor([b.b1, b.b2, b.c1, b.c2], dtype=DT)
    assert torch.equal(D.rules_detector(g, s, box), D.rules_detector(g, s))
    per_pixel = box.expand(6, 4).clone()
    per_pixel[4, 1] = -0.4  # tighten one pixel's box: it drops out
    assert D.rules_detector(g, s, per_pixel).tolist() == [True, True, False, False, False, False]
    with pytest.raises(ValueError, match="b1 <= b2"):
        D.RulesBox(b1=0.1, b2=-0.1)


def test_bhattacharyya_limits_and_symmetry():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(20000, generator=g, dtype=DT) * 0.1
    y = torch.randn(20000, generator=g, dtype=DT) * 0.1
    h = D.histogram2d(x, y, 32, (-1, 1), (-1, 1))
    assert float(h.sum()) == 20000
    assert abs(float(D.bhattacharyya(h, h)) - 1) < 1e-12
    h2 = D.histogram2d(x + 0.5, y, 32, (-1, 1), (-1, 1))
    bc = D.bhattacharyya(h, h2)
    assert abs(float(bc) - float(D.bhattacharyya(h2, h))) < 1e-15
    # two Gaussians of sigma 0.1 shifted by 0.5: BC = exp(-d^2 / (8 sigma^2)) = exp(-3.125)
    assert abs(float(bc) - math.exp(-0.5**2 / (8 * 0.1**2))) < 0.01
    near = D.histogram2d(x, y, 32, (-1, 7), (-1, 1))
    far = D.histogram2d(x + 5, y, 32, (-1, 7), (-1, 1))
    assert float(D.bhattacharyya(near, far)) == 0.0
    with pytest.raises(ValueError, match="empty"):
        D.bhattacharyya(torch.zeros(3, 3), torch.ones(3, 3))
