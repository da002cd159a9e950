"""Dataset configuration: validation, determinism and coverage of the declared ranges."""

import numpy as np
import pytest

from torchskin import tissue
from torchskin.dataset import config as C


@pytest.mark.slow
def test_defaults_validate_and_cover_declared_ranges():
    cfg = C.resolve_config({"sun": {"zenith_deg": [10.0, 60.0]}, "sampling": {"groups_per_shard": 2}})
    groups = [C.sample_group(cfg, 7, i) for i in range(400)]
    zen = np.array([s["zenith_deg"] for g in groups for s in g.suns])
    assert zen.min() >= 10.0 and zen.max() <= 60.0
    # uniform over the declared range: Kolmogorov-Smirnov distance small
    x = np.sort((zen - 10.0) / 50.0)
    ks = np.max(np.abs(np.arange(1, x.size + 1) / x.size - x))
    assert ks < 0.03
    cam = np.array([g.camera["zenith_deg"] for g in groups])
    assert cam.min() >= 0.0 and cam.max() <= 90.0 and cam.max() - cam.min() > 80.0
    rng_m = np.array([g.camera["range_m"] for g in groups])
    assert rng_m.min() >= 5.0 and rng_m.max() <= 100.0
    types = [t for g in groups for t in g.skin_types]
    assert set(types) == set(tissue.FITZPATRICK_TYPES)
    for g in groups[:50]:
        for t, mel in zip(g.skin_types, g.skins.melanosome.tolist()):
            lo, hi = tissue.FITZPATRICK_RANGES[t]["melanosome"]
            assert lo <= mel <= hi
        assert len(g.suns) == 16 and g.skins.shape == (3,) and len(g.skin_types) == 3 and 0 <= len(g.confusers) <= 3


@pytest.mark.slow
def test_confusers_come_from_the_configured_partition_only():
    from torchskin.confusers import partition

    for part in ("train", "test"):
        cfg = C.resolve_config({"confusers": {"count": [2, 3], "partition": part}})
        names = [c["name"] for i in range(30) for c in C.sample_group(cfg, 1, i).confusers]
        assert len(names) >= 60 and all(partition(n) == part for n in names)


def test_groups_are_a_pure_function_of_seed_and_index():
    cfg = C.resolve_config()
    a = [C.sample_group(cfg, 3, i).as_dict() for i in range(5)]
    b = [C.sample_group(cfg, 3, i).as_dict() for i in reversed(range(5))][::-1]
    assert a == b
    assert C.sample_group(cfg, 4, 0).as_dict() != a[0]
    assert len({C.group_seed(3, i) for i in range(1000)}) == 1000


def test_field_of_view_frames_the_subject():
    """``subject_fraction`` of the frame *height* is the subject: through the renderer's pinhole camera
    (``fov_deg`` horizontal) a subject of SUBJECT_HEIGHT_M at the range spans f h / R pixels vertically. A wide
    frame (W 320 x H 200) tells the axes apart: with width and height swapped it would span fraction W² / H."""
    from torchskin.render.scene import Camera

    W, H = 320, 200
    cfg = C.resolve_config({"camera": {"range_m": [50.0, 50.0], "subject_fraction": 0.5, "width": W, "height": H}})
    g = C.sample_group(cfg, 0, 0)
    assert (g.camera["width"], g.camera["height"]) == (W, H)
    cam = Camera(width=g.camera["width"], height=g.camera["height"], range_m=g.camera["range_m"],
                 fov_deg=g.camera["fov_deg"])
    assert cam.focal * C.SUBJECT_HEIGHT_M / 50.0 == pytest.approx(0.5 * H, rel=1e-12)


@pytest.mark.parametrize("override,msg", [
    ({"sun": {"zenith": [0, 10]}}, "unknown config key sun.zenith"),
    ({"lights": {}}, "unknown config section 'lights'"),
    ({"camera": {"range_m": [50.0, 10.0]}}, "camera.range_m: min 50 > max 10"),
    ({"sun": {"zenith_deg": [0.0, 95.0]}}, r"sun.zenith_deg must lie within \[0, 90\]"),
    ({"skin": {"types": ["VII"]}}, "skin.types must list Fitzpatrick types"),
    ({"sampling": {"pixels_per_class": 0}}, "sampling.pixels_per_class must be an integer >= 1"),
    ({"sensor": {"noise": "yes"}}, "sensor.noise must be true or false"),
])
def test_bad_config_raises(override, msg):
    with pytest.raises(ValueError, match=msg):
        C.resolve_config(override)


def test_load_config_from_toml(tmp_path):
    p = tmp_path / "cfg.toml"
    p.write_text('[camera]\nzenith_deg = [20.0, 30.0]\nwidth = 128\n\n[skin]\ntypes = ["I", "VI"]\n')
    cfg = C.load_config(p)
    assert cfg["camera"]["zenith_deg"] == [20.0, 30.0] and cfg["camera"]["width"] == 128
    assert cfg["skin"]["types"] == ["I", "VI"] and cfg["sun"]["per_pose"] == 16
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        C.load_config(bad)
    with pytest.raises(ValueError, match="does not exist"):
        C.load_config(tmp_path / "none.toml")


def test_the_shift_table_configs_load_and_lie_outside_the_defaults(tmp_path):
    """``scripts/shift_table.py``'s datasets: each config loads, and each changed range lies at or beyond the
    embedded default's edge (a widened default moves the shift with it)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("shift_table", Path(__file__).parents[1] / "scripts" / "shift_table.py")
    st = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(st)
    base = C.load_config(None)
    for name, (_, toml) in st.SHIFTS.items():
        p = tmp_path / f"{name}.toml"
        p.write_text(st.TEST_PARTITION + toml)
        cfg = C.load_config(p)
        assert cfg["confusers"]["partition"] == cfg["clothing"]["partition"] == "test"
        changed = [(s, k) for s in cfg for k in cfg[s] if cfg[s][k] != base[s][k] and s not in ("confusers", "clothing")]
        assert changed, name
        for s, k in changed:
            new, old = cfg[s][k], base[s][k]
            if isinstance(new, list) and len(new) == 2 and all(isinstance(v, float) for v in new):
                assert new[0] >= old[1] or new[1] >= 2 * old[1], (name, s, k, new, old)
