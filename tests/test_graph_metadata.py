"""Exported graphs record their detector kind and band set (``export.metadata``: ``kind``, ``bands``), and the
onboard runtime picks its head from ``kind``: the box head for box kinds, the graph as it is for any other;
exports without ``kind`` (made before graphs recorded it) are told by their node names, with the same results."""

import json
from pathlib import Path

import numpy as np
import onnx
import pytest

from torchskin.bands import INDEX_BANDS, BandSet
from torchskin.detectors import registry
from torchskin.detectors.boxes import BoxModel
from torchskin.detectors.classifier import SkinClassifier
from torchskin.export import export, metadata
from torchskin.onboard import OnboardDetector, model_fwhm

SHIPPED = Path(__file__).resolve().parents[1] / "exports" / "detector.onnx"
IO = {"cube", "config", "mask", "score"}


@pytest.fixture(scope="module")
def BOXES(tmp_path_factory) -> Path:
    """The shipped box model (``exports/boundaries.pt``, the detector before the lookup table) as a detector graph."""
    model, _ = registry.load(SHIPPED.parent / "boundaries.pt")
    return Path(export(model, tmp_path_factory.mktemp("boxes"))["detector"])


def meta_of(path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def with_meta(path, out, drop=(), **set_) -> Path:
    """The graph of ``path`` saved as ``out`` with the metadata keys ``drop`` removed and ``set_`` set."""
    m = onnx.load(str(path))
    meta = {p.key: p.value for p in m.metadata_props if p.key not in drop}
    meta.update(set_)
    del m.metadata_props[:]
    onnx.helper.set_model_props(m, meta)
    onnx.save(m, str(out))
    return Path(out)


def renamed(path, out) -> Path:
    """The graph of ``path`` with every node, initializer and intermediate tensor renamed (``x<k>``): nothing of
    the box graph's ``det_`` names is left, only its structure (inputs and outputs keep their names)."""
    m = onnx.load(str(path))
    names: dict[str, str] = {}

    def new(name: str) -> str:
        if name in IO or not name:
            return name
        return names.setdefault(name, f"x{len(names)}")

    for t in m.graph.initializer:
        t.name = new(t.name)
    for k, n in enumerate(m.graph.node):
        n.name = f"n{k}"
        n.input[:] = [new(i) for i in n.input]
        n.output[:] = [new(o) for o in n.output]
    del m.graph.value_info[:]
    onnx.checker.check_model(m)
    assert not any("det_" in s for s in m.SerializeToString().decode("latin-1").split("\0"))
    onnx.save(m, str(out))
    return Path(out)


def frames(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two 96 x 70 frames of random reflectance with a skin-like patch, and two configurations in the domain."""
    rng = np.random.default_rng(seed)
    cube = (rng.random((2, 4, 96, 70)) * 0.7).astype(np.float32)
    cube[:, :, 20:60, 10:50] = np.array([0.35, 0.5, 0.6, 0.2], dtype=np.float32)[:, None, None] \
        * (0.8 + 0.4 * rng.random((2, 1, 40, 40))).astype(np.float32)
    cfg = np.array([[30.0, 10.0, 90.0], [60.0, 45.0, 170.0]])
    return cube, cfg


def same_run(a: OnboardDetector, b: OnboardDetector) -> None:
    cube, cfg = frames()
    for floor in (0.0, 0.02):
        ra, rb = a(cube, cfg, min_reflectance=floor), b(cube, cfg, min_reflectance=floor)
        assert ra["mask"].tobytes() == rb["mask"].tobytes() and ra["score"].tobytes() == rb["score"].tobytes()
        assert ra["mask"].any()


def test_every_kind_records_its_kind_and_band_set(tmp_path):
    """Each built-in kind's graphs (detector.onnx of a box model and of a classifier, boundaries.onnx,
    baseline_box.onnx) carry ``kind`` and ``bands`` (``BandSet.to_json``, round-tripping), consistent with
    ``bands_nm``; a kind that declares other bands (centres and FWHM) records them, and the runtime reads them."""
    assert {"boxes", "classifier"} <= set(registry.kinds())
    made = {"boxes": BoxModel(), "classifier": SkinClassifier()}
    boxes_out = export(made["boxes"], tmp_path / "b", baseline=BoxModel())
    cls_out = export(made["boxes"], tmp_path / "c", detector=made["classifier"])
    graphs = {**{f"boxes/{k}": v for k, v in boxes_out.items()}, "classifier/detector": cls_out["detector"]}
    for name, path in graphs.items():
        meta = meta_of(path)
        assert meta["kind"] == name.split("/")[0], name
        bands = BandSet.from_json(meta["bands"])
        assert bands == INDEX_BANDS and json.loads(meta["bands_nm"]) == list(bands.centers), name
    for kind, model in made.items():
        assert metadata(model)["kind"] == kind == registry.kind_of(model)
    det = OnboardDetector(graphs["boxes/detector"])
    assert det.kind == "boxes" and det.band_set == INDEX_BANDS and model_fwhm(det) == [0.0] * 4
    wide = BoxModel()
    wide.bands = BandSet.parse("544/10,633/10,1080/20,1580/40")  # a kind with bands of its own
    out = export(wide, tmp_path / "w")
    det = OnboardDetector(out["detector"])
    assert det.band_set == wide.bands and det.bands_nm == [544.0, 633.0, 1080.0, 1580.0]
    assert model_fwhm(det) == [10.0, 10.0, 20.0, 40.0]


def test_the_shipped_detector_records_its_kind_and_gets_its_head(BOXES):
    """The shipped lookup table gets the lut head; the shipped boxes' detector graph the box head."""
    meta = meta_of(SHIPPED)
    assert meta["kind"] == "lut" and BandSet.from_json(meta["bands"]) == INDEX_BANDS
    det = OnboardDetector(SHIPPED, tile=1024)
    assert det.kind == "lut" and det.head_name == "lut" and det._lut is not None and det._split is None
    assert meta_of(BOXES)["kind"] == "boxes"
    det = OnboardDetector(BOXES, tile=1024)
    assert det.kind == "boxes" and det.head_name == "boxes" and det._split is not None


def test_a_graph_without_kind_falls_back_to_node_names_with_the_same_result(tmp_path, BOXES):
    """An export made before graphs recorded ``kind`` and ``bands``: the box head found by node names, the bands
    by ``bands_nm``; the same bits as the graph with its metadata."""
    old = with_meta(BOXES, tmp_path / "old.onnx", drop=("kind", "bands"))
    det = OnboardDetector(old, threads=2, tile=1024)
    assert det.kind is None and det.band_set is None and det.bands_nm == [544.0, 633.0, 1080.0, 1580.0]
    assert det.head_name == "boxes" and model_fwhm(det) is None
    same_run(det, OnboardDetector(BOXES, threads=2, tile=1024))


def test_the_head_follows_the_kind_not_the_node_names(tmp_path, BOXES):
    """A box graph whose nodes and tensors are renamed still gets the box head when ``kind`` says boxes (and the
    generic head without ``kind``: its names no longer tell); a box graph whose ``kind`` names another kind runs
    as it is. Every head gives the same bits."""
    ref = OnboardDetector(BOXES, threads=2, tile=1024)
    ren = renamed(BOXES, tmp_path / "renamed.onnx")
    det = OnboardDetector(ren, threads=2, tile=1024)
    assert det.head_name == "boxes" and det._split[1].groups == ref._split[1].groups
    same_run(det, ref)
    nameless = OnboardDetector(with_meta(ren, tmp_path / "renamed_old.onnx", drop=("kind",)), threads=2, tile=1024)
    assert nameless.head_name == "generic" and nameless._split is None
    same_run(nameless, ref)
    other = OnboardDetector(with_meta(BOXES, tmp_path / "other.onnx", kind="classifier"), threads=2, tile=1024)
    assert other.head_name == "generic" and other._split is None
    same_run(other, ref)


def test_a_graph_with_a_bad_band_set_is_refused(tmp_path):
    bad = with_meta(SHIPPED, tmp_path / "bad.onnx", bands="[]")
    with pytest.raises(ValueError, match="metadata 'bands' is not a band set"):
        OnboardDetector(bad)
