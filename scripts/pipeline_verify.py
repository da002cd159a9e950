#!/usr/bin/env python
"""Pipeline step 5/5: verify the exports with onnxruntime.

    python scripts/pipeline_verify.py [--exports exports]

Checks: onnx.checker; metadata (bands, features, domain, manifest hash, version); boundaries.onnx equals the
checkpoint to 1e-5 over the training domain; detector.onnx run by the torch-free onboard runtime equals the
torch reference (scores to 1e-5, masks except on a boundary) on a rendered-like cube; on the thesis geometry
(render, onboard ELM from the panels, detector) the learned boundaries keep > 90 % of the sunlit skin; the
model cards exist and quote the evaluation. Exit status 1 on any failure."""

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exports", default="exports")
    a = ap.parse_args(argv)
    import onnx
    import torch

    from torchskin import boundaries as Bd
    from torchskin.export import Detector as TorchDetector
    from torchskin.onboard import Boundaries, Detector

    out = Path(a.exports)
    missing = [f for f in ("boundaries.pt", "boundaries.onnx", "detector.onnx", "boundaries.md", "detector.md",
                           "evaluation.json") if not (out / f).is_file()]
    if missing:
        print(f"[verify] FAIL {out} lacks {', '.join(missing)} (scripts/pipeline_export.py writes them)")
        return 1
    failures = []

    def check(ok, what):
        print(f"[verify] {'ok  ' if ok else 'FAIL'} {what}", flush=True)
        if not ok:
            failures.append(what)

    for name in ("boundaries", "detector"):
        m = onnx.load(str(out / f"{name}.onnx"))
        onnx.checker.check_model(m, full_check=True)
        meta = {p.key: p.value for p in m.metadata_props}
        check(m.opset_import[0].version >= 17 and json.loads(meta["bands_nm"]) == [544.0, 633.0, 1080.0, 1580.0]
              and len(meta.get("training_manifest_sha256", "")) == 64 and meta.get("torchskin_version"),
              f"{name}.onnx: checker, opset >= 17, metadata")
    model = Bd.load(out / "boundaries.pt")
    lo, hi = model.domain[:, 0], model.domain[:, 1]
    cfg = lo + (hi - lo) * torch.rand(4096, len(model.features), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = model(cfg).numpy()
    got = Boundaries(out / "boundaries.onnx")(cfg.numpy())
    err = float(np.abs(got["boxes"] - ref).max())
    check(err < 1e-5 and not got["out_of_domain"].any(), f"boundaries.onnx vs checkpoint: max |diff| {err:.1e}")
    rng = np.random.default_rng(0)
    skin = np.array([0.30, 0.55, 0.55, 0.07], dtype=np.float32)[:, None, None]
    cube = (rng.random((2, 4, 256, 256)) * 0.6).astype(np.float32)
    cube[:, :, 64:192, 64:192] = skin * (0.8 + 0.4 * rng.random((2, 1, 128, 128))).astype(np.float32)
    c2 = cfg[:2].numpy()
    res = Detector(out / "detector.onnx")(cube, c2)
    with torch.no_grad():
        mt, st = TorchDetector(model)(torch.from_numpy(cube), torch.from_numpy(c2))
    serr = float(np.abs(res["score"] - st.numpy()).max())
    differ = res["mask"] != mt.numpy()
    check(serr < 1e-5 and bool((np.abs(st.numpy()[differ]) < 1e-6).all()),
          f"detector.onnx (onboard runtime) vs torch: max |score diff| {serr:.1e}, {int(differ.sum())} mask pixels differ")
    frac = float(res["mask"][:, 64:192, 64:192].mean())
    check(frac > 0.9, f"detector.onnx finds the skin-like square: {frac:.3f} of it")
    from torchskin.evaluate import thesis_frame

    t = thesis_frame(out / "detector.onnx")
    check(t["pd_sunlit_learned"] > 0.9 and not t["out_of_domain"],
          f"thesis geometry (horizontal camera, sun 45°, ELM from the frame's panels): learned boundaries keep "
          f"{t['pd_sunlit_learned']:.3f} of {t['sunlit_skin_pixels']} sunlit skin pixels (static box "
          f"{t['pd_sunlit_static']:.3f}), {t['false_alarms_learned']} false alarms")
    ev = json.loads((out / "evaluation.json").read_text())
    card = (out / "detector.md").read_text()
    check(f"{ev['learned']['pd_sunlit']:.3f}" in card and (out / "boundaries.md").is_file(),
          "model cards quote the evaluation")
    print(f"[verify] held-out Pd sunlit {ev['learned']['pd_sunlit']:.3f} (static box {ev['static']['pd_sunlit']:.3f}), "
          f"Pfa earthlib test {ev['learned']['pfa']:.2e}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(run())
