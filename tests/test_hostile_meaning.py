"""Inputs and outputs checked for meaning, not only for form (issue 23): each test is a user's mistake, or a
user trusting a flag, that used to succeed with a wrong answer."""

import math

import numpy as np
import pytest
import torch

from torchskin.dataset.config import resolve_config, sample_group
from torchskin.render.elm import (
    ELM_MAX_IRRADIANCE_RATIO,
    ELM_MIN_SEPARATION_SIGMA,
    elm_line_valid,
    panel_irradiance_ratio,
    panel_median_noise_dn,
)
from torchskin.render.scene import PANEL_KINDS


def _cfg(obj, sun_zenith, kind):
    return resolve_config({"camera": {"width": 64, "height": 64, "range_m": [8.0, 8.0], "zenith_deg": [30.0, 30.0]},
                           "sun": {"per_pose": 3, "zenith_deg": [sun_zenith, sun_zenith]},
                           "skin": {"per_pose": 2}, "subject": {"meshes": [str(obj)]}, "panels": {"kinds": [kind]},
                           "sampling": {"groups_per_shard": 1, "pixels_per_class": 32}, "confusers": {"count": [0, 0]}})


def _frames(obj, sun_zenith, kind):
    """(elm_valid, max |reflectance|) per configuration of one pose group, and whether the old rule (both panels
    sunlit) called each of its suns valid."""
    from torchskin.dataset.generate import group_rows, group_scene, panels_sunlit
    from torchskin.render.raycast import Raycaster

    group = sample_group(_cfg(obj, sun_zenith, kind), 0, 0)
    rows = {k: np.concatenate([np.asarray(x) for x in v]) for k, v in
            group_rows(group, 32).items() if k in ("elm_valid", "r544", "r633", "r1080", "r1580", "sun", "skin")}
    cfg = rows["skin"] * len(group.suns) + rows["sun"]
    refl = np.abs(np.stack([rows[k] for k in ("r544", "r633", "r1080", "r1580")], 1)).max(1)
    valid = np.array([rows["elm_valid"][cfg == c].all() for c in range(cfg.max() + 1)])
    assert all(len(set(rows["elm_valid"][cfg == c])) == 1 for c in range(cfg.max() + 1))  # one verdict per frame
    peak = np.array([refl[cfg == c].max() for c in range(cfg.max() + 1)])
    sc = group_scene(group)
    dirs = np.stack([s.direction for s in sc.suns])
    gb = Raycaster.from_scene(sc).gbuffer(sc.cameras, dirs)
    sunlit = panels_sunlit(gb, list(sc.panels), torch.tensor(dirs, dtype=torch.float32)).numpy()
    return valid, peak, sunlit


@pytest.mark.parametrize("kind", PANEL_KINDS)
def test_a_grazing_sun_frame_whose_panels_are_sunlit_is_not_called_valid(subject_obj, kind):
    """A user trains on ``elm_valid`` rows. A sun 87° from the zenith grazes the level panels (cos 87° = 0.05)
    while it lights the subject's sun-facing side head on: both panels are sunlit, yet the line through them
    makes that side read many times its reflectance. Such frames must not be called valid, whatever the panels."""
    valid, peak, sunlit = _frames(subject_obj, 87.0, kind)
    assert sunlit.any()  # the old rule (panels sunlit) called some of these frames valid
    assert peak.max() > 3.0  # and they read like that
    assert not valid.any()


@pytest.mark.parametrize("kind", PANEL_KINDS)
def test_a_moderate_sun_frame_stays_valid(subject_obj, kind):
    """The same scene under a sun 30° from the zenith: the line is physical and every frame valid. The panels
    receive at least 1 / 1.16 of any surface's light (cos 30°), so no row reads above 1.16 x the brightest
    reflectance in the scene (the white panel, 0.97), 1.13, beyond a skin glint's few per cent."""
    valid, peak, sunlit = _frames(subject_obj, 30.0, kind)
    assert sunlit.all() and valid.all()
    assert peak.max() <= 1.5


def test_the_rule_at_its_thresholds():
    """Exactly ``ELM_MIN_SEPARATION_SIGMA`` σ apart is a line, a hair less is not (exact binary numbers)."""
    assert ELM_MIN_SEPARATION_SIGMA == 20.0
    refs = torch.tensor([[0.75, 0.25]], dtype=torch.float64)[..., None]
    noise = torch.tensor([[36.0, 48.0]], dtype=torch.float64)[..., None]  # σ of the difference: 60 DN
    at = torch.tensor([[1230.0, 30.0]], dtype=torch.float64)[..., None]  # 1200 DN = 20 x 60 DN
    assert bool(elm_line_valid(at, refs, noise))
    assert not bool(elm_line_valid(at + torch.tensor([0.0, 1e-6], dtype=torch.float64)[:, None], refs, noise))
    assert not bool(elm_line_valid(at.flip(-2), refs, noise))  # the dark panel brighter: a negative gain


