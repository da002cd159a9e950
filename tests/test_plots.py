"""Figures a reader can read: the pixel-aligned render mask, labelled colour bars, the heat map's layout."""

import json

import numpy as np
import pytest
import torch

from torchskin import plots

GREEN, RED, YELLOW, BLACK = (26, 217, 51), (230, 38, 26), (255, 230, 26), (0, 0, 0)


def read_png(path, mode="RGB"):
    from PIL import Image

    with Image.open(path) as im:
        assert mode is None or im.mode == mode
        return np.asarray(im)


@pytest.fixture
def figures(monkeypatch):
    """The figures the plotting code closes (instead of closing them), to read their labels and layout."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kept, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: kept.append(fig))
    yield kept
    for f in kept:
        close(f)


def colorbar_labels(fig):
    return [cb.ax.get_ylabel() for ax in fig.axes if (cb := getattr(ax, "_colorbar", None)) is not None]


@pytest.mark.anny
@pytest.mark.slow
def test_render_mask_png_is_the_frame_pixel_for_pixel(tmp_path):
    from torchskin.render import Sensor, render, write_outputs
    from torchskin.render.scene import Camera, default_scene

    sc = default_scene(camera=Camera(width=96, height=72))
    res = render(sc, sensor=Sensor(seed=0))
    write_outputs(res, sc.to_dict(), tmp_path)
    a = read_png(tmp_path / "mask.png")
    m, t = res.mask[0, 0].cpu().numpy(), res.skin[0].cpu().numpy()
    assert a.shape == (72, 96, 3)  # H x W, one PNG pixel per frame pixel
    assert t.sum() > 20 and (m & t).sum() > 0  # skin in view, some of it detected
    want = np.zeros_like(a)
    want[m & t], want[~m & t], want[m & ~t] = GREEN, RED, YELLOW
    np.testing.assert_array_equal(a, want)
    ann = tmp_path / "mask_annotated.png"
    assert read_png(ann, mode=None).shape[:2] != (72, 96)  # the annotated figure: axes, title and key


@pytest.mark.anny
@pytest.mark.slow
def test_cli_render_mask_png_matches_render_json(tmp_path):
    from torchskin.cli import main

    assert main(["render", "--out", str(tmp_path), "--width", "80", "--height", "64"]) == 0
    a = read_png(tmp_path / "mask.png")
    assert a.shape == (64, 80, 3)
    colours, counts = np.unique(a.reshape(-1, 3), axis=0, return_counts=True)
    n = {tuple(int(v) for v in c): int(k) for c, k in zip(colours, counts)}
    assert set(n) <= {GREEN, RED, YELLOW, BLACK}
    s = json.loads((tmp_path / "render.json").read_text())["summary"]
    assert n.get(GREEN, 0) + n.get(RED, 0) == s["skin_pixels"] > 0
    assert n.get(GREEN, 0) == round(s["detected_fraction"] * s["skin_pixels"])
    assert n.get(YELLOW, 0) == s["false_alarm_pixels"]
    assert (tmp_path / "mask_annotated.png").is_file()


def test_mask_png_without_truth_is_white_on_black(tmp_path):
    m = torch.zeros(5, 7, dtype=torch.bool)
    m[1:3, 2:6] = True
    plots.mask_png(tmp_path / "m.png", m)
    a = read_png(tmp_path / "m.png")
    assert a.shape == (5, 7, 3)
    np.testing.assert_array_equal(a.all(-1), m.numpy())
    np.testing.assert_array_equal(a.any(-1), m.numpy())


def test_band_image_says_what_it_clips(tmp_path, figures):
    img = torch.linspace(-0.25, 1.5, 48).reshape(6, 8)
    plots.band_image(tmp_path / "b.png", img, "544 nm")
    (label,) = colorbar_labels(figures[-1])
    assert "reflectance" in label and "clipped to [0, 1]" in label and "min -0.25" in label and "max 1.5" in label


def test_band_images_of_a_frame_are_the_figures_drawn_one_by_one(tmp_path):
    """A frame's bands drawn by ``band_images`` (a figure per colour-bar kind, laid out once and redrawn) are,
    pixel for pixel, ``band_image``'s figure drawn for each band alone: bands whose titles and labels differ in
    length, and every kind of bar (clipped at neither end, below, above, both), in an interleaved order."""
    from matplotlib.image import imread

    g = torch.Generator().manual_seed(0)
    base = torch.rand(5, 7, generator=g)
    shifts = [(0.0, 1.0), (-0.1, 1.0), (0.0, 1.2), (-0.2, 1.3), (0.0, 0.5), (-0.05, 1.0), (0.0, 1.01), (0.0, 0.9)]
    imgs = [lo + (hi - lo) * base.roll(k, 1) for k, (lo, hi) in enumerate(shifts)]
    titles = [f"{450 + 137 * k * k:g} nm reflectance (ELM)" for k in range(len(imgs))]
    plots.band_images([tmp_path / f"many{k}.png" for k in range(len(imgs))], imgs, titles)
    for k, (img, title) in enumerate(zip(imgs, titles)):
        plots.band_image(tmp_path / f"one{k}.png", img, title)
        np.testing.assert_array_equal(imread(tmp_path / f"many{k}.png"), imread(tmp_path / f"one{k}.png"))
    with pytest.raises(ValueError, match="one shape"):
        plots.band_images([tmp_path / "a.png", tmp_path / "b.png"], [base, base[:3] + 1], ["a", "b"])
    with pytest.raises(ValueError, match="one path and title per image"):
        plots.band_images([tmp_path / "a.png"], [base, base], ["a", "b"])


@pytest.mark.slow
def test_spectra_colour_key(tmp_path, figures):
    from torchskin import tissue
    from torchskin.detect import indices

    skins, _ = tissue.sample(30, 0, dtype=torch.float64)
    wl = tissue.wavelength_grid(400, 1700, 10, dtype=torch.float64)
    R = tissue.reflectance(skins, wl)
    g, s = indices(tissue.reflectance(skins, torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64)))
    plots.plot_spectra(tmp_path / "s.png", wl, R, [f"s{k}" for k in range(30)], g, s,
                       shade=skins.melanosome / 0.45)
    fig = figures[-1]
    assert colorbar_labels(fig) == ["melanosome volume fraction"]
    assert any(ax.get_ylabel() == "Fitzpatrick type" for ax in fig.axes[-1].child_axes)
    plots.plot_spectra(tmp_path / "t.png", wl, R, [f"s{k}" for k in range(30)], g, s)  # no shade: keyed by order
    assert colorbar_labels(figures[-1]) == ["skin (order given)"]


@pytest.mark.slow
def test_pd_heatmap_labelled_and_not_overlapping(tmp_path, figures):
    from torchskin.evaluation import figures as evaluation_figures
    from torchskin.evaluation import metrics

    sun, cam = metrics.SUN_BINS, metrics.CAMERA_BINS
    bins = [{"sun_zenith_deg": [a, b], "camera_zenith_deg": [c, d], "learned": {"pd_sunlit": 0.9},
             "static": {"pd_sunlit": 0.4}} for a, b in zip(sun, sun[1:]) for c, d in zip(cam, cam[1:])]
    evaluation_figures.plots({"models": [{"name": "boundaries.onnx"}], "bins": bins}, tmp_path)
    assert {p.name for p in tmp_path.iterdir()} == {"roc.png", "pd_heatmap.png"}
    heat = figures[-1]
    assert colorbar_labels(heat) == ["Pd, sunlit skin (fraction detected)"]
    left, right = (ax for ax in heat.axes if getattr(ax, "_colorbar", None) is None)
    r = heat.canvas.get_renderer()
    ylab, yticks = right.yaxis.label.get_window_extent(r), right.yaxis.get_tightbbox(r)
    assert not ylab.overlaps(left.get_window_extent(r)) and not yticks.overlaps(left.get_tightbbox(r))
