"""Dataset generation: determinism, shards and manifest, verify/resume, crash safety, readers."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import rows_with_pixels  # a row's frame pixel

from torchskin.cli import main
from torchskin.dataset.config import resolve_config
from torchskin.dataset.generate import MANIFEST, generate
from torchskin.dataset.verify import verify
from torchskin.render.kernels import compiler_available


def small_cfg(obj, **over):
    o = {"camera": {"width": 64, "height": 64, "range_m": [5.0, 20.0]}, "sun": {"per_pose": 3},
         "skin": {"per_pose": 2}, "subject": {"meshes": [str(obj)]},
         "sampling": {"groups_per_shard": 1, "pixels_per_class": 16}, "confusers": {"count": [2, 3]}}
    for k, v in over.items():
        o.setdefault(k, {}).update(v)
    return resolve_config(o)


def checksums(d):
    return {s["name"]: s["sha256"] for s in json.loads((d / MANIFEST).read_text())["shards"]}


@pytest.mark.slow
def test_same_seed_same_bytes_and_balanced_classes(tmp_path, subject_obj):
    cfg = small_cfg(subject_obj)
    a = generate(cfg, 18, 1, tmp_path / "a", quiet=True)
    generate(cfg, 18, 1, tmp_path / "b", quiet=True)
    generate(cfg, 18, 2, tmp_path / "c", quiet=True)
    assert a["groups"] == 3 and a["n_shards"] == 3
    assert checksums(tmp_path / "a") == checksums(tmp_path / "b")
    assert checksums(tmp_path / "a") != checksums(tmp_path / "c")
    import pandas as pd
    import pyarrow.dataset as ds

    df = pd.read_parquet(tmp_path / "a")
    assert len(df) == sum(s["rows"] for s in a["shards"]) == ds.dataset(tmp_path / "a").count_rows()
    counts = df.groupby(["group", "sun", "skin", "label"]).size().unstack()
    assert (counts[True] == counts[False]).all()  # balanced per configuration
    # one set of pixels per pose group: every sun x skin of a group shades the same pixels, so a row's view angle
    # (camera and pixel only) repeats across the group's configurations, while its incidence angle follows the sun
    views = df.groupby(["group", "sun", "skin"]).theta_r_deg.apply(tuple).groupby("group").nunique()
    assert (views == 1).all()
    incid = df.groupby(["group", "sun"]).theta_i_deg.apply(tuple).groupby("group").nunique()
    assert (incid == 3).all()
    assert set(df.columns) >= {"sun_zenith_deg", "theta_i_deg", "r1580", "ndsi", "shadow", "label"}
    skin = df[df.label & ~df.shadow]
    assert skin.ndsi.median() > 0.5  # skin pixels look like skin at 1080/1580 nm
    from torchskin.confusers import partition

    conf = df[df.confuser != ""]
    assert len(conf) > 0 and not conf.label.any()
    assert all(partition(n) == "train" for n in conf.confuser.unique())


@pytest.mark.slow
def test_verify_and_resume_repair_shards(tmp_path, subject_obj, capsys):
    cfg = small_cfg(subject_obj)
    d = tmp_path / "ds"
    generate(cfg, 24, 0, d, quiet=True)
    good = checksums(d)
    assert verify(d)["ok"]
    shards = sorted(d.glob("shard-*.parquet"))
    raw = bytearray(shards[0].read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    shards[0].write_bytes(bytes(raw))  # flipped byte
    shards[1].write_bytes(shards[1].read_bytes()[:100])  # truncated
    shards[2].unlink()  # missing
    (d / ".shard-00003.parquet.abc.tmp").write_bytes(b"partial")
    rep = verify(d)
    assert not rep["ok"] and rep["missing"] == [shards[2].name]
    assert rep["corrupted"] == [shards[0].name, shards[1].name] and rep["partial"]
    assert main(["dataset", "verify", str(d)]) == 1
    capsys.readouterr()
    with pytest.raises(ValueError, match="not empty"):
        generate(cfg, 24, 0, d, quiet=True)
    generate(cfg, 24, 0, d, resume=True, quiet=True)
    assert checksums(d) == good and verify(d)["ok"]
    assert main(["dataset", "verify", str(d), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"]


@pytest.mark.slow
def test_sigkill_mid_run_then_resume_gives_the_same_dataset(tmp_path, subject_obj):
    cfgfile = tmp_path / "cfg.toml"
    cfgfile.write_text(
        '[camera]\nwidth = 64\nheight = 64\nrange_m = [5.0, 20.0]\n[sun]\nper_pose = 3\n[skin]\nper_pose = 2\n'
        f'[subject]\nmeshes = ["{subject_obj}"]\n[sampling]\ngroups_per_shard = 1\npixels_per_class = 16\n')
    args = ["generate", "--config", str(cfgfile), "--configs", "60", "--seed", "5", "--quiet"]
    ref = tmp_path / "ref"
    assert main([*args, "--out", str(ref)]) == 0
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "torchskin.cli", *args, "--out", str(run)], env=env)
    t0 = time.time()
    while time.time() - t0 < 120 and len(list(run.glob("shard-*.parquet"))) < 3:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(list(run.glob("shard-*.parquet"))) < 10  # it was killed mid-run
    assert main([*args, "--out", str(run), "--resume"]) == 0
    assert checksums(run) == checksums(ref)
    assert verify(run)["ok"]


def test_bad_inputs_write_nothing(tmp_path, subject_obj, capsys):
    out = tmp_path / "x"
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nzoom = 3\n")
    assert main(["generate", "--config", str(bad), "--configs", "5", "--out", str(out)]) == 2
    assert "unknown config key camera.zoom" in capsys.readouterr().err
    assert not out.exists()
    bad.write_text("[sun]\nzenith_deg = [50.0, 10.0]\n")
    assert main(["generate", "--config", str(bad), "--out", str(out)]) == 2
    assert "min 50 > max 10" in capsys.readouterr().err
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    cfg = small_cfg(subject_obj)
    with pytest.raises(ValueError, match="not empty"):
        generate(cfg, 6, 0, out, quiet=True)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_full_disk_stops_with_a_clear_error_and_no_partial_shard(tmp_path, subject_obj, monkeypatch):
    import errno

    import pyarrow.parquet as pq

    real = pq.write_table

    def full_disk(table, where, **kw):
        real(table, where, **kw)  # bytes reach the temporary file, then the disk fills up
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pq, "write_table", full_disk)
    out = tmp_path / "full"
    with pytest.raises(ValueError, match="shard-00000.parquet .* failed: No space left on device"):
        generate(small_cfg(subject_obj), 6, 0, out, quiet=True)
    assert not out.exists()  # no shard finished: the folder is left as it was found (it did not exist)
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="No space left"):
        generate(small_cfg(subject_obj), 6, 0, out, quiet=True, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]  # no manifest, shard or temporary left


@pytest.mark.slow
def test_peak_memory_does_not_grow_with_the_number_of_configurations(tmp_path, subject_obj):
    cfgfile = tmp_path / "cfg.toml"
    cfgfile.write_text(
        '[camera]\nwidth = 32\nheight = 32\nrange_m = [5.0, 20.0]\n[sun]\nper_pose = 3\n[skin]\nper_pose = 2\n'
        f'[subject]\nmeshes = ["{subject_obj}"]\n[sampling]\ngroups_per_shard = 5\npixels_per_class = 8\n'
        '[confusers]\ncount = [0, 0]\n')
    peaks = []
    for n in (100, 1000):  # each run measured in a fresh parent, so no other child's peak mixes in
        cmd = [sys.executable, "-m", "torchskin.cli", "generate", "--config", str(cfgfile), "--configs", str(n),
               "--out", str(tmp_path / f"d{n}"), "--quiet"]
        probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True); "
                 "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
        r = subprocess.run([sys.executable, "-c", probe, *cmd], check=True, capture_output=True, text=True)
        peaks.append(int(r.stdout.strip().splitlines()[-1]))
    assert len(list((tmp_path / "d1000").glob("shard-*.parquet"))) == 34  # 1000 / (6 x 5) per shard, rounded up
    assert peaks[1] < 1.2 * peaks[0], peaks


@pytest.mark.slow
def test_images_option_stores_cubes_matching_the_rows(tmp_path, subject_obj, monkeypatch):
    """Every Parquet row is its configuration's cube pixel, found by the row's local angles and material.

    The rows come from a pixel render (``render_pixels``) and the cubes from a full-frame render of the same
    G-buffer. Noise and quantization are switched off here (noise through the config, quantization by wrapping
    ``group_sensor``): what is left is float16 storage. With them on, the cubes reuse the rows' exposure, noise and
    empirical line (``generate.frame_cubes``; tests/test_dataset_user_mistakes.py)."""
    import dataclasses

    import pandas as pd

    import torchskin.dataset.generate as gen
    from torchskin.dataset.schema import BAND_COLUMNS

    sensor = gen.group_sensor
    monkeypatch.setattr(gen, "group_sensor", lambda g, light=None: dataclasses.replace(sensor(g, light), quantize=False))
    # non-square (W 64, H 48): the cube's last two axes must be (H, W)
    cfg = small_cfg(subject_obj, camera={"width": 64, "height": 48}, sensor={"noise": False})
    d = tmp_path / "img"
    man = generate(cfg, 12, 3, d, quiet=True, images=True)
    e = man["shards"][0]["images"]
    cube = np.load(d / e["name"])
    assert cube.dtype == np.float16
    assert list(cube.shape) == e["shape"] == [1, 2, 3, 4, 48, 64]  # groups, skins, suns, bands, H, W
    df = pd.read_parquet(d / man["shards"][0]["name"])
    assert len(df) == 2 * 3 * 2 * 16  # skins x suns x (16 skin + 16 other pixels)

    # the pixel of each row, from its local angles and material (conftest.rows_with_pixels)
    for k, s, rows, px in rows_with_pixels(cfg, 3, df):
        stored = cube[0, k, s].reshape(4, -1).T[px].astype(np.float64)  # (rows, bands)
        r = rows[list(BAND_COLUMNS)].to_numpy(np.float64)
        assert np.isfinite(r).all() and np.isfinite(stored).all()
        # float16 rounding: half a unit in the last place, <= 2^-11 |x| (normal) or 2^-25 (subnormal); the
        # float32 renders of the two paths add a few float32 ulps (2^-24 |x| each)
        tol = (2.0 ** -11 + 4 * 2.0 ** -24) * np.abs(r) + 2.0 ** -25
        assert (np.abs(stored - r) <= tol).all(), (k, s, np.abs(stored - r).max())

    assert verify(d)["ok"]
    (d / e["name"]).write_bytes(b"x")
    rep = verify(d)
    assert rep["corrupted"] == [e["name"]]
    generate(cfg, 12, 3, d, quiet=True, images=True, resume=True)
    assert verify(d)["ok"]
    assert np.array_equal(np.load(d / e["name"]), cube, equal_nan=True)  # the resumed shard is the same cube


def test_elm_validity_follows_panel_sunlight(tmp_path, subject_obj):
    """Level panels: lit by any sun above the horizon, not by one below it, and not when the subject's
    shadow covers them (a grazing sun straight along the panel-subject line)."""
    import math

    import numpy as np
    import torch

    from torchskin.dataset.config import sample_group
    from torchskin.dataset.generate import group_scene, panels_sunlit
    from torchskin.render.raycast import Raycaster

    g = sample_group(small_cfg(subject_obj, camera={"zenith_deg": [30.0, 30.0]}), 0, 0)
    sc = group_scene(g)
    az = math.radians(g.camera["azimuth_deg"])
    side = np.array([-math.sin(az), math.cos(az), 0.0])  # the white panel sits at +0.9 m along this
    zen = math.radians(89.0)
    dirs = np.stack([[0.0, 0.0, 1.0],                                          # overhead
                     [*(math.sin(math.radians(60)) * np.array([math.cos(az), math.sin(az)])), 0.5],
                     [*(-side[:2] * math.sin(zen)), math.cos(zen)],             # grazing, behind the subject
                     [0.6, 0.0, -0.8]])                                         # below the horizon
    gb = Raycaster.from_scene(sc).gbuffer(sc.cameras, dirs)
    ok = panels_sunlit(gb, list(sc.panels), torch.tensor(dirs, dtype=torch.float32))
    assert ok.tolist() == [True, True, False, False]


@pytest.mark.parametrize("camera_zenith", [50.0, 80.0, 90.0])
def test_panels_stay_visible_down_to_a_horizontal_camera(subject_obj, camera_zenith):
    """Level panels up to a 70° camera zenith; below 20° camera elevation they turn towards the camera just
    enough that it sees them 70° off their normal (a horizontal camera sees level panels edge-on), and the
    frame's ELM then follows the sun: valid with the sun behind the camera, not with a low sun behind the
    panels."""
    import math

    import numpy as np
    import torch

    from torchskin.dataset.config import sample_group
    from torchskin.dataset.generate import PANEL_MAX_VIEW_DEG, group_scene, panel_tilt_deg, panels_sunlit
    from torchskin.render.elm import panel_pixels
    from torchskin.render.raycast import Raycaster

    g = sample_group(small_cfg(subject_obj, camera={"zenith_deg": [camera_zenith] * 2, "range_m": [60.0, 60.0],
                                                    "width": 96, "height": 96}), 0, 0)
    sc = group_scene(g)
    az = math.radians(g.camera["azimuth_deg"])
    to_cam = np.array([math.cos(az), math.sin(az)])
    behind_camera = [*(math.sin(math.radians(40.0)) * to_cam), math.cos(math.radians(40.0))]
    low_behind_panels = [*(-math.sin(math.radians(85.0)) * to_cam), math.cos(math.radians(85.0))]
    dirs = np.array([behind_camera, low_behind_panels])
    gb = Raycaster.from_scene(sc).gbuffer(sc.cameras, dirs)
    view_deg = []
    for per_cam in panel_pixels(gb, list(sc.panels)):
        ix = per_cam[0]
        assert ix.numel() >= 20
        cos = (gb.normal.reshape(-1, 3)[ix] * gb.view.reshape(-1, 3)[ix]).sum(-1)
        view_deg.append(math.degrees(math.acos(float(cos.mean()))))
    expected = min(camera_zenith, PANEL_MAX_VIEW_DEG)
    assert panel_tilt_deg(camera_zenith) == 90.0 - max(0.0, camera_zenith - PANEL_MAX_VIEW_DEG)
    assert view_deg == pytest.approx([expected] * 2, abs=1.5)  # a 60 m range: nearly parallel rays
    ok = panels_sunlit(gb, list(sc.panels), torch.tensor(dirs, dtype=torch.float32)).tolist()
    assert ok == [True, camera_zenith <= PANEL_MAX_VIEW_DEG]  # a level panel is lit by any sun above the horizon


@pytest.mark.slow
def test_clothing_is_a_measured_spectrum_of_the_partition(monkeypatch):
    """The subject's clothing is an earthlib spectrum from the clothing families of the configured partition,
    recorded per row; its pixels are labelled "clothing" and, being Lambertian, ELM returns that spectrum up to
    one geometric factor per pixel (noise and the ADC's quantization off: the band ratios are the spectrum's)."""
    import torchskin.dataset.generate as gen
    from torchskin.confusers import CLOTHING_FAMILIES, family, partition, spectrum
    from torchskin.dataset.config import sample_group
    from torchskin.dataset.generate import group_rows

    sensor = gen.group_sensor
    monkeypatch.setattr(gen, "group_sensor", lambda g, light=None: dataclasses.replace(sensor(g, light), quantize=False))

    front = {"azimuth_deg": [0.0, 0.0]}  # camera and sun in front of the subject (facing +x)
    cfg = resolve_config({"camera": {"width": 192, "height": 192, "zenith_deg": [60.0, 70.0], "range_m": [6.0, 8.0],
                                     **front}, "subject": {"yaw_deg": [0.0, 0.0]},
                          "sun": {"per_pose": 1, "zenith_deg": [30.0, 40.0], **front}, "skin": {"per_pose": 1},
                          "sensor": {"noise": False}, "clothing": {"partition": "test"},
                          "confusers": {"count": [0, 0]}, "sampling": {"pixels_per_class": 400},
                          # the thesis's lamp without its sky: every band lit alike (outdoors, sky and ground tint it)
                          "light": {"model": "thesis", "sky_fraction": [0.0, 0.0]}})
    g = sample_group(cfg, 5, 0)
    assert g.clothing and partition(g.clothing) == "test" and family(g.clothing).startswith(CLOTHING_FAMILIES)
    rows = {k: np.concatenate(v) for k, v in group_rows(g, 400).items() if v}
    assert set(rows["clothing"]) == {g.clothing} and set(rows["surface"]) == {"thesis"}
    assert set(rows["material"][rows["label"]]) == {"skin"}
    cloth = (rows["material"] == "clothing") & ~rows["shadow"]
    assert cloth.sum() > 20
    r = np.stack([rows[f"r{b}"] for b in (544, 633, 1080, 1580)], -1)[cloth]
    ratio = r / np.array(spectrum(g.clothing, (544, 633, 1080, 1580)))
    assert np.allclose(ratio, ratio[:, :1], rtol=1e-4), ratio[:5]


@pytest.mark.slow
@pytest.mark.skipif(not compiler_available("cpu"), reason="no compiled CPU kernels here (devices.compiler_problem)")
def test_compiled_generation_matches_eager(tmp_path, subject_obj):
    import pandas as pd

    cfg = small_cfg(subject_obj)
    generate(cfg, 12, 4, tmp_path / "eager", quiet=True, compile=False)
    man = generate(cfg, 12, 4, tmp_path / "compiled", quiet=True, compile=True)
    assert man["compiled"] is True
    assert json.loads((tmp_path / "eager" / MANIFEST).read_text())["compiled"] is False
    a, b = pd.read_parquet(tmp_path / "eager"), pd.read_parquet(tmp_path / "compiled")
    assert len(a) == len(b) > 100
    for c in a.columns:
        if c in ("theta_i_deg", "theta_r_deg"):
            # local angles are acos of a dot product of unit float32 vectors, which fused (compiled) and eager
            # kernels round differently by a few ulps; acos amplifies that near 0 deg (d theta ~ sqrt(2 d cos):
            # 2 ulps of cos are 0.03 deg at normal incidence), so the cosines are compared, within 8 ulps of 1
            ca, cb = (np.cos(np.radians(x[c].to_numpy(np.float64))) for x in (a, b))
            assert np.allclose(ca, cb, rtol=0, atol=8 * np.finfo(np.float32).eps, equal_nan=True), c
        elif a[c].dtype.kind == "f":
            tol = 1e-3 if c.startswith(("r", "nd")) and c not in ("range_m", "relative_azimuth_deg") else 1e-4
            assert np.allclose(a[c], b[c], rtol=tol, atol=tol, equal_nan=True), c
        elif c != "shadow":  # a shadow test exactly at grazing incidence may flip
            assert (a[c].to_numpy() == b[c].to_numpy()).all(), c
    assert (a.shadow != b.shadow).mean() < 0.01
    assert all(e["compiled"] for e in man["shards"])
    with pytest.raises(ValueError, match="compile"):
        generate(cfg, 12, 4, tmp_path / "bad", quiet=True, compile="yes")
    (tmp_path / "eager" / "shard-00001.parquet").unlink()  # resumed compiled: the kept shards stay eager
    mixed = generate(cfg, 12, 4, tmp_path / "eager", quiet=True, resume=True, compile=True)
    assert mixed["compiled"] is False
    assert [e["compiled"] for e in mixed["shards"]] == [False, True] + [False] * (len(mixed["shards"]) - 2)


def test_the_irradiance_bound_splits_line_frames_from_physical_ones(tmp_path, subject_obj):
    """Suns 60-88° from the zenith over level panels: some frames' panels receive more than 3 times less light
    than a sun-facing surface. ``elm_valid`` is ``elm_line_valid`` with that bound (``panel_irradiance_ratio`` <=
    3); training's ``--frames line`` reads the line frames, evaluation's physical frames only, and a frame's
    rows read like its ratio says (sun-facing skin above 1 only where the ratio allows it)."""
    import numpy as np
    import pandas as pd

    from torchskin.dataset.files import read_valid
    from torchskin.detectors.boxes import load_skin_rows
    from torchskin.render.elm import ELM_MAX_IRRADIANCE_RATIO

    cfg = small_cfg(subject_obj, sun={"zenith_deg": [60.0, 88.0], "per_pose": 6},
                    camera={"zenith_deg": [20.0, 40.0]}, sampling={"groups_per_shard": 2})
    generate(cfg, 48, 5, tmp_path / "d", quiet=True)
    df = pd.read_parquet(tmp_path / "d")
    assert (df.elm_valid == (df.elm_line_valid & (df.panel_irradiance_ratio <= ELM_MAX_IRRADIANCE_RATIO))).all()
    limited = df.elm_line_valid & ~df.elm_valid
    assert limited.any() and df.elm_valid.any()  # both kinds of frame in the draw
    assert (df.panel_irradiance_ratio[limited] > ELM_MAX_IRRADIANCE_RATIO).all()
    cols = ["label", "r1080"]
    assert len(read_valid(tmp_path / "d", cols)[0]) == int(df.elm_valid.sum())
    assert len(read_valid(tmp_path / "d", cols, "line")[0]) == int(df.elm_line_valid.sum())
    with pytest.raises(ValueError, match="frames must be one of"):
        read_valid(tmp_path / "d", cols, "all")
    n_line = len(load_skin_rows(tmp_path / "d", frames="line")[0])
    n_phys = len(load_skin_rows(tmp_path / "d", frames="physical")[0])
    assert n_line > n_phys > 0
    # the bound is what it says: sunlit skin (brightest band below 0.75) reads at most the ratio times that,
    # below 3 in physical frames but for a glint's few rows; frames beyond the bound read skin above 3
    lit = df.label & ~df.shadow
    peak = df[["r544", "r633", "r1080", "r1580"]].max(axis=1)
    assert np.percentile(peak[lit & df.elm_valid], 99) < ELM_MAX_IRRADIANCE_RATIO < peak[lit & limited].max()