def test_the_irradiance_ratio_is_the_largest_over_every_orientation():
    """The closed form of ``panel_irradiance_ratio`` (the brightest orientation's irradiance over the panels')
    against a brute-force maximum of E(n) = E_beam max(0, n·s) + E_sky (1 + n_z) / 2 over 200,000 unit normals,
    for random suns, panel normals and beam-to-sky mixes; and its limits: a clear sky over level panels gives
    1 / cos θz (2 at 60°, exactly), a panel facing the sun 1, an overcast sky 1."""
    g = torch.Generator().manual_seed(3)
    n = torch.randn(200_000, 3, dtype=torch.float64, generator=g)
    n = n / n.norm(dim=1, keepdim=True)
    sun = torch.randn(6, 3, dtype=torch.float64, generator=g)
    sun[:, 2] = sun[:, 2].abs() + 0.05
    sun = sun / sun.norm(dim=1, keepdim=True)
    beam = torch.rand(6, 2, dtype=torch.float64, generator=g) * 1.5
    sky = torch.rand(6, 2, dtype=torch.float64, generator=g) * 0.5
    panels = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    e = beam[:, None, :] * (sun @ n.T).clamp_min(0)[..., None] + sky[:, None, :] * ((1 + n[:, 2]) / 2)[None, :, None]
    ep = beam[:, None, :] * (sun @ panels.T).clamp_min(0)[..., None] + sky[:, None, :] * ((1 + panels[:, 2]) / 2)[None, :, None]
    brute = (e.amax(1)[:, None, :] / ep).amax(dim=(1, 2))
    exact = panel_irradiance_ratio(beam, sky, sun, panels)
    assert (exact >= brute).all() and torch.allclose(exact, brute, rtol=2e-4)  # the sampled normals fall short
    up = panels[:1]
    s60 = torch.tensor([[0.75**0.5, 0.0, 0.5]], dtype=torch.float64)
    one = torch.ones(1, 1, dtype=torch.float64)
    assert float(panel_irradiance_ratio(one, 0 * one, s60, up)[0]) == 2.0
    assert float(panel_irradiance_ratio(one, 0 * one, s60, s60)[0]) == pytest.approx(1.0, abs=4e-16)  # |s|² rounds
    assert float(panel_irradiance_ratio(0 * one, one, s60, up)[0]) == 1.0
    assert math.isinf(float(panel_irradiance_ratio(one, 0 * one, s60, -s60)[0]))  # a panel turned from the sun
    assert ELM_MAX_IRRADIANCE_RATIO == 3.0


@pytest.mark.parametrize("signals", [[250.0, 750.0], [500.0, 500.0], [math.nan, 250.0], [math.inf, 250.0]],
                         ids=["panels swapped", "no contrast", "nan", "inf"])
def test_a_line_without_positive_finite_gain_is_not_valid(signals):
    """The white panel read darker than the dark one (mislabelled panels), both read the same (both clipped or
    both in shade), or a signal is not finite: no line, however quiet the sensor."""
    refs = torch.tensor([[0.75, 0.25]], dtype=torch.float64)[..., None]
    L = torch.tensor([signals], dtype=torch.float64)[..., None]
    assert not bool(elm_line_valid(L, refs, torch.zeros_like(L)))


def test_one_bad_band_invalidates_the_frame():
    refs = torch.tensor([[[0.75] * 4, [0.25] * 4]], dtype=torch.float64)
    L = torch.tensor([[[750.0, 750.0, 750.0, 251.0], [250.0] * 4]], dtype=torch.float64)
    assert elm_line_valid(L, refs, torch.ones_like(L)).tolist() == [False]
    L[0, 0, 3] = 750.0
    assert elm_line_valid(L, refs, torch.ones_like(L)).tolist() == [True]


def test_the_median_noise_is_the_sensors():
    """``panel_median_noise_dn`` predicts the spread of a 256-pixel median drawn by the sensor model itself
    (shot + read noise, ADC), within 10 %."""
    from torchskin.bands import as_bands
    from torchskin.render.sensor import Sensor, sensor_signal

    sensor = Sensor(read_noise_e=50.0, atmosphere=False)
    L = torch.full((400, 1, 256, 4), 0.01, dtype=torch.float64)  # 400 frames of a uniform panel
    dn = sensor_signal(L, sensor, as_bands([544, 633, 1080, 1580]), focal_px=1000.0,
                       generator=torch.Generator().manual_seed(3))
    med = dn.median(dim=2).values  # (400, 1, 4)
    want = panel_median_noise_dn(med.mean(0), 256, 50.0, 2**14 / sensor.full_well_e)
    assert med.std(0) / want == pytest.approx(torch.ones(1, 4, dtype=torch.float64), rel=0.1)


