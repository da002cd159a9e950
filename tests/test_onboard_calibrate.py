"""Onboard ELM (numpy only): panel regions -> gain/offset -> reflectance; the torch ELM, the renderer's own ELM
and the ``torchskin calibrate`` command agree; bad input writes nothing."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchskin.cli.calibrate import parse_roi
from torchskin.onboard import elm_apply, elm_fit, panel_signal
from torchskin.render.elm import elm_coefficients

GAIN = np.array([12000.0, 9000.0, 15000.0, 7000.0])
OFFSET = np.array([120.0, 80.0, 300.0, 40.0])
PANELS = [((4, 20, 4, 20), 0.97), ((4, 20, 40, 56), 0.03), ((30, 46, 4, 20), [0.40, 0.41, 0.42, 0.43])]


def scene(noise: float = 0.0, seed: int = 0):
    """Reflectance map with three panels on a textured background, its signals DN = gain·ρ + offset; each panel
    region's outer ring of pixels is mixed with the background (the edge pixels ELM must not use)."""
    rng = np.random.default_rng(seed)
    rho = rng.uniform(0.05, 0.6, (4, 64, 64))
    for (y0, y1, x0, x1), r in PANELS:
        rho[:, y0:y1, x0:x1] = np.asarray(r, dtype=float).reshape(-1, 1, 1)
        rho[:, y0, x0:x1] = rho[:, y1 - 1, x0:x1] = rho[:, y0:y1, x0] = rho[:, y0:y1, x1 - 1] = 0.9  # mixed edge
    dn = GAIN[:, None, None] * rho + OFFSET[:, None, None] + noise * rng.standard_normal(rho.shape)
    return rho, dn


def test_two_and_three_panels_recover_the_line_and_reflectance():
    rho, dn = scene()
    for panels in (PANELS[:2], PANELS):
        fit = elm_fit(dn, panels)
        assert np.allclose(fit["gain"], GAIN, rtol=1e-12) and np.allclose(fit["offset"], OFFSET, rtol=1e-10)
        assert np.abs(fit["residual"]).max() < 1e-12
        back = elm_apply(dn, fit["gain"], fit["offset"])
        assert back.dtype == np.float32 and np.abs(back - rho).max() < 1e-6
    with pytest.raises(ValueError, match="interior"):  # without erosion the mixed edge would bias the medians
        panel_signal(dn, (4, 6, 4, 20), erode=1)
    (y0, y1, x0, x1), r = PANELS[1]
    assert not np.allclose(dn[:, y0:y1, x0:x1].mean((1, 2)), OFFSET + GAIN * r, rtol=0.01)  # a mean: edge-biased
    assert np.allclose(panel_signal(dn, PANELS[1][0], erode=0), OFFSET + GAIN * r)  # the median: robust


def test_matches_the_torch_elm_and_applies_to_batches():
    _, dn = scene()
    fit = elm_fit(dn, PANELS[:2])
    a, b = elm_coefficients(torch.tensor(fit["signals"][0]), torch.tensor(fit["signals"][1]),
                            torch.tensor(0.97, dtype=torch.float64), torch.tensor(0.03, dtype=torch.float64))
    assert np.allclose(a.numpy(), fit["gain"], rtol=1e-14) and np.allclose(b.numpy(), fit["offset"], rtol=1e-12)
    batch = elm_apply(np.stack([dn, dn]), fit["gain"], fit["offset"])
    assert batch.shape == (2, 4, 64, 64) and np.array_equal(batch[1], elm_apply(dn, fit["gain"], fit["offset"]))


def test_noisy_middle_panel_reads_its_reflectance():
    """Appendix C with 40 DN of noise: the 0.40 panel, calibrated with the 0.97/0.03 pair, reads 0.40 ± 0.01."""
    _, dn = scene(noise=40.0, seed=3)
    fit = elm_fit(dn, PANELS[:2])
    refl = elm_apply(dn, fit["gain"], fit["offset"])
    mid = np.median(refl[:, 31:45, 5:19].reshape(4, -1), axis=1)
    assert np.allclose(mid, [0.40, 0.41, 0.42, 0.43], atol=0.01)
    assert fit["residual"].max() < 1e-12  # two panels: the line passes through both


@pytest.mark.parametrize("panels, msg", [
    ([PANELS[0]], "at least 2"),
    ([PANELS[0], ((4, 20, 40, 56), 0.97)], "differ in every band"),
    ([((4, 20, 4, 20), 0.03), ((4, 20, 40, 56), 0.97)], "swapped"),
    ([PANELS[0], ((4, 20, 40, 70), 0.03)], "0 <= X0 < X1 <= 64"),
    ([PANELS[0], ((4, 20, 40, 56), 1.2)], r"\(0, 1\]"),
    ([PANELS[0], ((4, 20, 40, 56), [0.1, 0.2])], "one per band"),
])
def test_bad_panels_are_named(panels, msg):
    _, dn = scene()
    with pytest.raises(ValueError, match=msg):
        elm_fit(dn, panels)


def test_bad_regions_and_nan():
    _, dn = scene()
    with pytest.raises(ValueError, match="Y0:Y1:X0:X1"):
        parse_roi("1:2:3")
    dn[2, 10, 10] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        elm_fit(dn, PANELS[:2])
    with pytest.raises(ValueError, match="gain must be"):
        elm_apply(dn, -GAIN, OFFSET)


@pytest.mark.parametrize("module", ["torchskin.onboard", "torchskin.cli", "torchskin.cli.detect",
                                    "torchskin.cli.calibrate"])
