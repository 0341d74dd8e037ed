"""The package type-checks: ``mypy -p svr`` (configured in pyproject.toml) reports no errors.

mypy cannot follow the editable install's import hook, so the check runs on a copy of the installed
layout made of symbolic links: ``svr/`` with ``models/``, ``sampling/``, ``reconstruction/`` and
``masking/`` (pyproject.toml's package-dir) as ``svr/models`` and so on. The cache lives in the
repository's git-ignored ``.mypy_cache``, so repeated runs are fast.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from layout import REPO, subpackage_folders

SUBPACKAGES = tuple(subpackage_folders().values())


def _installed_layout(root: Path) -> None:
    """Symbolic links under ``root`` that look like the installed ``svr`` package."""
    package = root / "svr"
    package.mkdir()
    for entry in sorted((REPO / "svr").iterdir()):
        if entry.name != "__pycache__":
            (package / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    for name in SUBPACKAGES:
        (package / name).symlink_to(REPO / name, target_is_directory=True)


def test_mypy_reports_no_errors(tmp_path):
    _installed_layout(tmp_path)
    args = [
        sys.executable,
        "-m",
        "mypy",
        "-p",
        "svr",
        "--config-file",
        str(REPO / "pyproject.toml"),
        "--cache-dir",
        str(REPO / ".mypy_cache"),
    ]
    result = subprocess.run(
        args, cwd=tmp_path, capture_output=True, text=True, timeout=600, check=False
    )
    assert result.returncode == 0, f"mypy found errors:\n{result.stdout}\n{result.stderr}"
