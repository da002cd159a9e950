"""Every `torchskin` command against malformed input, held to the contract for bad input: exit status 2,
exactly one line on stderr of the form `torchskin <command>: error: ...` that names the parameter or file,
nothing on stdout, no traceback, and the files around it (inputs and output locations) left exactly as they
were. Then a hypothesis fuzz of the numeric
options of `spectra`, `render` and `detect`, and the cases that would exhaust memory under a memory limit."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchskin.cli import main
from torchskin.cli.spectra import MAX_SAMPLE

EXPORTS = Path(__file__).resolve().parents[1] / "exports"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A folder of good and bad inputs (nothing in it may change while the cases run)."""
    w = tmp_path_factory.mktemp("hostile")
    (w / "adir").mkdir()
    (w / "afile").write_text("not a folder")
    (w / "junk.pt").write_text("junk")
    (w / "truncated.pt").write_bytes((EXPORTS / "boundaries.pt").read_bytes()[:200])
    torch.save({"a": 1}, w / "wrongschema.pt")
    (w / "junk.onnx").write_bytes(b"\x00\x01junk")
    good = np.full((4, 8, 8), 0.3, dtype=np.float32)
    np.save(w / "cube.npy", good)
    np.save(w / "empty.npy", np.zeros((0,), dtype=np.float32))
    np.savez(w / "cube.npz", cube=good)
    np.save(w / "object.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    inf = good.copy()
    inf[1, 2, 3] = np.inf
    np.save(w / "inf.npy", inf)
    np.save(w / "text.npy", np.array(["a", "b"]))
    (w / "bad.csv").write_text("name,foo,bar\ns0,0.1,0.2\n")
    (w / "dark.csv").write_text("name,500,550,600,650,700,750,800\ns0,0,0,0,0,0,0,0\n")
    (w / "words.csv").write_text("hello world\n")
    (w / "brdf.csv").write_text("theta_i_deg,theta_r_deg\n1,2\n")
    (w / "bad.toml").write_text("[sun\nzenith_deg = [0, 10]\n")
    (w / "nan.toml").write_text("[sun]\nzenith_deg = [0, nan]\n")
    (w / "unknown.toml").write_text("[sun]\nbrightness = 3\n")
    (w / "list.json").write_text("[1, 2, 3]")
    (w / "empty.obj").write_text("")
    (w / "mesh.txt").write_text("v 0 0 0\n")
    (w / "notadataset").mkdir()
    (w / "notadataset" / "readme.txt").write_text("x")
    return w


def snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(d.rglob("*"))}


C = "cube.npy"
DET = str(EXPORTS / "detector.onnx")
BND = str(EXPORTS / "boundaries.onnx")
CFG = ["--sun-zenith", "40", "--camera-zenith", "30", "--relative-azimuth", "60", "--diffuse-share", "0.2"]  # the shipped lut
PANELS = ["--panel", "1:4:1:4=0.97", "--panel", "4:7:4:7=0.03"]

