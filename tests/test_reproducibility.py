"""Reproducibility: learners that reach the same answer from any start (seed, thread count), and datasets whose
bytes depend on the configuration and the seed alone (not on the thread count, the backend or the order in
which a library sums).

`make test` runs this module twice: with the CPU's own kernels and again under ``ATEN_CPU_CAPABILITY=avx2``
(each run ends with a line naming the capability it used). No assertion here follows an optimisation
trajectory: the learners are judged by what they learned, against bounds derived in the comments.
"""

import contextlib
import hashlib

import numpy as np
import pytest
import torch
from test_boundaries_onnx import diagonal  # skin walking with the sun between confusers
from torch.utils._python_dispatch import TorchDispatchMode

from torchskin.detectors import boxes as Bx
from torchskin.detectors import classifier as Cl
from torchskin.detectors.features import tuning_configs

pytestmark = [pytest.mark.slow, pytest.mark.reproducibility]

SEEDS = (0, 1, 2)
THREADS = (1, 2)


@contextlib.contextmanager
def torch_threads(n: int):
    """Run with ``n`` intra-op threads (torch's OpenMP and BLAS), then restore the count."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ------------------------------------------------------------------------------------------------ learners
@pytest.mark.parametrize("n_threads", THREADS)
@pytest.mark.parametrize("seed", SEEDS)
def test_box_learner_holds_the_walking_skin_from_any_start(seed, n_threads):
    """The box learner of the shipped detector on skin that walks with the sun between confusers. The
    nearest confuser sits 0.19 (index units) from the walk, so a box of +-3 sigma (0.045) plus the 0.02 margin
    fits everywhere: it holds 0.9973^2 = 0.995 of the pixels. Before the boxes started from the data, 7 of 10
    runs (seeds 0-4 x 1-2 threads) stopped at 0.74-0.77, and which ones moved with the float rounding; the
    issue's bar is 0.95 (met with 1.000 over seeds 0-9 x threads 1, 2 when this test was written)."""
    X, Y, C = diagonal(3000, seed=seed)
    with torch_threads(n_threads):
        model, info = Bx.learn(X, Y, confusers=C, steps=800, margin=0.02)
    assert info["train_coverage"] >= 0.95, info["train_coverage"]
    Xt, Yt, _ = diagonal(20000, seed=100 + seed)  # fresh pixels of the same walk
    assert Bx.train_coverage(model, Xt, Yt) >= 0.95
    # and no confuser inside any box of the training domain (the budget allows floor(1e-3 x 6) = 0)
    assert info["pfa_train_worst"] == 0.0
    with torch.no_grad():
        boxes = model(tuning_configs(model, X, grid=12))
    assert float(Bx.false_alarm_rate(boxes, C).max()) == 0.0


def test_box_learner_start_follows_the_data():
    """The start of the box learner is the conditional quantile box (``fit_quantiles``), not a pooled box: on
    the walk, b1 at sun zenith 75 deg lies about 0.5 x 70 / 80 = 0.44 above b1 at 5 deg before any coverage
    step (init only: steps=0 of the coverage loss). The tolerance 0.06 is the NDGRI spread of the 2 % to 98 %
    quantiles (4.1 sigma = 0.06) which a 400-step fit resolves only roughly."""
    X, Y, C = diagonal(3000, seed=0)
    res = Bx.train_boxes(X, Y, C, steps=0, init_steps=400)
    with torch.no_grad():
        lo, hi = res.model(torch.tensor([[5.0, 30.0, 90.0], [75.0, 30.0, 90.0]]))
    assert float(hi[0] - lo[0]) == pytest.approx(0.5 * 70 / 80, abs=0.06)
    # each edge near its conditional quantile: q = 0.02 of a N(m(t), 0.015) is m - 2.05 sigma = m - 0.031
    m5 = -0.6 + 0.5 * 5 / 80
    assert float(lo[0]) == pytest.approx(m5 - 0.031, abs=0.02)
    with pytest.raises(ValueError, match="init_quantile"):
        Bx.train_boxes(X, Y, C, init_quantile=0.6)