def test_a_billion_configurations_are_refused_before_anything_is_written(tmp_path, capsys):
    """``generate --configs 1000000000`` would write ~8 TB: refused in one line naming --configs, exit 2, and the
    output folder never made."""
    from torchskin.cli import main

    out = tmp_path / "huge"
    assert main(["generate", "--configs", "1000000000", "--out", str(out), "--quiet"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--configs" in err[0] and "GB free" in err[0], err
    assert not out.exists()


def test_the_disk_estimate_covers_what_generate_writes(subject_obj, tmp_path):
    """The estimate is not below what a run writes (so that a run that fits is not cut short by a full disk),
    nor wildly above it (so that a run that fits is not refused)."""
    from torchskin.dataset.generate import estimate_bytes, generate

    cfg = _cfg(subject_obj, 30.0, "lambertian")
    for images in (False, True):
        d = tmp_path / f"d{images}"
        man = generate(cfg, 12, 0, d, quiet=True, images=images)
        wrote = sum(s["bytes"] + s.get("images", {}).get("bytes", 0) for s in man["shards"])
        est = estimate_bytes(cfg, 12, images)
        assert wrote <= est <= 20 * wrote + 2**20


def test_too_little_disk_is_refused_when_resuming(monkeypatch, tmp_path):
    import shutil

    from torchskin.dataset import generate as G

    monkeypatch.setattr(shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**12, 10**12 - 1000, 1000))
    with pytest.raises(ValueError, match="--configs: the dataset would take about"):
        G.check_disk_space(tmp_path / "not" / "yet", 1001)
    G.check_disk_space(tmp_path / "not" / "yet", 1000)
    G.check_disk_space(tmp_path, 1500, reclaim=500)  # what --overwrite deletes first counts as free


def test_verify_of_a_dataset_missing_most_of_its_shards_prints_one_short_line(tmp_path, capsys):
    """An interrupted run of a billion configurations leaves a manifest that lists 20 million shards and holds a
    few (here 300,000 for speed): ``dataset verify`` says how many are missing and where, in one short line (text and --json)."""
    import json

    from torchskin.cli import main
    from torchskin.dataset.generate import MANIFEST

    n = 300_000  # a billion configurations list 20 million
    (tmp_path / MANIFEST).write_text(json.dumps({"n_shards": n, "shards": []}))
    assert main(["dataset", "verify", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert len(out) < 300 and f"missing {n}: shard-00000.parquet..shard-{n - 1:05d}.parquet;" in out, out
    assert main(["dataset", "verify", str(tmp_path), "--json"]) == 1
    out = capsys.readouterr().out
    rep = json.loads(out)
    assert len(out) < 400 and rep["missing"] == n and rep["corrupted"] == 0 and not rep["ok"]


def test_name_ranges_shows_runs_and_gaps():
    from torchskin.dataset.verify import name_ranges

    names = [f"shard-{k:05d}.parquet" for k in (0, 1, 2, 5, 7, 8)] + ["images/images-00003.npy", ".x.tmp"]
    assert name_ranges(names, limit=10) == ("8: .x.tmp, images/images-00003.npy, shard-00000.parquet.."
                                            "shard-00002.parquet, shard-00005.parquet, shard-00007.parquet.."
                                            "shard-00008.parquet")
    assert name_ranges(names, limit=2).endswith("... (3 more runs)")
    assert name_ranges([]) == "none"


def _closed_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed once the socket is: nothing listens there


def test_a_ray_address_where_no_cluster_answers_fails_in_bounded_time(monkeypatch, tmp_path, capsys):
    """``generate --backend ray --address`` with a typo in the port: one line naming --address within the
    connect timeout (shortened here), exit 2, no output folder; Ray itself would retry for minutes."""
    import time

    pytest.importorskip("ray")
    from torchskin.cli import main
    from torchskin.dataset import ray_backend

    monkeypatch.setattr(ray_backend, "RAY_CONNECT_TIMEOUT_S", 2.0)
    out = tmp_path / "d"
    t0 = time.monotonic()
    rc = main(["generate", "--configs", "48", "--out", str(out), "--quiet", "--backend", "ray",
               "--address", f"127.0.0.1:{_closed_port()}"])
    took = time.monotonic() - t0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and "--address" in err[0] and "within 2 s" in err[0], err
    assert took < 10 and not out.exists()


def test_a_listening_cluster_is_found_at_once_and_a_malformed_address_is_named():
    import socket
    import time

    from torchskin.dataset.generate import wait_for_cluster

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        t0 = time.monotonic()
        wait_for_cluster(f"ray://127.0.0.1:{s.getsockname()[1]}", timeout_s=5.0)
        assert time.monotonic() - t0 < 1.0
    for bad in ("head", "head:", "head:99999", ":6379"):
        with pytest.raises(ValueError, match="--address must be host:port"):
            wait_for_cluster(bad)


# ------------------------------------------------------------------------------------------------ onboard
from pathlib import Path  # noqa: E402

DET = str(Path(__file__).resolve().parents[1] / "exports" / "detector.onnx")
CFG = ["--sun-zenith", "40", "--camera-zenith", "30", "--relative-azimuth", "60", "--diffuse-share", "0.2"]  # the shipped lut takes the share


def _skin_cube(h=20, w=20):
    """A reflectance frame: a skin patch (rows 5-14, columns 5-14) on a grey background."""
    cube = np.full((4, h, w), 0.2, dtype=np.float32)
    cube[:, 5:15, 5:15] = np.array([0.25, 0.35, 0.55, 0.15], dtype=np.float32)[:, None, None]
    return cube


def _one_line(capsys, rc):
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and out == "" and len(lines) == 1, (rc, out, err)
    return lines[0]


@pytest.mark.parametrize("scale,hint", [(13142 / 0.55, "digital numbers"), (100.0, "per cent")],
                         ids=["digital numbers", "per cent"])
def test_detect_on_a_cube_that_is_not_reflectance_is_refused_with_a_hint(tmp_path, capsys, scale, hint):
    """``detect`` on ``signal.npy`` (DN up to 13,142) or on a cube in per cent used to exit 0 with skin pixels."""
    from torchskin.cli import main

    np.save(tmp_path / "c.npy", _skin_cube() * np.float32(scale))  # max 13,142 DN, resp. 55 %
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(tmp_path / "c.npy"), *CFG]))
    assert hint in line and "1.5" in line, line


