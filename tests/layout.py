"""The repository's layout as pyproject.toml installs it: the tests' one reading of it."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def subpackage_folders() -> dict[str, str]:
    """``{"svr.models": "models", ...}``: the top-level folders installed as ``svr`` subpackages.

    Read from ``[tool.setuptools.package-dir]`` in pyproject.toml (``"svr" = "svr"`` left out).
    """
    text = (REPO / "pyproject.toml").read_text()
    table = text.split("[tool.setuptools.package-dir]", 1)[1].split("\n[", 1)[0]
    pairs = dict(re.findall(r'^"([\w.]+)"\s*=\s*"([\w/]+)"', table, flags=re.MULTILINE))
    return {name: folder for name, folder in pairs.items() if name != "svr"}