# (command line with {w} for the world folder, text the one error line must hold)
CASES = [
    # spectra: numbers and sizes
    ("spectra --bands 544/1e9", "fwhm"),
    ("spectra --bands 544,abc", "band"),
    ("spectra --bands 300", "nm"),
    ("spectra --wavelengths 400:1700:1e-9", "wavelength"),
    ("spectra --wavelengths 400:abc:10", "--wavelengths"),
    ("spectra --wavelengths 1700:400:10", "start"),
    ("spectra --sample 0", "--sample"),
    ("spectra --sample -5", "--sample"),
    ("spectra --sample 100000000000", "--sample"),
    ("spectra --incidence-deg nan", "--incidence-deg"),
    ("spectra --incidence-deg 95", "--incidence-deg"),
    ("spectra --param melanosome=2", "melanosome"),
    ("spectra --param bogus=1", "bogus"),
    ("spectra --param melanosome=abc", "melanosome"),
    ("spectra --param blood=nan", "blood"),
    ("spectra --preset XX", "preset"),
    ("spectra --plot {w}/adir", "--plot"),
    ("spectra --plot {w}/afile/p.png", "--plot"),
    ("spectra --plot {w}/p.txt", "--plot"),
    ("spectra --plot {w}/nothere/p.png", "--plot"),
    ("spectra --plot /proc/p.png", "--plot"),
    # render: geometry, resolution, devices, meshes, outputs
    ("render --out {w}/r --source-azimuth nan", "--source-azimuth"),
    ("render --out {w}/r --source-zenith 95", "--source-zenith"),
    ("render --out {w}/r --camera-zenith -1", "--camera-zenith"),
    ("render --out {w}/r --camera-azimuth inf", "--camera-azimuth"),
    ("render --out {w}/r --sky 2", "--sky"),
    ("render --out {w}/r --range 0", "--range"),
    ("render --out {w}/r --fov 0", "--fov"),
    ("render --out {w}/r --width 0", "--width"),
    ("render --out {w}/r --width 100000 --height 100000", "megapixels"),
    ("render --out {w}/r --width 2000 --height 2000 --max-megapixels nan", "--max-megapixels"),
    ("render --out {w}/r --device cuda:7", "--device"),
    ("render --out {w}/r --device tpu", "--device"),
    ("render --out {w}/r --mesh {w}/missing.obj", "--mesh"),
    ("render --out {w}/r --mesh {w}/mesh.txt", "--mesh"),
    ("render --out {w}/r --skin XX", "preset"),
    ("render --out {w}/r --bands 544/1e9", "fwhm"),
    ("render --out {w}/afile", "--out"),
    ("render --out {w}/afile/r", "--out"),
    ("render --out /proc/frame", "--out"),
    ("render --out {w}/r --panels plastic", "--panels"),
    # experiment
    ("experiment --out {w}/afile", "--out"),
    ("experiment --out {w}/e --device cuda", "--device"),
    ("experiment --out {w}/e --width 8", "--width"),
    ("experiment --out {w}/e --surface lambert", "--surface"),
    # fits
    ("fit-skin {w}/missing.csv --out {w}/p.csv", "missing.csv"),
    ("fit-skin {w}/bad.csv --out {w}/p.csv", "bad.csv"),
    ("fit-skin {w}/dark.csv --out {w}/p.csv", "dark.csv"),
    ("fit-skin {w}/words.csv --out {w}/p.csv", "words.csv"),
    ("fit-skin {w}/bad.csv --out {w}/adir", "--out"),
    ("fit-skin {w}/bad.csv --out {w}/p.csv --noise -1", "--noise"),
    ("fit-skin {w}/bad.csv --out {w}/p.csv --r0 nan", "--r0"),
    ("fit-brdf {w}/missing.csv --out {w}/b.json", "missing.csv"),
    ("fit-brdf {w}/brdf.csv --out {w}/b.json", "brdf.csv"),
    ("fit-brdf {w}/brdf.csv --out {w}/adir", "--out"),
    # datasets
    ("generate --configs 0 --out {w}/g", "--configs"),
    ("generate --config {w}/missing.toml --out {w}/g", "--config"),
    ("generate --config {w}/bad.toml --out {w}/g", "bad.toml"),
    ("generate --config {w}/nan.toml --out {w}/g", "sun.zenith_deg"),
    ("generate --config {w}/unknown.toml --out {w}/g", "sun.brightness"),
    ("generate --out {w}/g --device cuda", "--device"),
    ("generate --out {w}/afile", "--out"),
    ("generate --out {w}/g --resume --overwrite", "--resume"),
    ("generate --out {w}/g --workers 0", "--workers"),
    ("generate --out {w}/g --seed -1", "--seed"),
    ("generate --out {w}/g --surface bogus", "--surface"),
    ("dataset verify {w}/nothere", "nothere"),
    ("dataset verify {w}/notadataset", "not a torchskin dataset"),
    # learned boundaries
    ("train --data {w}/nothere --out {w}/m.pt", "nothere"),
    ("train --data {w}/notadataset --out {w}/m.pt", "notadataset"),
    ("train --data {w}/notadataset --out {w}/m.pt --steps 0", "--steps"),
    ("train --data {w}/notadataset --out {w}/adir", "--out"),
    ("train --data {w}/notadataset --out {w}/m.pt --pfa-budget 2", "--pfa-budget"),
    ("export --model {w}/junk.pt --out {w}/x", "junk.pt"),
    ("export --model {w}/truncated.pt --out {w}/x", "truncated.pt"),
    ("export --model {w}/wrongschema.pt --out {w}/x", "wrongschema.pt"),
    ("export --model {w}/missing.pt --out {w}/x", "missing.pt"),
    ("export --model {w}/adir --out {w}/x", "adir' is a folder"),
    ("export --model " + str(EXPORTS / "boundaries.pt") + " --out {w}/x --metrics {w}/list.json", "--metrics"),
    ("export --model " + str(EXPORTS / "boundaries.pt") + " --out {w}/afile", "--out"),
    # a model without boxes is exported as detector.onnx alone: a --detector beside it is refused
    ("export --model " + str(EXPORTS / "classifier.pt") + " --detector " + str(EXPORTS / "boundaries.pt")
     + " --out {w}/x", "classifier"),
    ("evaluate --data {w}/notadataset --model {w}/junk.pt", "junk.pt"),
    ("design-bands --data {w}/nothere --heldout {w}/nothere --fresh {w}/nothere --out {w}/design", "nothere"),
    ("design-bands --data {w}/notadataset --heldout {w}/notadataset --fresh {w}/notadataset --out {w}/design",
     "notadataset"),
    ("design-bands --data {w}/nothere --heldout {w}/nothere --fresh {w}/nothere --out {w}/design --ranges uv",
     "--ranges"),
    ("design-bands --data {w}/nothere --heldout {w}/nothere --fresh {w}/nothere --out {w}/design --step 0", "--step"),
    ("evaluate --data {w}/nothere --model " + BND, "nothere"),
    ("evaluate --data {w}/notadataset --model " + BND, "notadataset"),
    ("evaluate --data {w}/notadataset --model " + BND + " --save {w}/adir", "--save"),
    ("evaluate --data {w}/notadataset --model " + BND + " --plots {w}/afile", "--plots"),
    ("evaluate --data {w}/notadataset --model {w}/junk.onnx", "junk.onnx"),
    # onboard: detect
    ("detect --model " + BND + " --cube {w}/" + C + " " + " ".join(CFG), "not a detector"),
    ("detect --model {w}/junk.onnx --cube {w}/" + C + " " + " ".join(CFG), "junk.onnx"),
    ("detect --model {w}/missing.onnx --cube {w}/" + C + " " + " ".join(CFG), "missing.onnx"),
    ("detect --model " + DET + " --cube {w}/empty.npy " + " ".join(CFG), "empty.npy"),
    ("detect --model " + DET + " --cube {w}/cube.npz " + " ".join(CFG), "--cube"),
    ("detect --model " + DET + " --cube {w}/object.npy " + " ".join(CFG), "object.npy"),
    ("detect --model " + DET + " --cube {w}/text.npy " + " ".join(CFG), "text.npy"),
    ("detect --model " + DET + " --cube {w}/inf.npy " + " ".join(CFG), "inf.npy"),
    ("detect --model " + DET + " --cube {w}/missing.npy " + " ".join(CFG), "missing.npy"),
    ("detect --model " + DET + " --cube {w}/" + C + " --sun-zenith nan --camera-zenith 30 --relative-azimuth 60 --diffuse-share 0.2",
     "--sun-zenith"),
    ("detect --model " + DET + " --cube {w}/" + C + " --camera-zenith 30 --relative-azimuth 60 --diffuse-share 0.2", "--sun-zenith"),
    ("detect --model " + DET + " --cube {w}/" + C + " " + " ".join(CFG) + " --out {w}/adir", "--out"),
    ("detect --model " + DET + " --cube {w}/" + C + " " + " ".join(CFG) + " --min-reflectance 2", "min_reflectance"),
    # onboard: calibrate
    ("calibrate --cube {w}/" + C + " --panel 1:4:1:4=0.97 --out {w}/o.npy", "at least 2"),
    ("calibrate --cube {w}/" + C + " --panel 1:4=0.97 --panel 4:7:4:7=0.03 --out {w}/o.npy", "Y0:Y1:X0:X1"),
    ("calibrate --cube {w}/" + C + " --panel 1:4:1:4=nan --panel 4:7:4:7=0.03 --out {w}/o.npy", "--panel"),
    ("calibrate --cube {w}/" + C + " " + " ".join(PANELS) + " --out {w}/adir", "--out"),
    ("calibrate --cube {w}/" + C + " " + " ".join(PANELS) + " --out {w}/o.npy --save-coefficients {w}/afile/c.json",
     "--save-coefficients"),
    ("calibrate --cube {w}/inf.npy " + " ".join(PANELS) + " --out {w}/o.npy", "inf.npy"),
    ("calibrate --cube {w}/" + C + " --coefficients {w}/list.json --out {w}/o.npy", "--coefficients"),
    ("calibrate --cube {w}/cube.npz " + " ".join(PANELS) + " --out {w}/o.npy", "--cube"),
    # the command line itself
    ("nonsense", "nonsense"),
    ("bench --only bogus", "bogus"),
    ("bench --only ,", "--only"),
]


