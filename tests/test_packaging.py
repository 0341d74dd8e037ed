"""One import namespace: the package installs as ``svr`` only, beside users' own packages."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import venv
from pathlib import Path

import pytest
from layout import subpackage_folders

REPO = Path(__file__).resolve().parents[1]


def _run(args: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, env=env, check=False)
    assert result.returncode == 0, f"{args} failed:\n{result.stdout}\n{result.stderr}"
    return result.stdout


def test_subpackages_live_in_the_svr_namespace():
    import svr
    import svr.models.predict
    import svr.reconstruction.pipeline
    import svr.sampling.dataset

    assert Path(svr.models.predict.__file__).parent == REPO / "models"
    assert Path(svr.sampling.dataset.__file__).parent == REPO / "sampling"
    assert Path(svr.reconstruction.pipeline.__file__).parent == REPO / "reconstruction"
    assert (Path(svr.__file__).parent / "py.typed").is_file()


def test_imports_beside_unrelated_models_and_sampling_packages(tmp_path):
    for name in subpackage_folders().values():
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"OWNER = 'user {name}'\n")
    script = textwrap.dedent(
        """
        import models, sampling, reconstruction, masking
        import svr.models.predict, svr.sampling.dataset, svr.reconstruction.pipeline, svr.masking
        from svr.models.predict import load_pose_model
        assert models.OWNER == "user models", models.__file__
        assert sampling.OWNER == "user sampling", sampling.__file__
        assert reconstruction.OWNER == "user reconstruction", reconstruction.__file__
        assert masking.OWNER == "user masking", masking.__file__
        load_pose_model("default")
        print(svr.models.predict.__file__)
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = _run([sys.executable, "-c", script], cwd=tmp_path, env=env)
    assert Path(out.strip()).parent == REPO / "models"


@pytest.mark.slow
def test_wheel_installs_into_a_fresh_venv_and_runs(tmp_path):
    # Build from a copy of the working tree (git-ignored files left out), so that nothing
    # (build/, *.egg-info) lands in the checkout.
    listed = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"]
    tracked = _run(listed, cwd=REPO).split("\0")
    source = tmp_path / "source"
    for name in filter(None, tracked):
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
    dist = tmp_path / "dist"
    build = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "-w", str(dist), "-q"]
    try:  # build offline with this environment's setuptools when it is new enough
        import setuptools

        if int(setuptools.__version__.split(".")[0]) >= 68:
            build.append("--no-build-isolation")
    except ImportError:
        pass
    _run(build, cwd=tmp_path)
    wheels = list(dist.glob("fetal_svr-*.whl"))
    assert len(wheels) == 1
    fresh = tmp_path / "fresh"
    venv.EnvBuilder(with_pip=True).create(fresh)
    python = fresh / "bin" / "python"
    _run(
        [str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheels[0])],
        tmp_path,
    )
    # The dependencies (torch, ...) come from this environment's site-packages, added as a plain
    # path: its .pth files (this checkout's editable install among them) are not processed.
    site = _run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path
    ).strip()
    (Path(site) / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    installed = sorted(p.name for p in Path(site).iterdir())
    for name in subpackage_folders().values():
        assert name not in installed
        assert (Path(site) / "svr" / name / "__init__.py").is_file()
    for model in ("default", "brain_mask", "stack_pose"):
        for name in ("config.json", "model.safetensors", "README.md"):
            assert (Path(site) / "svr" / "models" / "pretrained" / model / name).is_file()
    assert (Path(site) / "svr" / "py.typed").is_file()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = _run([str(fresh / "bin" / "svr"), "--help"], cwd=tmp_path, env=env)
    assert "reconstruct" in out and "segment-stack" in out
    where = _run(
        [
            str(python),
            "-c",
            "import svr.models.predict as p; p.load_pose_model('default'); print(p.__file__)",
        ],
        cwd=tmp_path,
        env=env,
    )
    assert Path(where.strip()).is_relative_to(Path(site))


# Which subpackages each layer may import (module-level and function-level imports alike).
LAYERS = {
    "core": ("svr",),
    "sampling": ("svr", "svr.sampling"),
    "models": ("svr", "svr.sampling", "svr.models"),
    "reconstruction": ("svr", "svr.sampling", "svr.models", "svr.reconstruction"),
    # The masking stage runs before stack preparation and uses preparation and registration
    # (the fusion); nothing below it imports it.
    "masking": ("svr", "svr.sampling", "svr.models", "svr.reconstruction", "svr.masking"),
    # The tissue stage runs after reconstruction on its output files: atlases and labels only.
    "tissue": ("svr", "svr.sampling", "svr.tissue"),
}
UPPER = (
    "svr.sampling",
    "svr.models",
    "svr.reconstruction",
    "svr.masking",
    "svr.tissue",
    "svr.apps",
    "svr.cli",
)
FOLDERS = {folder: name for name, folder in subpackage_folders().items()}
"""The repository's top-level folders installed as subpackages of ``svr`` (pyproject.toml)."""


def _layer(path: Path) -> str | None:
    rel = path.relative_to(REPO).parts
    if rel[0] in FOLDERS:
        return rel[0]
    if rel[0] == "svr" and rel[1] not in ("apps", "cli", "__main__.py"):
        return "core"
    return None


def test_layers_import_only_downwards():
    import ast

    assert set(LAYERS) - {"core"} == set(FOLDERS), "every installed folder has a layer"
    assert set(UPPER) >= set(FOLDERS.values())

    bad = []
    for path in sorted(REPO.glob("*/**/*.py")):
        layer = _layer(path) if path.parts[len(REPO.parts)] != ".venv" else None
        if layer is None:
            continue
        allowed = LAYERS[layer]
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            for name in names:
                upper = [u for u in UPPER if name == u or name.startswith(u + ".")]
                if upper and not any(name == a or name.startswith(a + ".") for a in allowed[1:]):
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno} imports {name}")
                if name.split(".")[0] in FOLDERS:
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno} imports top-level {name}")
    assert not bad, "\n".join(bad)


def _module_imports() -> dict[str, set[str]]:
    """The package's import graph: each ``svr`` module and the ``svr`` modules it imports.

    Module-level and function-level imports alike. ``from package import submodule`` is an edge
    to the submodule (the package's ``__init__`` runs first either way: that is not an edge).
    """
    import ast

    roots = {"svr": REPO / "svr", **{name: REPO / folder for folder, name in FOLDERS.items()}}
    modules: dict[str, Path] = {}
    for package, folder in roots.items():
        for path in folder.rglob("*.py"):
            parts = (package, *path.relative_to(folder).with_suffix("").parts)
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = {f"{node.module}.{a.name}" for a in node.names} & modules.keys()
                if len(subs) < len(node.names) and node.module in modules:
                    edges.add(node.module)
                edges |= subs
            elif isinstance(node, ast.Import):
                edges |= {a.name for a in node.names} & modules.keys()
        graph[name] = edges - {name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_package_import_graph_has_no_cycle():
    graph = _module_imports()
    assert {"svr.masking.stage", "svr.reconstruction.stacks", "svr.cli.reconstruct"} <= set(graph)
    assert "svr.reconstruction.stacks" in graph["svr.masking.stage"]
    assert _cycles(graph) == []
    # The check finds a cycle when there is one (preparation calling the masking stage back).
    graph["svr.reconstruction.stacks"] = graph["svr.reconstruction.stacks"] | {"svr.masking.stage"}
    cycles = _cycles(graph)
    assert any({"svr.masking.stage", "svr.reconstruction.stacks"} <= set(c) for c in cycles)
