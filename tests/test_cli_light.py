"""Building the command-line parsers needs no library: these command modules import only the
standard library and light ``svr`` modules at their top level, register their options without
importing anything, and the library defaults their help shows are the library's."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

import svr.cli

CLI = Path(svr.cli.__file__).parent
LIGHT_MODULES = (
    "defaults",
    "evaluate",
    "export_model",
    "sample",
    "segment_stack",
    "simulate",
    "stack_pose_brains",
    "train",
    "train_brain_mask",
    "train_stack_pose",
)
LIGHT_SVR = ("svr.cli", "svr.errors", "svr.files")
"""The ``svr`` modules that a light command module may import at its top level."""


def _top_level_imports(tree: ast.Module) -> list[str]:
    """Modules imported at the top level, outside ``if TYPE_CHECKING:`` blocks."""
    names = []
    for node in tree.body:
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    return names


@pytest.mark.parametrize("name", LIGHT_MODULES)
def test_command_modules_import_no_library_at_their_top_level(name):
    tree = ast.parse((CLI / f"{name}.py").read_text(encoding="utf-8"))
    heavy = [
        module
        for module in _top_level_imports(tree)
        if module.split(".")[0] not in sys.stdlib_module_names and not module.startswith(LIGHT_SVR)
    ]
    assert not heavy, f"svr/cli/{name}.py imports {heavy} at its top level; import in run()"


@pytest.mark.parametrize("name", LIGHT_MODULES)
def test_registering_the_options_imports_nothing(name):
    tree = ast.parse((CLI / f"{name}.py").read_text(encoding="utf-8"))
    for function in ast.walk(tree):
        if isinstance(function, ast.FunctionDef) and (
            function.name == "add_parser" or function.name.startswith("_add_")
        ):
            imports = [
                ast.unparse(node)
                for node in ast.walk(function)
                if isinstance(node, ast.Import | ast.ImportFrom)
            ]
            assert not imports, f"{name}.{function.name} imports {imports}"


def test_the_help_defaults_are_the_library_defaults():
    from svr.cli import defaults
    from svr.masking.recipe import MaskerRecipe
    from svr.masking.train import BrainMaskTrainingConfig
    from svr.models.heads import SE3_ROTATIONS
    from svr.models.stack_pose import StackPoseConfig
    from svr.models.stack_pose_train import StackPoseTrainingConfig
    from svr.sampling.mirror_planes import SYMMETRY_MODES, SYMMETRY_THRESHOLD
    from svr.sampling.simulate import SimulationConfig
    from svr.sampling.synthesis import SYNTHESIS_MODES

    assert tuple(SE3_ROTATIONS) == defaults.SE3_ROTATIONS
    assert tuple(SYNTHESIS_MODES) == defaults.SYNTHESIS_MODES
    assert tuple(SYMMETRY_MODES) == defaults.SYMMETRY_MODES
    assert defaults.SYMMETRY_THRESHOLD == SYMMETRY_THRESHOLD
    for literal, config in (
        (defaults.SIMULATION, SimulationConfig()),
        (defaults.STACK_POSE_MODEL, StackPoseConfig()),
        (defaults.STACK_POSE_TRAINING, StackPoseTrainingConfig()),
        (defaults.BRAIN_MASK_TRAINING, BrainMaskTrainingConfig()),
        (defaults.MASKER_RECIPE, MaskerRecipe()),
    ):
        assert literal == {name: getattr(config, name) for name in literal}, type(config)