@pytest.mark.parametrize("line,token", CASES, ids=[c[0][:60] for c in CASES])
def test_malformed_input_gets_one_line_and_changes_nothing(world, capsys, line, token):
    argv = line.format(w=world).split()
    before = snapshot(world)
    rc = main(argv)
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, (rc, err)
    assert out == "", out  # nothing on stdout: a script reading it must not take half a result for one
    assert len(lines) == 1, err
    assert lines[0].startswith("torchskin") and ": error: " in lines[0], err
    assert token.lower() in lines[0].lower(), (token, err)
    assert "Traceback" not in err
    assert snapshot(world) == before  # nothing written, nothing half-written, nothing removed


def test_at_least_sixty_cases_over_every_command():
    assert len(CASES) >= 60
    commands = {c[0].split()[0] for c in CASES}
    assert commands >= {"spectra", "render", "experiment", "fit-skin", "fit-brdf", "generate", "dataset", "train",
                        "export", "evaluate", "design-bands", "detect", "calibrate", "bench"}


def test_debug_shows_the_traceback(world, capsys):
    with pytest.raises(ValueError):
        main(["spectra", "--sample", "0", "--debug"])


def test_library_entry_points_refuse_bad_input():
    from torchskin.render.scene import Camera, Scene, Sun

    for bad in ("{}", '{"materials": {}, "meshes": [], "cameras": [{"width": "x"}], "suns": []}', "{oops"):
        with pytest.raises(ValueError):
            Scene.from_json(bad)
    with pytest.raises(ValueError, match="azimuth_deg"):
        Sun(azimuth_deg=float("nan"))
    with pytest.raises(ValueError, match="target"):
        Camera(target=[0.0, float("inf"), 1.0])
    from torchskin.onboard import OnboardBoxes, OnboardDetector

    with pytest.raises(ValueError, match="not a detector"):
        OnboardDetector(BND)
    with pytest.raises(ValueError, match="not a boundaries"):
        OnboardBoxes(DET)
    d = OnboardDetector(DET)
    cube = np.full((1, 4, 4, 4), 0.3, dtype=np.float32)
    assert d(cube, np.array([[40, 30, 60, 0]]))["mask"].shape == (1, 4, 4)  # whole-degree integers are cast
    cube[0, 2, 1, 1] = np.inf
    with pytest.raises(ValueError, match="infinite"):
        d(cube, [[40.0, 30.0, 60.0, 0.2]])


