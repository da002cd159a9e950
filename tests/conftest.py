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