def overlapping(n=3000, seed=0):
    """Skin and non-skin rows whose ratio features overlap (so the budget costs some skin): skin-like spectra
    and earthlib train spectra pulled halfway towards skin, under random configurations."""
    g = torch.Generator().manual_seed(seed)
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    skin = torch.tensor([0.30, 0.60, 0.53, 0.08]) * (0.8 + 0.4 * torch.rand(n, 4, generator=g))
    C = Cl._earthlib_reflectance("train")
    neg = C[torch.randint(len(C), (n,), generator=g)]
    neg = 0.5 * neg + 0.5 * torch.tensor([0.30, 0.60, 0.53, 0.08]) * (0.6 + 0.8 * torch.rand(n, 4, generator=g))
    label = torch.arange(2 * n) < n
    return torch.cat([X, X]), torch.cat([skin, neg]), label, torch.ones(2 * n, dtype=torch.bool)


@pytest.fixture(scope="module")
def classifiers():
    """Classifiers trained with seeds SEEDS x threads THREADS on the same rows."""
    X, R, label, sunlit = overlapping()
    out = {}
    for seed in SEEDS:
        for n in THREADS:
            state = torch.get_rng_state()
            with torch_threads(n):
                out[seed, n] = Cl.train_classifier(X, R, label, sunlit, hidden=8, steps=300, batch=2048, seed=seed,
                                                   max_tuning_configs=50, sunlit_only=True, scene_budget=None)
            out[seed, n] += (torch.equal(state, torch.get_rng_state()),)
    return X, R, label, out


def test_classifier_leaves_the_global_generator_alone(classifiers):
    assert all(same for *_, same in classifiers[3].values())


def test_classifier_starts_from_one_linear_fit():
    """The linear part starts at a convex fit (float64 L-BFGS on every row; ``fit_linear`` takes no seed): one
    optimum, whatever the thread count or the MLP's weights."""
    X, R, label, sunlit = overlapping()
    pos, neg = label & sunlit, ~label
    wp = torch.full((int(pos.sum()),), 1.0 / int(pos.sum()))
    starts = []
    for seed, n in zip(SEEDS, THREADS):
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)  # other MLP weights: the linear fit must not see them
            m = Cl.SkinClassifier(hidden=4, mean=X.mean(0), std=X.std(0), domain=[[0, 80], [0, 70], [0, 180]])
        with torch_threads(n):
            Cl.fit_linear(m, R[pos], X[pos], wp, R[neg], X[neg], Cl._earthlib_reflectance("train"), 4.0)
        starts.append(torch.cat([m.linear.weight.flatten(), m.linear.bias]).detach().clone())
    # L-BFGS stops at a gradient of 1e-10 in float64: another summation order moves the optimum far below
    # float32's resolution; 1e-5 leaves room for the float32 copy of weights of order 1-10
    torch.testing.assert_close(starts[1], starts[0], rtol=0, atol=1e-5)
    assert float(starts[0][:3].abs().max()) > 0.1  # it learned something from the ratios


def test_classifier_decides_alike_from_any_start(classifiers):
    """Trained from seeds 0-2 with 1 and 2 threads, every classifier keeps the budget on the earthlib train
    spectra and keeps the same share of held-out skin within a tolerance: the held-out set has n = 3000 skin
    rows, so a difference of Pd between two runs from sampling alone has a standard error of about
    sqrt(2 p (1 - p) / n) <= 0.013 at p = 0.5; what the seed adds must stay within the same 0.04 (3 sigma)."""
    X, R, label, models = classifiers
    Xt, Rt, lt, _ = overlapping(seed=50)
    pds, pfas = [], []
    for (model, info, _) in models.values():
        keep = model.decide(Rt, Xt)
        pds.append(float(keep[lt].float().mean()))
        pfas.append(float(keep[~lt].float().mean()))
        assert info["pfa_budget"] == 1e-3 and info["threshold"] >= 0.0
    assert min(pds) > 0.2, pds  # the overlap leaves room for skin at the budget
    assert max(pds) - min(pds) <= 0.04, pds
    assert max(pfas) - min(pfas) <= 0.04, pfas


# ------------------------------------------------------------------------------------------------ datasets
def _reversed_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b with the inner sum taken in reverse order, accumulating in the inputs' dtype."""
    out = torch.zeros(a.shape[:-1] + b.shape[-1:], dtype=a.dtype)
    for k in range(a.shape[-1] - 1, -1, -1):
        out = out + a[..., :, k:k + 1] * b[..., k:k + 1, :]
    return out