# ------------------------------------------------------------------------------------------------- fuzzing
hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

HOSTILE = st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e308", "-1e308", "0", "-1", "1e-300", "-0"]),
                    st.floats(allow_nan=True, allow_infinity=True).map(repr))


def _ok_or_one_line(capsys, rc):
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if rc != 0:
        assert rc == 2 and len([ln for ln in err.splitlines() if ln.strip()]) == 1, (rc, err)
        assert out == "", out


@pytest.mark.slow
@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(opt=st.sampled_from(["--incidence-deg", "--sample", "--seed"]), value=HOSTILE)
def test_fuzz_spectra_numbers(capsys, opt, value):
    if opt in ("--sample", "--seed"):
        value = value.split(".")[0].replace("inf", "9" * 30).replace("nan", "x")
    if opt == "--sample" and value.isdigit() and 1000 < int(value) <= MAX_SAMPLE:
        value = "1000"  # a valid draw of millions of skins takes minutes: valid sizes run with a small one
    rc = main(["spectra", "--preset", "I", opt, value])
    _ok_or_one_line(capsys, rc)


@pytest.mark.anny
@pytest.mark.slow
@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(opt=st.sampled_from(["--source-zenith", "--source-azimuth", "--camera-zenith", "--camera-azimuth", "--sky",
                            "--range", "--fov", "--max-megapixels"]), value=HOSTILE)
def test_fuzz_render_numbers(tmp_path_factory, capsys, opt, value):
    out = tmp_path_factory.mktemp("fuzz") / "r"
    rc = main(["render", "--out", str(out), "--width", "16", "--height", "16", "--no-ground", opt, value])
    _ok_or_one_line(capsys, rc)
    if rc != 0:
        assert not out.exists()


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(opt=st.sampled_from(["--sun-zenith", "--camera-zenith", "--relative-azimuth", "--diffuse-share",
                            "--min-reflectance"]), value=HOSTILE)
