"""The documentation: the site builds without a warning, the README stays short, and neither the
package nor the documents point to files a user does not have (a design note outside the
repository, the development workspace's data folder).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from layout import subpackage_folders

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_FOLDERS = ("svr", *subpackage_folders().values())
README_MAX_LINES = 230
# Names of files that only exist in the development workspace, never in a user's clone.
WORKSPACE_REFERENCES = re.compile(r"DESIGN\.md|\.\./shared\b")


def test_site_builds_strictly(tmp_path):
    """``mkdocs build --strict``: a broken link, a missing page or a renamed API fails."""
    mkdocs = Path(sys.executable).with_name("mkdocs")
    if not mkdocs.exists():
        pytest.fail(f"mkdocs is not installed next to {sys.executable}: pip install -e '.[test]'")
    result = subprocess.run(
        [str(mkdocs), "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    problems = [
        line
        for line in (result.stdout + result.stderr).splitlines()
        if line.startswith(("WARNING", "ERROR"))
    ]
    assert result.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(
        problems or (result.stdout + result.stderr).splitlines()[-40:]
    )
    assert (tmp_path / "index.html").exists()
    assert (tmp_path / "api" / "losses" / "index.html").exists()


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}); move details to docs/"
    )


def _product_files() -> list[Path]:
    files = [
        path
        for folder in PACKAGE_FOLDERS
        for pattern in ("*.py", "*.md", "*.json")  # the shipped models' READMEs and configs too
        for path in sorted((ROOT / folder).rglob(pattern))
    ]
    files += [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return files


def test_no_workspace_paths_in_the_product():
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _product_files()
        for number, line in enumerate(path.read_text().splitlines(), start=1)
        if WORKSPACE_REFERENCES.search(line)
    ]
    assert not found, (
        "the package and the documents must name files a user has (docs/conventions.md, a "
        "download location such as atlas/), not:\n" + "\n".join(found)
    )