@pytest.mark.parametrize("tile", [65536, 1024], ids=["one call", "tiled"])
def test_a_calibrated_frame_with_a_glint_is_detected_and_one_in_per_cent_is_not(tile):
    """A sun glint (water, glass) reads several times 1 in a few pixels of a calibrated frame: the frame is
    detected, its other pixels as without the glint; a frame with 2 % of its values above 1.5 is refused,
    on the one-call path and on the tiled one."""
    from torchskin.onboard import REFLECTANCE_MAX, REFLECTANCE_MAX_SHARE, OnboardDetector

    det = OnboardDetector(DET, tile=tile)
    cfg = np.array([[40.0, 30.0, 60.0, 0.2]])
    cube = np.tile(_skin_cube(), (1, 4, 4))[None]  # (1, 4, 80, 80): 6,400 pixels, several tiles of 1024
    clean = det(cube, cfg)["mask"]
    glint = cube.copy()
    glint[0, :, 0, :3] = 6.0  # 3 pixels of 6,400
    res = det(glint, cfg)["mask"]
    assert (res[0, 1:] == clean[0, 1:]).all() and res[0, 1:].any()
    many = cube.copy()
    k = int(2 * REFLECTANCE_MAX_SHARE * many[0, 0].size)
    many[0, :, 40, :] = 6.0  # one row of 80 pixels per band ...
    many[0, :, 41:41 + (k - 80) // 80 + 1, :] = 6.0  # ... and more, about 2 % of the values in all
    assert (many > REFLECTANCE_MAX).mean() > REFLECTANCE_MAX_SHARE
    with pytest.raises(ValueError, match="per cent"):
        det(many, cfg)


def test_detect_refuses_reflectance_far_below_zero_even_when_clipping(tmp_path, capsys):
    """--clip-negative is for noise on dark pixels (about -0.001), not for a cube with an offset (-0.5)."""
    from torchskin.cli import main

    cube = _skin_cube() - np.float32(0.7)
    np.save(tmp_path / "c.npy", cube)
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", str(tmp_path / "c.npy"), *CFG,
                                   "--clip-negative"]))
    assert "far below 0" in line, line


def test_the_detector_refuses_out_of_meaning_values_on_the_tiled_path_too():
    """Frames larger than a tile run tile by tile (and in threads); the range check holds there as well: a
    single bright value (a glint) passes, a band in per cent is refused, an offset far below 0 too."""
    from torchskin.onboard import OnboardDetector

    det = OnboardDetector(DET, threads=2, tile=1024)
    cube = np.tile(_skin_cube(), (1, 4, 4))[None]  # 80 x 80: 7 tiles
    out = det(cube, [40.0, 30.0, 60.0, 0.2])
    assert out["mask"].sum() > 0
    cube[0, 2, 70, 70] = 1.6  # one value in the last tile: a glint
    glint = det(cube, [40.0, 30.0, 60.0, 0.2])["mask"]
    glint[0, 70, 70] = out["mask"][0, 70, 70]  # the glint pixel itself may change its verdict, no other
    assert (glint == out["mask"]).all()
    percent = cube.copy()
    percent[0, 3] *= 100  # one band in per cent: a quarter of the values
    with pytest.raises(ValueError, match="per cent"):
        det(percent, [40.0, 30.0, 60.0, 0.2])
    low = cube.copy()
    low[0, 1, 75, 75] = -0.5  # one value in the last tile: no noise reads that
    with pytest.raises(ValueError, match="far below 0"):
        det(low, [40.0, 30.0, 60.0, 0.2], negative="clip")
    cube[0, 2, 70, 70] = -0.05  # noise: clipped, accepted
    assert "clipped_values" in det(cube, [40.0, 30.0, 60.0, 0.2], negative="clip")