def test_fuzz_detect_numbers(world, capsys, opt, value):
    args = {"--sun-zenith": "40", "--camera-zenith": "30", "--relative-azimuth": "60", "--diffuse-share": "0.2"}
    args[opt] = value
    rc = main(["detect", "--model", DET, "--cube", str(world / C), *[x for kv in args.items() for x in kv]])
    _ok_or_one_line(capsys, rc)


# ----------------------------------------------------------------------------------------- memory limits
@pytest.mark.slow
@pytest.mark.parametrize("args", [
    ["spectra", "--bands", "544/1e9"],
    ["spectra", "--wavelengths", "400:1700:1e-9"],
    ["render", "--out", "{tmp}/r", "--width", "100000", "--height", "100000"],
    ["render", "--out", "{tmp}/r", "--width", "20000", "--height", "20000", "--max-megapixels", "1e6"],
])
def test_huge_requests_refused_under_a_memory_limit(tmp_path, args):
    """Run in a child limited to 3 GiB of address space: the refusal comes before any large allocation (no
    MemoryError, no kill), as one line with status 2."""
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)); "
            "from torchskin.cli import main; sys.exit(main(sys.argv[1:]))")
    argv = [a.format(tmp=tmp_path) for a in args]
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "error:" in lines[0], r.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.anny
@pytest.mark.slow
def test_render_elm_validity_is_reported(tmp_path, capsys):
    """The sun behind the panels: the frame is rendered, flagged elm_valid false in render.json and --json,
    with a warning line."""
    out = tmp_path / "r"
    rc = main(["render", "--out", str(out), "--width", "48", "--height", "48", "--source-azimuth", "180", "--json"])
    cap = capsys.readouterr()
    assert rc == 0 and "warning" in cap.err and "not sunlit" in cap.err
    doc = json.loads(cap.out)
    saved = json.loads((out / "render.json").read_text())
    assert doc["elm_valid"] is False and saved["summary"]["elm_valid"] is False
    assert max(doc["panel_sunlit_fraction"]) < 0.5


@pytest.mark.anny
@pytest.mark.slow
@pytest.mark.parametrize("view", [["--camera-azimuth", "90", "--source-azimuth", "110"], ["--camera-zenith", "0"]],
                         ids=["side", "overhead"])
def test_render_side_and_overhead_views_calibrate_and_detect(tmp_path, capsys, view):
    """The panels face the camera wherever it is: a side view (camera azimuth 90°, the sun turned with it: with
    the default sun at azimuth 20° the panels facing that camera are lit at half the subject's irradiance and the
    frame reads up to 2.2, not a physical line) and an overhead camera both give a valid ELM; `calibrate` through the panel regions in render.json reproduces the renderer's
    reflectance and `detect` runs the shipped detector on it."""
    out = tmp_path / "r"
    assert main(["render", "--out", str(out), "--width", "128", "--height", "128", *view, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["elm_valid"] and min(doc["panel_sunlit_fraction"]) > 0.9 and doc["sunlit_skin_pixels"] > 30
    regions = json.loads((out / "render.json").read_text())["panels"]
    panels = [x for name, ref in (("panel_white", 0.97), ("panel_dark", 0.03))
              for x in ("--panel", ":".join(map(str, regions[name]["region"])) + f"={ref}")]
    assert main(["calibrate", "--cube", str(out / "signal.npy"), *panels, "--out", str(tmp_path / "refl.npy")]) == 0
    ours, theirs = np.load(tmp_path / "refl.npy"), np.load(out / "reflectance.npy")
    skin = np.load(out / "reflectance.npy").sum(0) > 0.05
    assert np.abs(ours - theirs)[:, skin].max() < 5e-3
    camera_az = float(view[1]) if view[0] == "--camera-azimuth" else 0.0
    cam_zen = float(view[1]) if view[0] == "--camera-zenith" else 90.0
    rel = abs((20.0 - camera_az + 180.0) % 360.0 - 180.0)
    capsys.readouterr()
    assert main(["detect", "--model", DET, "--cube", str(tmp_path / "refl.npy"), "--sun-zenith", "45",
                 "--camera-zenith", str(cam_zen), "--relative-azimuth", str(rel), "--diffuse-share", "0.17",
                 "--clip-negative", "--json"]) == 0
    det = json.loads(capsys.readouterr().out)
    assert det["skin_pixels"] > 20 and det["out_of_domain"] == [False]
