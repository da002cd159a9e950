import pytest
import torch


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
    terminalreporter.write_line(capability_line())  # also under -q, which leaves the header out


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
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.render.meshes import sphere_mesh, write_obj

    d = tmp_path_factory.mktemp("registry")
    v, f = sphere_mesh(0.35, 3)
    write_obj(d / "head.obj", v + [0.0, 0.0, 0.9], f)
    cfg = resolve_config({"camera": {"width": 64, "height": 64, "range_m": [5.0, 10.0]}, "sun": {"per_pose": 3},
                          "skin": {"per_pose": 2}, "subject": {"meshes": [str(d / "head.obj")]},
                          "sampling": {"groups_per_shard": 2, "pixels_per_class": 24},
                          "confusers": {"partition": "test"}, "clothing": {"partition": "test"}})
    generate(cfg, 12, 7, d / "ds", quiet=True)
    return d / "ds"
