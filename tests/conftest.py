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


#: the documentation build (``docs_build_command``), started beside the suite when ``tests/test_docs.py`` is among
#: the selected tests, and awaited by its ``site`` fixture: sphinx runs on about one core for ~50 s while the
#: suite's tests go on (most of them one CLI subprocess at a time); keys "proc", "out", "log"
DOCS_BUILD: dict = {}


def docs_build_command(out) -> list[str]:
    """The sphinx build ``make docs`` runs (warnings are errors) into ``out``."""
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    return [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(root / "docs"), str(out),
            "-d", str(Path(out) / ".doctrees")]


def pytest_collection_finish(session):
    if DOCS_BUILD or not any(item.path.name == "test_docs.py" for item in session.items):
        return
    import subprocess
    import tempfile
    from pathlib import Path

    top = Path(tempfile.mkdtemp(prefix="torchskin-docs-"))
    log = open(top / "sphinx.log", "w")  # a file, not a pipe: nothing can block on a full pipe
    DOCS_BUILD.update(out=top / "html", log=top / "sphinx.log", top=top,
                      proc=subprocess.Popen(docs_build_command(top / "html"), stdout=log, stderr=subprocess.STDOUT,
                                            text=True))
    log.close()


def pytest_sessionfinish(session, exitstatus):
    if DOCS_BUILD:
        import shutil

        proc = DOCS_BUILD["proc"]
        if proc.poll() is None:  # the run stopped before test_docs (-x, an interrupt)
            proc.kill()
            proc.wait()
        shutil.rmtree(DOCS_BUILD["top"], ignore_errors=True)
