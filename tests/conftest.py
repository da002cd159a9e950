import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):  # `pytest -n 2`: one intra-op thread per worker (and per CLI it runs)
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def available_devices():
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda")
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        devs.append("mps")
    return devs


DEVICES = available_devices()


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def dtype_for(device):
    """float64 where the device supports it (MPS does not)."""
    return torch.float32 if device.type == "mps" else torch.float64


def capability_line() -> str:
    """The CPU capability torch's kernels run with (ATEN_CPU_CAPABILITY chooses a lower one) and the thread count:
    what a run of the reproducibility tests exercised."""
    import os

    cap = torch.backends.cpu.get_cpu_capability()
    forced = os.environ.get("ATEN_CPU_CAPABILITY")
    return (f"torch {torch.__version__}: CPU capability {cap}" + (f" (ATEN_CPU_CAPABILITY={forced})" if forced else "")
            + f", {torch.get_num_threads()} intra-op threads")


def pytest_report_header(config):
    return capability_line()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    line = capability_line()  # also under -q, which leaves the header out
    workers = getattr(config.option, "numprocesses", None)
    if workers:  # the tests ran in the workers, one thread each (above)
        line = line.rsplit(", ", 1)[0] + f", {workers} pytest-xdist workers of 1 intra-op thread"
    terminalreporter.write_line(line)


@pytest.fixture(scope="module")
def subject_obj(tmp_path_factory):
    """A small sphere mesh (a head 0.9 m above the ground) as an OBJ subject for dataset tests."""
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.35, 3)
    p = tmp_path_factory.mktemp("mesh") / "head.obj"
    write_obj(p, v + [0.0, 0.0, 0.9], f)
    return p


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A tiny generated dataset (12 configurations of a sphere head, a few pixels per class; test-partition
    confusers and clothing) for the detector-kind tests."""
    return tiny_generate(tmp_path_factory.mktemp("registry"))


def tiny_generate(d, bands: str | None = None, seed: int = 7):
    """The tiny dataset (``tiny_dataset``) generated into ``d / "ds"``, in the bands ``bands`` (a ``--bands`` list;
    default the index bands), from ``seed``; returns its folder."""
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.35, 3)
    write_obj(d / "head.obj", v + [0.0, 0.0, 0.9], f)
    cfg = resolve_config({"camera": {"width": 64, "height": 64, "range_m": [5.0, 10.0]}, "sun": {"per_pose": 3},
                          "skin": {"per_pose": 2}, "subject": {"meshes": [str(d / "head.obj")]},
                          "sampling": {"groups_per_shard": 2, "pixels_per_class": 24},
                          "confusers": {"partition": "test"}, "clothing": {"partition": "test"},
                          **({"bands": {"spec": bands}} if bands else {})})
    generate(cfg, 12, seed, d / "ds", quiet=True)
    return d / "ds"


def rows_with_pixels(cfg, master_seed, df):
    """Each (skin, sun) group of a shard's rows ``df`` (one pose group) with the frame pixel of every row, flat
    indices into H*W. The rows keep no pixel index, but their local (θi, θr, Δφ) and material are a key: they
    are recomputed here from the group's G-buffer with the generator's own angle function, and each row must
    match its pixel's float32 angles to 1e-4 degrees."""
    import numpy as np

    import torchskin.dataset.generate as gen
    from torchskin.dataset.config import sample_group
    from torchskin.render.raycast import Raycaster

    group = sample_group(cfg, master_seed, int(df.group.iloc[0]))
    scene = gen.group_scene(group)
    suns = torch.tensor(np.stack([s.direction for s in scene.suns]), dtype=torch.float32)
    gb = Raycaster.from_scene(scene).gbuffer(scene.cameras, suns.numpy(), shadows=False)
    labels = gen.pixel_labels(group, scene, gb)
    material = labels.material_labels[labels.material + 1]
    every = torch.arange(gb.hit[0].numel())
    for (k, s), rows in df.groupby(["skin", "sun"]):
        angles = np.stack([a.float().numpy() for a in gen.pixel_angles_deg(gb, every, suns[s].expand(len(every), 3))], -1)
        key = rows[["theta_i_deg", "theta_r_deg", "delta_phi_deg"]].to_numpy()
        dist = np.abs(key[:, None] - angles[None]).max(-1)  # (rows, pixels), degrees
        dist[rows.material.to_numpy()[:, None] != material[None]] = np.inf
        px = dist.argmin(1)
        assert (dist[np.arange(len(px)), px] <= 1e-4).all()  # the same float32 angles: the same pixel
        yield k, s, rows, px


#: the test files that take longest (``pytest --durations``), scheduled first under ``pytest -n`` (``make test``): the
#: workers take whole files in collection order, and a long file taken last leaves the other worker idle
LONG_FILES = ("test_reproducibility.py", "test_readme.py", "test_docs.py", "test_export_shipped.py",
              "test_boundaries_onnx.py", "test_dataset_generate.py")


def pytest_collection_modifyitems(session, config, items):
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # the workers collect; the controller schedules their order
        return
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