class ReorderedSums(TorchDispatchMode):
    """Every matrix product and every floating-point sum, mean, norm or product computed in another order:
    matrix products summed in reverse, reductions over their reduced axes reversed (another assignment of
    terms to SIMD lanes and partial sums). What a different thread count, BLAS or CPU can do to the last bits."""

    REDUCTIONS = {"sum", "mean", "linalg_vector_norm", "prod", "nansum"}

    def __init__(self):
        super().__init__()
        self.calls = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if name in ("mm", "bmm") and args[0].is_floating_point():
            self.calls += 1
            return _reversed_matmul(args[0], args[1])
        if name == "addmm" and args[1].is_floating_point():
            self.calls += 1
            return _reversed_matmul(args[1], args[2]) * kwargs.get("alpha", 1) + args[0] * kwargs.get("beta", 1)
        if name in self.REDUCTIONS and args[0].is_floating_point() and args[0].numel() > 1:
            x = args[0]
            names = [a.name for a in func._schema.arguments]
            dims = None
            if "dim" in names:
                i = names.index("dim")
                dims = kwargs.get("dim", args[i] if len(args) > i else None)
            dims = [dims] if isinstance(dims, int) else dims
            dims = list(range(x.ndim)) if not dims else [d % x.ndim for d in dims]
            self.calls += 1
            return func(x.flip(dims), *args[1:], **kwargs)
        return func(*args, **kwargs)


def _rows_digest(rows: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(rows):
        for chunk in rows[k]:
            h.update(k.encode())
            a = np.asarray(chunk)  # string columns come as pyarrow dictionary arrays (object once converted)
            h.update(a.astype(str if a.dtype == object else a.dtype).tobytes())
    return h.hexdigest()


@pytest.mark.anny
def test_dataset_rows_do_not_depend_on_the_order_of_sums():
    """A pose group of the default configuration (an anny body) renders the same rows, bit for bit, when every
    matrix product and reduction on the way sums in another order. In float32, the anny body's blend shapes (136
    coefficients against 41,154 coordinates) moved a vertex's last bit with the BLAS's thread count, a triangle
    edge crossed a pixel's ray on the silhouette, the skin list gained or lost a pixel and every pick after it
    moved to a neighbour: 6,248 of 12,288 rows differed between 1 and 2 threads on one machine."""
    from torchskin.dataset.config import resolve_config, sample_group
    from torchskin.dataset.generate import group_rows

    cfg = resolve_config({})
    group = sample_group(cfg, 7, 0)
    want = _rows_digest(group_rows(group, 64))
    mode = ReorderedSums()
    with mode:
        got = _rows_digest(group_rows(group, 64))
    assert mode.calls > 50  # the body model, the camera rays and the angles went through it
    assert got == want


@pytest.mark.anny
def test_generate_gives_the_same_bytes_at_1_2_and_4_threads(tmp_path):
    """``generate`` with the default anny subject: the same shard checksums with 1, 2 and 4 torch threads."""
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate

    cfg = resolve_config({})
    sums = {}
    for n in (1, 2, 4):
        with torch_threads(n):
            man = generate(cfg, 24, 7, tmp_path / f"t{n}", quiet=True)
        sums[n] = [s["sha256"] for s in man["shards"]]
    assert sums[1] == sums[2] == sums[4], sums


@pytest.mark.anny
def test_ray_backend_with_two_workers_matches_local(tmp_path):
    """The Ray backend (two one-thread workers, each its own process) writes the same bytes as this process,
    with the default anny subject; Ray Data reads the folder directly (the manifest's leading underscore keeps
    it out)."""
    ray = pytest.importorskip("ray")
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.dataset.verify import verify

    cfg = resolve_config({"sampling": {"groups_per_shard": 1}, "sun": {"per_pose": 2}, "skin": {"per_pose": 2}})
    local = generate(cfg, 8, 5, tmp_path / "local", quiet=True)
    man = generate(cfg, 8, 5, tmp_path / "ray", quiet=True, backend="ray", workers=2)
    assert local["n_shards"] == 2
    assert [s["sha256"] for s in local["shards"]] == [s["sha256"] for s in man["shards"]]
    assert verify(tmp_path / "ray")["ok"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        assert ray.data.read_parquet(str(tmp_path / "ray")).count() == sum(s["rows"] for s in man["shards"])
    finally:
        ray.shutdown()