def test_onboard_modules_import_without_torch(module):
    """The runtime, its command line and the dispatcher import with numpy (and onnxruntime) alone."""
    r = subprocess.run([sys.executable, "-c", f"import sys, {module}; assert 'torch' not in sys.modules"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def run_cli(args):
    """``torchskin calibrate`` in a subprocess where importing torch fails (the onboard path)."""
    script = ("import sys; sys.modules['torch'] = None; from torchskin.cli import main; "
              f"sys.exit(main({['calibrate', *args]!r}))")
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)


@pytest.mark.anny
@pytest.mark.slow
def test_cli_on_a_rendered_frame_reproduces_the_renderers_elm(tmp_path):
    """``render`` writes the signal cube and each panel's pixel region; ``calibrate`` with those regions (no
    torch) gives the renderer's reflectance cube (noise off: the panels are uniform, both medians agree)."""
    from torchskin.cli import main

    assert main(["render", "--out", str(tmp_path / "f"), "--width", "96", "--height", "96", "--no-noise"]) == 0
    doc = json.loads((tmp_path / "f" / "render.json").read_text())
    refs = {"panel_white": 0.97, "panel_dark": 0.03}
    panels = [f"{':'.join(map(str, doc['panels'][p]['region']))}={r}" for p, r in refs.items()]
    out = tmp_path / "refl.npy"
    r = run_cli(["--cube", str(tmp_path / "f" / "signal.npy"), *sum([["--panel", p] for p in panels], []),
                 "--out", str(out), "--save-coefficients", str(tmp_path / "elm.json"), "--json"])
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    ours, theirs = np.load(out), np.load(tmp_path / "f" / "reflectance.npy")
    assert ours.shape == theirs.shape == (4, 96, 96) and np.abs(ours - theirs).max() < 1e-5
    assert np.allclose([p["signal"] for p in res["panels"]], [np.ravel(doc["panels"][p]["signal"]) for p in refs],
                       rtol=1e-6)
    again = tmp_path / "again.npy"
    r = run_cli(["--cube", str(tmp_path / "f" / "signal.npy"), "--coefficients", str(tmp_path / "elm.json"),
                 "--out", str(again)])
    assert r.returncode == 0 and np.array_equal(np.load(again), ours)


@pytest.mark.slow
def test_cli_errors_write_nothing(tmp_path):
    _, dn = scene()
    np.save(tmp_path / "dn.npy", dn.astype(np.float32))
    cube = str(tmp_path / "dn.npy")
    out = tmp_path / "o.npy"
    for args, msg in [(["--panel", "4:20:4:20=0.97"], "at least 2"),
                      (["--panel", "4:20:4:20=0.97", "--panel", "4:20:40=0.03"], "Y0:Y1:X0:X1"),
                      (["--panel", "4:20:4:20=0.97", "--panel", "4:20:40:56=x"], "--panel must be"),
                      ([], "either --panel"),
                      (["--coefficients", str(tmp_path / "missing.json")], "missing.json' does not exist")]:
        r = run_cli(["--cube", cube, *args, "--out", str(out)])
        assert r.returncode == 2 and msg in r.stderr, r.stderr
        assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1, (r.stdout, r.stderr)  # one line, no more
        assert not out.exists()
    r = run_cli(["--cube", str(tmp_path / "none.npy"), "--panel", "4:20:4:20=0.97", "--panel", "4:20:40:56=0.03",
                 "--out", str(out)])
    assert r.returncode == 2 and "--cube" in r.stderr and "does not exist" in r.stderr and not out.exists()
    assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1, (r.stdout, r.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dn.npy"]  # no temporary file left behind


def test_onboard_elm_equals_the_renderers_elm():
    """The numpy ELM of the onboard runtime (``onboard.elm_fit`` + ``elm_apply``) and the renderer's torch ELM
    (``render.elm.elm_coefficients`` + ``apply_elm``) give the same line and the same reflectance."""
    import torch

    from torchskin import onboard
    from torchskin.render.elm import apply_elm, elm_coefficients

    rng = np.random.default_rng(7)
    gain, offset = rng.uniform(500, 5000, 4), rng.uniform(0, 300, 4)
    rho = rng.uniform(0, 1, (4, 24, 32))
    rho[:, 2:8, 2:8], rho[:, 2:8, 20:26] = 0.97, np.array([0.03, 0.04, 0.05, 0.06])[:, None, None]
    signal = gain[:, None, None] * rho + offset[:, None, None]
    fit = onboard.elm_fit(signal, [((2, 8, 2, 8), 0.97), ((2, 8, 20, 26), [0.03, 0.04, 0.05, 0.06])], erode=0)
    a, b = elm_coefficients(torch.tensor(signal[:, 4, 4]), torch.tensor(signal[:, 4, 22]),
                            torch.full((4,), 0.97, dtype=torch.float64), torch.tensor([0.03, 0.04, 0.05, 0.06]))
    np.testing.assert_allclose(fit["gain"], a.numpy(), rtol=1e-6)  # onboard medians in float32
    np.testing.assert_allclose(fit["offset"], b.numpy(), rtol=1e-6, atol=1e-3)
    frame = torch.tensor(signal).permute(1, 2, 0)[None, None]  # (S, C, H, W, B)
    panels = torch.tensor(np.stack([signal[:, 4, 4], signal[:, 4, 22]]))[None, None]
    refs = torch.tensor([[0.97] * 4, [0.03, 0.04, 0.05, 0.06]], dtype=torch.float64)[None, None]
    torch_rho = apply_elm(frame, panels, refs)[0, 0].permute(2, 0, 1).numpy()
    np.testing.assert_allclose(onboard.elm_apply(signal, fit["gain"], fit["offset"]), torch_rho, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(torch_rho, rho, atol=1e-9)
