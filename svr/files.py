"""Safe output files: atomic writes that never overwrite existing files unless asked."""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputExistsError(FileExistsError):
    """An output exists and overwriting was not allowed (the caller words how to allow it).

    Attributes:
        path: The output file or folder.
        problem: What is in the way, e.g. ``"output exists"``.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str = "output exists") -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple[type[OutputExistsError], tuple[Path, str]]:
        return type(self), (self.path, self.problem)


def check_output_path(path: str | os.PathLike[str], overwrite: bool) -> Path:
    """Check that ``path`` can be written: its folder exists and it does not exist unless allowed.

    Args:
        path: The output file.
        overwrite: Whether an existing file may be replaced.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        OutputExistsError: If the file exists and ``overwrite`` is false.
        FileNotFoundError: If the parent folder does not exist.
        PermissionError: If the parent folder is not writable.
    """
    p = Path(path)
    if p.exists() and not overwrite:
        raise OutputExistsError(p)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(f"{p}: output folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise PermissionError(f"{p}: output folder {parent} is not writable")
    return p


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _default_mode(mode: int, path: Path) -> None:
    """Give a temporary file or folder the permissions a plain ``open``/``mkdir`` would."""
    os.chmod(path, mode & ~_umask())


def atomic_write_text(path: str | os.PathLike[str], text: str, overwrite: bool = False) -> Path:
    """Write a UTF-8 text file atomically (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite)


@contextmanager
def atomic_directory(path: str | os.PathLike[str], overwrite: bool = False) -> Iterator[Path]:
    """Build an output folder in a temporary sibling and move it into place when done.

    On an error the temporary folder is removed and any existing folder is left untouched.

    Args:
        path: The folder to create.
        overwrite: Whether an existing folder may be replaced.

    Yields:
        The temporary folder to write into.

    Raises:
        OutputExistsError: If the folder exists and ``overwrite`` is false.
        FileNotFoundError: If its parent folder does not exist.
    """
    out = check_output_path(path, overwrite)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _default_mode(0o777, tmp)
        yield tmp
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, overwrite: bool = False) -> Path:
    """Write a file atomically: to a temporary file in the same folder, then renamed.

    A reader never sees a partial file, and a failure leaves any existing file untouched.

    Args:
        path: The output file.
        data: Its content.
        overwrite: Whether an existing file may be replaced.

    Returns:
        The written path.
    """
    p = check_output_path(path, overwrite)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        _default_mode(0o666, Path(tmp))
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's content (hex), read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()
