"""MkDocs hooks: the API pages' source layout and the generated command-line reference.

The ``svr`` namespace is installed from several folders (``svr/``, ``models/``, ``sampling/``,
...; ``[tool.setuptools.package-dir]`` in pyproject.toml, read here), so mkdocstrings,
which reads the source statically, would not find ``svr.models`` under ``svr/``. ``on_config``
therefore copies the Python files into the installed layout in a temporary folder and points the
Python handler at it. ``on_page_markdown`` replaces the marker in ``cli.md`` by the help of every
``svr`` subcommand, taken from the parser itself, so the reference never falls out of step.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import tempfile
from pathlib import Path

from mkdocs.plugins import event_priority

REPO = Path(__file__).resolve().parents[1]
SUBPACKAGES = tuple(
    folder
    for name, folder in re.findall(
        r'^"(svr\.\w+)"\s*=\s*"(\w+)"',
        (REPO / "pyproject.toml").read_text().split("[tool.setuptools.package-dir]", 1)[1],
        flags=re.MULTILINE,
    )
)
"""The top-level folders installed as ``svr`` subpackages (pyproject.toml's package-dir)."""
CLI_MARKER = "<!-- svr-cli-reference -->"
HELP_WIDTH = "100"

_layout_dir: Path | None = None


def _not_source(folder: str, names: list[str]) -> set[str]:
    """What ``shutil.copytree`` leaves out: caches and every file that is not Python source."""
    return {
        name
        for name in names
        if name == "__pycache__" or (Path(folder, name).is_file() and not name.endswith(".py"))
    }


def _installed_layout(root: Path) -> None:
    """A copy of the package's Python files under ``root``, laid out as installed.

    A copy rather than symbolic links: the static loader resolves a linked ``__init__.py`` to the
    repository's ``svr/`` and would look for the subpackages there again.
    """
    package = root / "svr"
    shutil.copytree(REPO / "svr", package, ignore=_not_source)
    for name in SUBPACKAGES:
        shutil.copytree(REPO / name, package / name, ignore=_not_source)


@event_priority(50)  # before mkdocstrings' own on_config, which creates the handler
def on_config(config):
    """Point mkdocstrings' Python handler at a copy of the installed layout."""
    global _layout_dir
    if _layout_dir is None:
        _layout_dir = Path(tempfile.mkdtemp(prefix="svr-docs-layout-"))
    shutil.rmtree(_layout_dir / "svr", ignore_errors=True)  # fresh on every (re)build
    _installed_layout(_layout_dir)
    handlers = config.plugins["mkdocstrings"].config.handlers
    handlers.setdefault("python", {})["paths"] = [str(_layout_dir)]
    return config


def on_shutdown():
    """Remove the temporary layout."""
    global _layout_dir
    if _layout_dir is not None:
        shutil.rmtree(_layout_dir, ignore_errors=True)
        _layout_dir = None


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def cli_reference() -> str:
    """Markdown with ``svr --help`` and the help of every subcommand, in the parser's order."""
    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_WIDTH  # argparse wraps to the terminal width
    try:
        from svr.cli import build_parser

        parser = build_parser()
        parts = ["## svr", "", "```text", parser.format_help().rstrip(), "```", ""]
        for name, sub in _subcommands(parser).items():
            parts += [f"## svr {name}", "", "```text", sub.format_help().rstrip(), "```", ""]
    finally:
        if previous is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = previous
    return "\n".join(parts)


def on_page_markdown(markdown, page, config, files):
    """Fill the command-line reference into the page that holds the marker."""
    if CLI_MARKER in markdown:
        return markdown.replace(CLI_MARKER, cli_reference())
    return markdown