@pytest.mark.parametrize("dtype", ["<f8", ">f8", "<f2", ">f4", "<f4"])
def test_detect_reads_every_float_dtype_and_byte_order_alike(tmp_path, capsys, dtype):
    """``detect`` used to refuse float64, float16 and big-endian float32 ("must be float32 ... got >f4") while
    ``calibrate`` converted them: the same cube in any float dtype gives the same mask."""
    import json

    from torchskin.cli import main

    np.save(tmp_path / "c.npy", _skin_cube().astype(dtype))
    assert main(["detect", "--model", DET, "--cube", str(tmp_path / "c.npy"), *CFG, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100


@pytest.mark.parametrize("dtype", ["<f8", ">f4", "<f2", "<u2"])
def test_calibrate_reads_every_dtype_alike(tmp_path, capsys, dtype):
    from torchskin.cli import main

    dn = np.full((4, 20, 20), 500.0, dtype=np.float64)
    dn[:, :5, :5], dn[:, -5:, -5:] = 9700.0, 300.0  # panels 0.97 and 0.03 with gain 10000, offset 0
    np.save(tmp_path / "dn.npy", dn.astype(dtype))
    assert main(["calibrate", "--cube", str(tmp_path / "dn.npy"), "--panel", "0:5:0:5=0.97", "--panel",
                 "15:20:15:20=0.03", "--out", str(tmp_path / "r.npy")]) == 0
    capsys.readouterr()
    r = np.load(tmp_path / "r.npy")
    assert r.dtype == np.float32 and r[:, 10, 10] == pytest.approx([0.05] * 4, abs=1e-3)


@pytest.mark.parametrize("second", ["0:5:0:5=0.5", "2:7:2:7=0.5"], ids=["same region", "overlapping"])
def test_calibrate_refuses_the_same_or_overlapping_panel_regions(tmp_path, capsys, second):
    """The same region given twice (= 0.97 and = 0.5) used to exit 0 with reflectance from -0.157 to 0.874."""
    from torchskin.cli import main

    dn = np.full((4, 20, 20), 500.0, dtype=np.float32)
    np.save(tmp_path / "dn.npy", dn)
    line = _one_line(capsys, main(["calibrate", "--cube", str(tmp_path / "dn.npy"), "--panel", "0:5:0:5=0.97",
                                   "--panel", second, "--out", str(tmp_path / "r.npy")]))
    assert "panel regions 0:5:0:5 and" in line and ("same region" in line or "overlap" in line), line
    assert not (tmp_path / "r.npy").exists()


def test_calibrate_reports_the_fit_residual(tmp_path, capsys):
    """With three panels, one of them off the line (its reflectance mistyped), the residual says so."""
    import json

    from torchskin.cli import main

    dn = np.full((4, 30, 30), 500.0, dtype=np.float32)
    dn[:, :5, :5], dn[:, 10:15, 10:15], dn[:, -5:, -5:] = 9700.0, 5000.0, 300.0
    np.save(tmp_path / "dn.npy", dn)
    argv = ["calibrate", "--cube", str(tmp_path / "dn.npy"), "--panel", "0:5:0:5=0.97", "--panel",
            "25:30:25:30=0.03", "--out", str(tmp_path / "r.npy")]
    assert main([*argv, "--panel", "10:15:10:15=0.5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["residual"] == pytest.approx([0.0] * 4, abs=1e-9)
    assert main([*argv, "--panel", "10:15:10:15=0.3", "--json"]) == 0  # should have been 0.5
    assert min(json.loads(capsys.readouterr().out)["residual"]) > 0.05
    assert main([*argv, "--panel", "10:15:10:15=0.3"]) == 0
    assert "residual 0." in capsys.readouterr().out


@pytest.mark.parametrize("command", ["detect", "calibrate"])
def test_a_huge_cube_that_is_cut_short_is_refused_from_its_header(tmp_path, capsys, command):
    """A 4 x 20000 x 20000 float32 cube (6.4 GB) used to be loaded whole by ``detect``, then was refused above a
    16-megapixel cap. ``detect`` and ``calibrate`` now stream one frame in row tiles (issue 24: streaming replaces
    the cap for them; ``test_cubefiles`` bounds the memory), so such a header is fine, but this file holds the
    header only: refused from the header before any data is mapped, as truncated, nothing written."""
    from torchskin.cli import main

    p = tmp_path / "big.npy"
    with open(p, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False,
                                                  "shape": (4, 20000, 20000)})
    argv = ["--cube", str(p), *(CFG if command == "detect" else ["--panel", "0:5:0:5=0.97", "--panel",
                                                                 "9:12:9:12=0.03"])]
    out = tmp_path / ("m.png" if command == "detect" else "r.npy")
    extra = ["--model", DET] if command == "detect" else []
    line = _one_line(capsys, main([command, *extra, *argv, "--out", str(out)]))
    assert "truncated" in line and "4 x 20000 x 20000" in line and "big.npy" in line, line
    assert sorted(f.name for f in tmp_path.iterdir()) == ["big.npy"]


def test_max_megapixels_caps_a_batch_read_whole_and_not_a_streamed_frame(tmp_path, capsys):
    """``--max-megapixels`` caps what is read whole, as for render: a (B, 4, H, W) batch. One frame streams in
    row tiles (issue 24), so the cap no longer refuses it: the same mask either way."""
    import json

    from torchskin.cli import main

    np.save(tmp_path / "b.npy", _skin_cube()[None])  # a batch of one 400-pixel frame
    argv = ["detect", "--model", DET, "--cube", str(tmp_path / "b.npy"), *CFG, "--json"]
    assert "--max-megapixels" in _one_line(capsys, main([*argv, "--max-megapixels", "0.0001"]))
    assert main([*argv, "--max-megapixels", "0.0004"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100
    np.save(tmp_path / "c.npy", _skin_cube())
    one = ["detect", "--model", DET, "--cube", str(tmp_path / "c.npy"), *CFG, "--json", "--tile-rows", "3"]
    assert main([*one, "--max-megapixels", "0.0001"]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == 100


def test_the_onboard_path_still_imports_no_torch(tmp_path):
    import subprocess
    import sys

    np.save(tmp_path / "c.npy", _skin_cube().astype(">f8"))
    argv = ["detect", "--model", DET, "--cube", str(tmp_path / "c.npy"), *CFG]
    code = (f"import sys; from torchskin.cli import main; rc = main({argv!r}); "
            "assert 'torch' not in sys.modules, 'torch imported'; sys.exit(rc)")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_render_calls_a_grazing_sun_frame_invalid_as_the_dataset_does(tmp_path, capsys):
    """``render`` with a sun 87° from the zenith, off to the side of a camera 30° from the zenith: the panels
    are sunlit, but the line through them is not the scene's; render.json says elm_valid false (as the dataset generator would) and the warning says why."""
    import json

    from torchskin.cli import main

    out = tmp_path / "r"
    argv = ["render", "--out", str(out), "--width", "48", "--height", "48", "--json", "--camera-zenith", "30",
            "--source-azimuth", "90"]
    assert main([*argv, "--source-zenith", "87"]) == 0
    cap = capsys.readouterr()
    doc = json.loads((out / "render.json").read_text())["summary"]
    assert min(doc["panel_sunlit_fraction"]) >= 0.5 and doc["elm_line_valid"] and not doc["elm_valid"]
    assert doc["panel_irradiance_ratio"] > ELM_MAX_IRRADIANCE_RATIO
    assert "times their irradiance" in cap.err and "not sunlit" not in cap.err
    assert main([*argv, "--source-zenith", "30", "--overwrite"]) == 0  # the same folder: the earlier frame replaced
    cap = capsys.readouterr()
    assert json.loads(cap.out)["elm_valid"] and "warning" not in cap.err


# ------------------------------------------------------------------------------- provenance: one world per artefact
BOUNDARIES_PT = Path(__file__).resolve().parents[1] / "exports" / "boundaries.pt"


def _other_world(tmp_path, surface="conserving"):
    """A copy of the shipped box checkpoint whose training summary says it was trained on a dataset rendered
    with another skin surface model (what ``torchskin train`` on a ``--surface conserving`` dataset records)."""
    ck = torch.load(BOUNDARIES_PT, map_location="cpu", weights_only=True)
    ck["meta"] = {**ck["meta"], "surface": surface, "training_manifest_sha256": "c" * 64, "data": "data-conserving"}
    path = tmp_path / "C.pt"
    torch.save(ck, path)
    return path


def _onnx_meta(path):
    import onnx

    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def test_export_of_checkpoints_from_two_worlds_is_refused_and_recorded_when_allowed(tmp_path, capsys):
    """A user exports a thesis-surface --model with a --detector trained on a conserving-surface dataset: the
    graphs used to all say skin_surface_model=thesis with --model's manifest hash. Refused in one line; with
    --allow-mixed-worlds every graph records its own checkpoint's world, and the flag."""
    from torchskin.cli import main

    other, out = _other_world(tmp_path), tmp_path / "ex"
    line = _one_line(capsys, main(["export", "--model", str(BOUNDARIES_PT), "--detector", str(other),
                                   "--out", str(out)]))
    assert "different worlds" in line and "--detector conserving" in line and "--model thesis" in line, line
    assert not out.exists()
    assert main(["export", "--model", str(BOUNDARIES_PT), "--detector", str(other), "--out", str(out),
                 "--allow-mixed-worlds"]) == 0
    capsys.readouterr()
    b, d = _onnx_meta(out / "boundaries.onnx"), _onnx_meta(out / "detector.onnx")
    own = torch.load(BOUNDARIES_PT, map_location="cpu", weights_only=True)["meta"]
    assert (b["skin_surface_model"], b["training_manifest_sha256"]) == ("thesis", own["training_manifest_sha256"])
    assert (d["skin_surface_model"], d["training_manifest_sha256"]) == ("conserving", "c" * 64)
    assert "mixed_worlds" in b and b["mixed_worlds"] == d["mixed_worlds"]
    card = (out / "detector.md").read_text()
    assert "c" * 64 in card and "`conserving`" in card and own["training_manifest_sha256"] not in card


def test_export_of_one_world_records_it_as_before(tmp_path, capsys):
    """The shipped combination (one world) exports without the flag and without a mixed_worlds key."""
    from torchskin.cli import main

    out = tmp_path / "ex"
    assert main(["export", "--model", str(BOUNDARIES_PT), "--out", str(out)]) == 0
    capsys.readouterr()
    assert "mixed_worlds" not in _onnx_meta(out / "detector.onnx")


def test_evaluate_warns_when_a_model_comes_from_another_world(tmp_path, capsys, subject_obj):
    """``evaluate --data <thesis-surface dataset> --model <conserving-surface model>`` used to report its Pd
    with no word: one warning line on stderr naming the model and both worlds, and the same in the JSON."""
    import json

    from torchskin.cli import main
    from torchskin.dataset.generate import generate

    data = tmp_path / "d"
    generate(_cfg(subject_obj, 40.0, "spectralon"), 6, 0, data, quiet=True)
    other = _other_world(tmp_path)
    assert main(["evaluate", "--data", str(data), "--model", str(other), "--json"]) == 0
    cap = capsys.readouterr()
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("torchskin evaluate: warning: ") and str(other) in lines[0], lines
    assert "skin surface model conserving (the data: thesis)" in lines[0]
    assert json.loads(cap.out)["warnings"] == [lines[0].removeprefix("torchskin evaluate: warning: ")]
    assert main(["evaluate", "--data", str(data), "--model", str(BOUNDARIES_PT), "--json"]) == 0
    cap = capsys.readouterr()
    assert "warning" not in cap.err and "warnings" not in json.loads(cap.out)


# ---------------------------------------------------------------------------------- a pip user without an extra
@pytest.mark.parametrize("module", ["onnxruntime", "open3d", "pvlib", "anny", "earthlib", "ray", "spectral",
                                    "tifffile"])
def test_a_command_whose_extra_is_missing_names_the_extra(tmp_path, module):
    """A pip user without the extra ran ``detect`` (or ``render``) and got
    "unexpected ModuleNotFoundError: No module named 'onnxruntime'" with no hint: the line names the extra.
    Every missing package gives the same line and status (1): pvlib, anny, earthlib and ray used to answer
    in their own words with status 2, and generate started its progress bar before earthlib was missed."""
    import subprocess
    import sys

    from torchskin.errors import EXTRAS

    code = ("import sys, builtins\n"
            f"real = builtins.__import__\n"
            f"def fake(name, *a, **k):\n"
            f"    if name.partition('.')[0] == {module!r}: raise ModuleNotFoundError(f'No module named {{name!r}}', name=name)\n"
            f"    return real(name, *a, **k)\n"
            "builtins.__import__ = fake\n"
            "from torchskin.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    np.save(tmp_path / "c.npy", _skin_cube())
    inputs = ["c.npy"]
    if module == "spectral":  # an ENVI cube, written by hand (the header is text)
        (tmp_path / "c.hdr").write_text("ENVI\nsamples = 20\nlines = 20\nbands = 4\nheader offset = 0\n"
                                        "data type = 4\ninterleave = bsq\nbyte order = 0\n"
                                        "wavelength units = nm\nwavelength = {544, 633, 1080, 1580}\n")
        (tmp_path / "c.img").write_bytes(_skin_cube().astype("<f4").tobytes())
        inputs += ["c.hdr", "c.img"]
    if module == "tifffile":  # a GeoTIFF cube, written here with tifffile, missed by the command
        pytest.importorskip("tifffile").imwrite(tmp_path / "c.tif", _skin_cube(), photometric="minisblack",
                                                planarconfig="separate")  # the bands as one page's planes
        inputs += ["c.tif"]
    argv = {"onnxruntime": ["detect", "--model", DET, "--cube", "c.npy", *CFG],  # the onboard path itself
            "spectral": ["detect", "--model", DET, "--cube", "c.hdr", *CFG, "--out", "m.png"],
            "tifffile": ["detect", "--model", DET, "--cube", "c.tif", *CFG, "--out", "m.png"],
            "open3d": ["render", "--out", "r", "--width", "16", "--height", "16"],
            "pvlib": ["render", "--out", "r", "--width", "16", "--height", "16"],
            "anny": ["render", "--out", "r", "--width", "16", "--height", "16", "--illumination", "thesis"],
            "earthlib": ["generate", "--configs", "48", "--out", "d"],
            "ray": ["generate", "--configs", "48", "--out", "d", "--backend", "ray", "--address", "127.0.0.1:1"]}[module]
    command = argv[0]
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env={**__import__("os").environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert r.returncode == 1 and r.stdout == "", (r.returncode, r.stdout, r.stderr)
    if module in EXTRAS:
        dist, extra = EXTRAS[module]
        want = (f"this command needs {dist}: pip install 'torchskin[{extra}]' (or 'torchskin[all]' for every "
                "command)")
    else:  # a base requirement (onnxruntime runs the onboard path): only an install with --no-deps lacks it
        want = (f"this command needs {module}, a requirement of torchskin that is not installed: pip install "
                f"{module} (an install with --no-deps leaves it out)")
    assert r.stderr.strip().splitlines() == [f"torchskin {command}: error: {want}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(inputs)  # nothing written


def test_every_optional_package_is_in_the_extra_the_error_names():
    """``errors.EXTRAS`` and pyproject's extras agree: each named extra lists the package, and ``all`` holds every
    extra a command needs."""
    import re
    import tomllib

    from torchskin.errors import EXTRAS

    extras = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    names = {k: {re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() for r in v} for k, v in extras.items()}
    for module, (dist, extra) in EXTRAS.items():
        assert dist in names[extra], (module, dist, extra)
        assert extra in extras["all"][0], (module, extra)
    from torchskin.errors import BASE

    base = {re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() for r in tomllib.loads(
        (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]["dependencies"]}
    assert set(BASE.values()) <= base and not set(BASE) & set(EXTRAS)
    assert "onnxruntime" in base  # pip install torchskin runs detect (issue 23)


# ------------------------------------------------------------------------------ bands mean wavelengths everywhere
def _reordered(tmp_path, order):
    """The skin cube with its bands in ``order`` (indices into 544, 633, 1080, 1580 nm), saved as c.npy."""
    cube = _skin_cube()[list(order)]
    np.save(tmp_path / "c.npy", cube)
    return str(tmp_path / "c.npy"), [[544, 633, 1080, 1580][i] for i in order]


@pytest.mark.parametrize("how", ["--bands", "sidecar"])
def test_detect_reads_a_cube_in_another_band_order_by_its_wavelengths(tmp_path, capsys, how):
    """A cube written 1580, 544, 1080, 633 used to be read as 544, 633, 1080, 1580 and gave 0 skin pixels
    instead of the right count: its wavelengths (``--bands`` or the sidecar) put the bands in the model's order."""
    import json

    from torchskin.cli import main
    from torchskin.io import bands_sidecar_text, sidecar_path

    ref, _ = _reordered(tmp_path, (0, 1, 2, 3))
    assert main(["detect", "--model", DET, "--cube", ref, *CFG, "--json"]) == 0
    want = json.loads(capsys.readouterr().out)["skin_pixels"]
    assert want == 100
    other = tmp_path / "o"
    other.mkdir()
    path, bands = _reordered(other, (3, 0, 2, 1))
    extra = ["--bands", ",".join(map(str, bands))] if how == "--bands" else []
    if how == "sidecar":
        sidecar_path(path).write_text(bands_sidecar_text(bands))
    assert main(["detect", "--model", DET, "--cube", path, *CFG, "--json", *extra]) == 0
    assert json.loads(capsys.readouterr().out)["skin_pixels"] == want


@pytest.mark.parametrize("batch", [False, True], ids=["one frame", "a batch"])
def test_a_cube_without_wavelengths_is_read_in_the_models_order_and_detect_says_so(tmp_path, capsys, batch):
    """A user saves a cube in another band order with np.save and no sidecar: nothing can tell its order, so
    detect reads it as the model's, and says so in one warning line (stderr and the JSON's "warnings"), naming the
    bands it assumed; the same cube with its sidecar gets no warning."""
    import json

    from torchskin.cli import main
    from torchskin.io import bands_sidecar_text, sidecar_path

    # 633, 544, 1580, 1080 nm: read in the model's order, 1580 nm outshines 1080 nm, which no skin does (1580, 544,
    # 1080, 633 nm would not do: read in order it is what Type VI skin reads at grazing incidence)
    path, bands = _reordered(tmp_path, (1, 0, 3, 2))
    if batch:
        np.save(path, np.load(path)[None])
    assert main(["detect", "--model", DET, "--cube", path, *CFG, "--json"]) == 0
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("torchskin detect: warning: ") and "544, 633, 1080, 1580 nm" in lines[0]
    assert "no wavelengths" in lines[0] and path in lines[0], lines
    doc = json.loads(cap.out)
    assert doc["warnings"] == [lines[0].removeprefix("torchskin detect: warning: ")] and doc["skin_pixels"] == 0
    sidecar_path(path).write_text(bands_sidecar_text(bands))
    assert main(["detect", "--model", DET, "--cube", path, *CFG, "--json"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and "warnings" not in json.loads(cap.out) and json.loads(cap.out)["skin_pixels"] == 100


@pytest.mark.parametrize("bands,needle", [("544,633,1080", "gives 3 bands"), ("544,633,1080,1550", "1580 nm"),
                                          ("0.544,0.633,1.08,1.58", "micrometres"), ("544,544,1080,1580", "twice")],
                         ids=["count", "missing band", "micrometres", "duplicate"])
def test_detect_refuses_a_cube_whose_bands_do_not_match_the_model(tmp_path, capsys, bands, needle):
    from torchskin.cli import main

    path, _ = _reordered(tmp_path, (0, 1, 2, 3))
    out = tmp_path / "m.png"
    line = _one_line(capsys, main(["detect", "--model", DET, "--cube", path, *CFG, "--bands", bands,
                                   "--out", str(out)]))
    assert needle in line, line
    assert not out.exists()


def test_render_writes_the_cubes_wavelengths_and_calibrate_carries_them(tmp_path, capsys):
    """``render`` writes reflectance.bands.json and signal.bands.json beside its cubes; ``calibrate`` of the
    signal writes the same wavelengths beside its reflectance cube, which ``detect`` then reads."""
    import json

    from torchskin.cli import main
    from torchskin.io import read_bands_sidecar, sidecar_path

    out = tmp_path / "r"
    assert main(["render", "--out", str(out), "--width", "48", "--height", "48", "--no-ground"]) == 0
    capsys.readouterr()
    for cube in ("reflectance", "signal"):
        assert read_bands_sidecar(out / f"{cube}.npy") == [544.0, 633.0, 1080.0, 1580.0]
        assert json.loads(sidecar_path(out / f"{cube}.npy").read_text())["quantity"] == cube
    doc = json.loads((out / "render.json").read_text())
    panels = [f"{':'.join(map(str, v['region']))}={v['reference'][0][0][0]}" for v in doc["panels"].values()]
    refl = tmp_path / "refl.npy"
    argv = ["calibrate", "--cube", str(out / "signal.npy"), "--out", str(refl)]
    assert main([*argv, *[x for p in panels for x in ("--panel", p)]]) == 0
    capsys.readouterr()
    assert read_bands_sidecar(refl) == [544.0, 633.0, 1080.0, 1580.0]

def test_a_dataset_given_as_the_model_is_named_as_such(tmp_path, capsys):
    """``evaluate --data D --model D`` (the folder twice) said the model file "does not exist"."""
    from torchskin.cli import main

    data = tmp_path / "d"
    data.mkdir()
    (data / "_manifest.json").write_text("{}")
    line = _one_line(capsys, main(["evaluate", "--data", str(data), "--model", str(data)]))
    assert "is a folder (a dataset: pass it as --data)" in line and "does not exist" not in line, line
