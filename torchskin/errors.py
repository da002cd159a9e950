"""One error path for every ``torchskin`` command (torch-free: the onboard commands use it too).

Every command runs inside ``run_command``: bad input (``ValueError``, argparse usage) prints one line,
``torchskin <command>: error: <what, which file or parameter, what was expected>``, and exits with status 2;
a failure while working (a full disk, a permission refused while writing, a ``Failure`` such as a training
that left its data, an unexpected exception) prints one line the same way and exits with status 1; never a
traceback unless ``--debug`` (or ``TORCHSKIN_DEBUG=1``) asks
for it. Output paths are checked before any work (``check_output_file``, ``check_output_folder``), so a failed
command leaves its output location as it found it.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from .io import StrPath

EXIT_USAGE = 2
EXIT_FAILURE = 1
#: the optional packages a command may need: import name -> (distribution, the extra that installs it; pyproject's
#: ``[project.optional-dependencies]``, checked by a test)
EXTRAS = {"onnx": ("onnx", "onnx"), "pyarrow": ("pyarrow", "dataset"),
          "pandas": ("pandas", "dataset"), "earthlib": ("earthlib", "dataset"), "open3d": ("open3d", "render"),
          "kornia": ("kornia", "render"), "skimage": ("scikit-image", "render"), "anny": ("anny", "render"),
          "pvlib": ("pvlib", "render"), "ray": ("ray", "ray"),
          "spectral": ("spectral", "formats"), "tifffile": ("tifffile", "formats")}

#: the base requirements a command imports (pyproject's ``dependencies``): a ``--no-deps`` install may lack them
BASE = {"onnxruntime": "onnxruntime", "torch": "torch", "matplotlib": "matplotlib", "tqdm": "tqdm"}


def missing_extra(e: ModuleNotFoundError) -> str | None:
    """The one-line hint for a missing optional package (``EXTRAS``), or None for a module torchskin does not
    know as optional.

    >>> missing_extra(ModuleNotFoundError("No module named 'open3d'", name="open3d"))
    "this command needs open3d: pip install 'torchskin[render]' (or 'torchskin[all]' for every command)"
    """
    top = (e.name or "").partition(".")[0]
    if top in BASE:
        return (f"this command needs {BASE[top]}, a requirement of torchskin that is not installed: pip install "
                f"{BASE[top]} (an install with --no-deps leaves it out)")
    if top not in EXTRAS:
        return None
    dist, extra = EXTRAS[top]
    return f"this command needs {dist}: pip install 'torchskin[{extra}]' (or 'torchskin[all]' for every command)"


class Failure(RuntimeError):
    """A command's work failed through no fault of its input (a training whose boxes left the data, say): one line
    and exit status 1 in ``run_command``, where a ``ValueError`` (bad input) exits with status 2."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line, ``<prog>: error: <message> (see <prog> --help)``,
    with exit status 2 (argparse prints the whole usage block first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def one_line(e: BaseException) -> str:
    """The exception's message on one line (at most 600 characters).

    Args:
        e: any exception.

    Returns:
        Its message with every run of whitespace (newlines included) made one space, cut to 600 characters;
        the exception's type name when the message is empty.

    >>> one_line(ValueError("bad\\n   value"))
    'bad value'
    >>> one_line(KeyError())
    'KeyError'
    """
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 600 else text[:597] + "..."


def _describe_os_error(e: OSError) -> str:
    what = e.strerror or one_line(e)
    return f"{what}: {e.filename!r}" if e.filename else what


def run_command(name: str, fn: Callable[[], int | None], debug: bool = False) -> int:
    """Run ``fn()`` with the error path described above.

    Args:
        name: the command's name, for the message (``torchskin <name>: error: ...``).
        fn: the command; returns its exit status (None: 0).
        debug: re-raise instead of printing one line (also when ``TORCHSKIN_DEBUG`` is set and not "0").

    Returns:
        The exit status: ``fn``'s, 2 (``EXIT_USAGE``) for bad input, 1 (``EXIT_FAILURE``) for a failure while
        working (``Failure``, ``OSError``, ...), 130 when interrupted.

    >>> run_command("demo", lambda: 0)
    0
    >>> import contextlib, io
    >>> with contextlib.redirect_stderr(io.StringIO()) as err:
    ...     status = run_command("demo", lambda: int("x"))
    >>> status, err.getvalue()
    (2, "torchskin demo: error: invalid literal for int() with base 10: 'x'\\n")
    >>> def diverged():
    ...     raise Failure("training failed: the optimisation left the data")
    >>> with contextlib.redirect_stderr(io.StringIO()) as err:
    ...     status = run_command("demo", diverged)
    >>> status, err.getvalue()
    (1, 'torchskin demo: error: training failed: the optimisation left the data\\n')
    """
    debug = debug or os.environ.get("TORCHSKIN_DEBUG", "") not in ("", "0")
    try:
        with warnings.catch_warnings():
            if not debug:  # warnings as one line each, like errors
                warnings.showwarning = lambda message, *args, **kw: print(
                    f"torchskin {name}: warning: {one_line(message)}", file=sys.stderr)
            return int(fn() or 0)
    except SystemExit as e:  # argparse (--help, usage errors: already printed): its status as the return value
        return e.code if isinstance(e.code, int) else (0 if e.code is None else EXIT_USAGE)
    except KeyboardInterrupt:
        print(f"torchskin {name}: interrupted", file=sys.stderr)
        return 130
    except ValueError as e:
        if debug:
            raise
        print(f"torchskin {name}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except Failure as e:  # the work failed, not the input: one line, status 1
        if debug:
            raise
        print(f"torchskin {name}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_FAILURE
    except MemoryError:
        if debug:
            raise
        print(f"torchskin {name}: error: out of memory (reduce the resolution, the batch or the number of "
              "configurations)", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as e:
        if debug:
            raise
        print(f"torchskin {name}: error: {_describe_os_error(e)}", file=sys.stderr)
        return EXIT_FAILURE
    except ModuleNotFoundError as e:  # an optional package not installed: the extra that installs it
        if debug:
            raise
        hint = missing_extra(e) or (f"unexpected ModuleNotFoundError: {one_line(e)} (run with --debug for the "
                                    "traceback)")
        print(f"torchskin {name}: error: {hint}", file=sys.stderr)
        return EXIT_FAILURE
    except Exception as e:  # anything unforeseen: still one line, and the way to the traceback
        if debug:
            raise
        print(f"torchskin {name}: error: unexpected {type(e).__name__}: {one_line(e)} (run with --debug for the "
              "traceback)", file=sys.stderr)
        return EXIT_FAILURE


def _writable_dir(d: Path, option: str, what: str) -> None:
    if not d.exists():
        raise ValueError(f"{option} {what}: folder {str(d)!r} does not exist")
    if not d.is_dir():
        raise ValueError(f"{option} {what}: {str(d)!r} is a file, not a folder")
    if not os.access(d, os.W_OK | os.X_OK) or not _can_create_in(d):
        raise ValueError(f"{option} {what}: folder {str(d)!r} is not writable")


def _can_create_in(d: Path) -> bool:
    """Whether a file can really be created in ``d`` (a probe, removed at once: permission bits do not tell for
    root, read-only mounts or pseudo file systems)."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=d, prefix=".torchskin-probe-"):
            return True
    except OSError:
        return False


def check_output_file(path: StrPath | None, option: str, suffixes: tuple[str, ...] = ()) -> Path:
    """Check before any work that ``path`` can be written as a file: not an existing folder, its folder exists
    and is writable, and (when given) it ends in one of ``suffixes``.

    Args:
        path: the file a command will write.
        option: the command-line option that named it, for the message (e.g. "--out").
        suffixes: the allowed suffixes, lower case with the dot (any when empty).

    Returns:
        ``path`` as a Path; ``ValueError`` naming ``option`` when it cannot be written.
    """
    if path is None or str(path).strip() == "":
        raise ValueError(f"{option} needs a file path")
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {str(p)!r} is an existing folder; a file path is expected")
    if suffixes and p.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {str(p)!r} must end in {' or '.join(suffixes)}")
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"{option} {str(p)!r} exists and is not writable")
    _writable_dir(p.parent if str(p.parent) else Path("."), option, str(p))
    return p


def check_folder_empty(path: StrPath, option: str, overwrite: bool, instead: str = "") -> None:
    """``ValueError`` naming ``option`` when ``path`` is an existing folder that holds anything and ``overwrite`` is
    False: a command that writes a folder of files writes into a new or empty folder, and replaces what is there
    only when asked (``--overwrite``; ``instead``: another way the command offers, e.g. "--resume to continue").

    >>> import tempfile
    >>> d = tempfile.mkdtemp()
    >>> _ = (Path(d) / "render.json").write_text("{}")
    >>> check_folder_empty(d, "--out", overwrite=False)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: --out folder '...' is not empty: pass --overwrite to replace its files, or choose another folder
    """
    p = Path(path)
    if overwrite or not p.is_dir() or not any(p.iterdir()):
        return
    how = f"{instead} or --overwrite" if instead else "--overwrite to replace its files"
    raise ValueError(f"{option} folder {str(p)!r} is not empty: pass {how}, or choose another folder")


def check_output_folder(path: StrPath | None, option: str, overwrite: bool | None = None) -> Path:
    """Check before any work that ``path`` can be (or is) a writable folder: an existing folder, or a new one
    whose nearest existing ancestor is a writable folder (not a file). Nothing is created here.

    Args:
        path: the folder a command will write into.
        option: the command-line option that named it, for the message.
        overwrite: for a command with ``--overwrite``, its value: False refuses an existing folder that is not
            empty (``check_folder_empty``); None (a command without the option) does not look inside.

    Returns:
        ``path`` as a Path; ``ValueError`` naming ``option`` when it cannot be written.
    """
    if path is None or str(path).strip() == "":
        raise ValueError(f"{option} needs a folder path")
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise ValueError(f"{option} {str(p)!r} is an existing file; a folder is expected")
        if not os.access(p, os.W_OK | os.X_OK) or not _can_create_in(p):
            raise ValueError(f"{option} folder {str(p)!r} is not writable")
        if overwrite is not None:
            check_folder_empty(p, option, overwrite)
        return p
    q = p.parent
    while not q.exists() and q != q.parent:
        q = q.parent
    if q.exists() and not q.is_dir():
        raise ValueError(f"{option} {str(p)!r} lies under {str(q)!r}, which is a file")
    _writable_dir(q, option, str(p))
    return p


def check_input_file(path: StrPath, option: str, suffixes: tuple[str, ...] = ()) -> Path:
    """Check before any work that ``path`` is an existing, readable file (ending in one of ``suffixes`` when
    given).

    Args:
        path: the file a command will read.
        option: the command-line option that named it, for the message.
        suffixes: the allowed suffixes, lower case with the dot (any when empty).

    Returns:
        ``path`` as a Path; ``ValueError`` naming ``option`` when it is missing, a folder or unreadable.

    >>> check_input_file("no/such/file.csv", "--spectra")
    Traceback (most recent call last):
    ...
    ValueError: --spectra 'no/such/file.csv' does not exist
    """
    p = Path(str(path))
    if not p.exists():
        raise ValueError(f"{option} {str(p)!r} does not exist")
    if p.is_dir():
        raise ValueError(f"{option} {str(p)!r} is a folder; a file is expected")
    if suffixes and p.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {str(p)!r} must be a {' or '.join(suffixes)} file")
    if not os.access(p, os.R_OK):
        raise ValueError(f"{option} {str(p)!r} is not readable")
    return p


__all__ = ["EXIT_FAILURE", "EXIT_USAGE", "Failure", "Parser", "check_folder_empty", "check_input_file", "check_output_file", "check_output_folder", "one_line",
           "run_command"]
