"""``svr reconstruct`` and ``svr register``: end to end on a tiny simulated case, and errors."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch
from recon_settings import recon_config
from synthetic import small_phantom

import svr.cli
import svr.files
import svr.reconstruction.pipeline as pipeline
from svr.image import Image, load_nifti, resample_to_grid, save_nifti, stack_slice_poses
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import save_checkpoint
from svr.models.network import ModelConfig, build_model, checkpoint_model_config
from svr.models.predict import load_slice_folder
from svr.pose_io import read_pose_table
from svr.sampling.simulate import SimulationConfig, simulate_case, write_case
from svr.sampling.volume import canonicalize

F64 = torch.float64
# 2.5 mm in-plane, 5 mm slices of a 20-week phantom at 2 mm: three 26 x 26 x 13 stacks.
FAST = [
    "--thicknesses",
    "5",
    "--output-resolution",
    "2.5",
    "--iterations",
    "2",
    "--sr-iterations",
    "5",
    "--svr-iterations",
    "3",
    "--device",
    "cpu",
    "-q",
]


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    volume, mask = small_phantom()
    config = SimulationConfig(
        thickness_mm=5.0,
        in_plane_mm=2.5,
        margin_mm=3.0,
        random_walk_rotation_deg=3.0,
        random_walk_translation_mm=1.5,
        noise=0.01,
    )
    simulated = simulate_case(canonicalize(volume, mask, name="phantom"), config)
    return write_case(simulated, tmp_path_factory.mktemp("case") / "case")


def inputs(case: Path) -> list[str]:
    stacks = [str(case / "stacks" / f"stack{i}.nii.gz") for i in range(3)]
    masks = [str(case / "masks" / f"stack{i}_mask.nii.gz") for i in range(3)]
    return ["--input-stacks", *stacks, "--stack-masks", *masks]


def correlation(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack([a[mask], b[mask]]).double())[0, 1])


def run_capturing_result(argv: list[str]):
    """Run the CLI in-process and return its exit status and the pipeline's result."""
    results = []

    def spy(*args, **kwargs):
        results.append(real(*args, **kwargs))
        return results[-1]

    real = pipeline.reconstruct
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pipeline, "reconstruct", spy)
        code = svr.cli.main(argv)
    return code, results[0] if results else None


@pytest.fixture(scope="module")
def scanner_run(case, tmp_path_factory):
    """``svr reconstruct --registration none`` with every output."""
    out = tmp_path_factory.mktemp("none")
    outputs = {
        "volume": out / "srr.nii.gz",
        "slices": out / "slices",
        "transforms": out / "slices.csv",
        "qa": out / "qa.png",
        "log": out / "srr.log",
    }
    argv = ["reconstruct", *inputs(case), *FAST, "--registration", "none"]
    argv += [f"--output-{name}={path}" for name, path in outputs.items()]
    code, result = run_capturing_result(argv)
    assert code == 0
    return outputs, result


def test_volume_is_float32_finite_and_better_than_the_initial_one(case, scanner_run):
    outputs, result = scanner_run
    nii = nib.load(outputs["volume"])
    assert nii.get_data_dtype() == np.float32
    volume = load_nifti(outputs["volume"])
    assert bool(torch.isfinite(volume.data).all()) and float(volume.data.max()) > 0
    # Axis-aligned 2.5 mm grid in the scanner frame around the brain (~60 mm long).
    torch.testing.assert_close(volume.affine[:3, :3], 2.5 * torch.eye(3, dtype=F64))
    assert all(15 <= n <= 45 for n in volume.shape)
    truth = load_nifti(case / "gt_volume.nii.gz")
    brain = resample_to_grid(load_nifti(case / "gt_mask.nii.gz"), volume).data > 0.5
    on_grid = resample_to_grid(truth, volume).data
    final = correlation(volume.data, on_grid, brain)
    initial = correlation(result.initial_volume.data.cpu(), on_grid, brain)
    assert final > initial + 0.01, (final, initial)


def test_transforms_table(case, scanner_run):
    outputs, result = scanner_run
    table = read_pose_table(outputs["transforms"])
    assert table.frame == "scanner" and len(table.files) == len(result.slices)
    assert set(table.files) == {str(case / "stacks" / f"stack{i}.nii.gz") for i in range(3)}
    with outputs["transforms"].open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["excluded"] == "True" for r in rows] == result.excluded.tolist()
    ncc = torch.tensor([float(r["ncc"]) for r in rows])
    torch.testing.assert_close(ncc, result.slice_ncc.double().float())
    assert bool(((ncc >= -1) & (ncc <= 1)).all())
    # Only slices with enough brain to make their NCC meaningful are ever excluded by it.
    pixels = result.slices.masks.flatten(1).sum(1).cpu()
    assert bool((pixels[result.excluded] >= recon_config().schedule.min_slice_pixels).all())


def test_slices_folder_round_trip(scanner_run):
    outputs, result = scanner_run
    items = load_slice_folder(outputs["slices"])
    kept = torch.nonzero(~result.excluded).flatten().tolist()
    assert [s.index for s in items] == kept
    for item in items[:5]:
        expected = result.slices.poses[item.index].cpu()
        torch.testing.assert_close(stack_slice_poses(item.image)[0], expected, atol=1e-4, rtol=1e-5)


def test_qa_figure_and_log(scanner_run):
    outputs, result = scanner_run
    assert outputs["qa"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = outputs["log"].read_text()
    for expected in (
        "# svr reconstruct summary",
        "time per phase (s):",
        "super-resolution: ",
        "start: scanner",
        "--ncc-threshold: 0.5",
        "initialisation per stack:",
        "stack2.nii.gz: none",
        "frame: scanner",
        "excluded slices: ",
    ):
        assert expected in text
    # The rounds (adaptive by default; --iterations 2: the first and the final round, so no
    # verdict), one line each, as the log printed them.
    assert "rounds: 2 (adaptive schedule)\n" in text
    assert [r.stage for r in result.rounds] == ["first", "final"]
    for record in result.rounds:
        assert f"  {record.line()}\n" in text


def test_stack_registration_replaces_an_existing_output_only_when_asked(case, tmp_path, capsys):
    out = tmp_path / "slices.json"
    out.write_text("keep me")
    volume = tmp_path / "srr.nii.gz"
    argv = ["reconstruct", *inputs(case), *FAST, "--iterations", "1", "--registration", "stack"]
    argv += ["--template", "1"]
    argv += ["--output-volume", str(volume), "--output-transforms", str(out)]
    assert svr.cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err == f"svr reconstruct: error: {out}: output exists; pass --overwrite to replace it\n"
    assert out.read_text() == "keep me" and not volume.exists()
    assert svr.cli.main([*argv, "--overwrite"]) == 0
    assert "wrote " in capsys.readouterr().out
    table = read_pose_table(out)
    assert table.frame == "scanner" and volume.exists()


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    config = ModelConfig(
        backbone=BackboneConfig(width=8, depth=2), input_size=(32, 32), spacing_mm=2.0
    )
    folder = tmp_path_factory.mktemp("model") / "tiny"
    weights = build_model(config).state_dict()
    return save_checkpoint(folder, weights, checkpoint_model_config(config))


def test_register_with_a_cnn_runs_end_to_end(case, tiny_model, tmp_path, capsys, monkeypatch):
    # An untrained model's frame is arbitrary, and the brain's mirror plane rightly sends such a
    # volume back to the scanner frame (tests/test_verdict.py); here the canonical outputs' path
    # is what is tested, so the mirror plane is not measured.
    monkeypatch.setattr(
        "svr.reconstruction.pipeline.level_to_midplane", lambda result: (result, None)
    )
    outputs = {"transforms": tmp_path / "poses.csv", "volume": tmp_path / "atlas.nii.gz"}
    argv = ["register", *inputs(case), *FAST, "--iterations", "1", "--registration", "cnn"]
    argv += ["--model", str(tiny_model)]
    argv += ["--output-log", str(tmp_path / "register.log")]
    argv += [f"--output-{name}={path}" for name, path in outputs.items()]
    assert svr.cli.main(argv) == 0
    assert "canonical frame" in capsys.readouterr().out
    table = read_pose_table(outputs["transforms"])
    assert table.frame == "canonical" and bool(table.poses.isfinite().all())
    assert bool(torch.isfinite(load_nifti(outputs["volume"]).data).all())
    log = (tmp_path / "register.log").read_text()
    assert "# svr register summary" in log and "frame: canonical" in log
    assert f"model: {tiny_model}" in log


# --- errors: one line on stderr, exit status 1, nothing written ---


def one_line_error(capsys, command: str = "reconstruct") -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"svr {command}: error: "), err
    assert "Traceback" not in err
    return err.strip()


def write_raw(path: Path, data: np.ndarray, affine: np.ndarray | None = None) -> str:
    affine = np.eye(4) if affine is None else affine
    nib.save(nib.Nifti1Image(data.astype(np.float32), affine), path)
    return str(path)


@pytest.fixture
def bad(case, tmp_path) -> dict[str, list[str]]:
    """Argument lists with one problem each (outputs go to tmp_path / 'out')."""
    stacks = inputs(case)[1:4]
    masks = inputs(case)[5:8]
    mask = load_nifti(masks[0])
    far = mask.affine.clone()
    far[:3, 3] += 1000.0
    nan = np.asarray(nib.load(stacks[0]).dataobj, dtype=np.float32)
    nan[3, 4, 5] = np.nan
    files = {
        "far_mask": str(save_nifti(Image(mask.data, far), tmp_path / "far_mask.nii.gz")),
        "empty_mask": str(
            save_nifti(Image(torch.zeros_like(mask.data), mask.affine), tmp_path / "empty.nii.gz")
        ),
        "flat": write_raw(tmp_path / "flat.nii.gz", np.ones((8, 8))),
        "four_d": write_raw(tmp_path / "four_d.nii.gz", np.ones((8, 8, 4, 2))),
        "nan": write_raw(tmp_path / "nan.nii.gz", nan, nib.load(stacks[0]).affine),
    }
    return {
        "missing": ["--input-stacks", str(tmp_path / "nope.nii.gz")],
        "flat": ["--input-stacks", files["flat"]],
        "four_d": ["--input-stacks", files["four_d"]],
        "nan": ["--input-stacks", files["nan"], *stacks[1:]],
        "far_mask": ["--input-stacks", *stacks, "--stack-masks", files["far_mask"], *masks[1:]],
        "empty_mask": ["--input-stacks", *stacks, "--stack-masks", files["empty_mask"], *masks[1:]],
        "mask_count": ["--input-stacks", *stacks, "--stack-masks", *masks[:2]],
        "thicknesses": ["--input-stacks", *stacks, "--thicknesses", "3", "4"],
        "template": ["--input-stacks", *stacks, "--template", "3"],
        "threshold": ["--input-stacks", *stacks, "--ncc-threshold", "1.5"],
        "no_model": ["--input-stacks", *stacks, "--registration", "cnn", "--model", "nomodel"],
    }


@pytest.mark.parametrize(
    ("problem", "message"),
    [
        ("missing", "nope.nii.gz: no such file"),
        ("flat", "flat.nii.gz: expected a 3D image, got 2D"),
        ("four_d", "four_d.nii.gz: expected a 3D image, got 4D"),
        ("nan", "nan.nii.gz: 1 voxels are NaN or Inf"),
        ("far_mask", "far_mask.nii.gz: the mask does not overlap its stack"),
        ("empty_mask", "empty.nii.gz: the mask is empty"),
        ("mask_count", "--stack-masks: got 2 masks for 3 stacks; give none or one per stack"),
        ("thicknesses", "--thicknesses: got 2 values for 3 stacks; give one for all stacks"),
        ("template", "--template 3: must be a stack index in [0, 3)"),
        ("threshold", "--ncc-threshold must be in [-1, 1], got 1.5"),
        ("no_model", "nomodel: checkpoint folder does not exist"),
    ],
)
def test_bad_inputs_give_one_line_errors(bad, problem, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    argv = ["reconstruct", *bad[problem], "--output-volume", str(out / "srr.nii.gz"), "-q"]
    assert svr.cli.main([*argv, "--output-transforms", str(out / "t.csv")]) == 1
    assert message in one_line_error(capsys)
    assert list(out.iterdir()) == []


def never_called(*args, **kwargs):
    raise AssertionError("the reconstruction started before the outputs were checked")


@pytest.mark.parametrize(
    ("outputs", "message"),
    [
        (["--output-volume", "OUT/srr.mgz"], "--output-volume OUT/srr.mgz: must end in .nii or"),
        (["--output-transforms", "OUT/t.txt"], "--output-transforms OUT/t.txt: must end in .csv"),
        (["--output-qa", "OUT/qa.jpg"], "--output-qa OUT/qa.jpg: must end in .png or .pdf"),
        (
            ["--output-transforms", "OUT/t.csv", "--output-log", "OUT/t.csv"],
            "--output-log OUT/t.csv: the same path as --output-transforms",
        ),
        (["--output-slices", "OUT/no/such/slices"], "output folder OUT/no/such does not exist"),
        (["--output-log", "OUT/srr.nii.gz/log.txt"], "output folder OUT/srr.nii.gz does not"),
    ],
)
def test_bad_outputs_are_refused_before_the_computation(
    case, outputs, message, tmp_path, capsys, monkeypatch
):
    out = tmp_path / "out"
    out.mkdir()
    (out / "srr.nii.gz").write_text("keep me")  # exists: only written with --overwrite
    monkeypatch.setattr(pipeline, "reconstruct", never_called)
    argv = ["reconstruct", *inputs(case), "--output-volume", str(out / "v.nii.gz"), "-q"]
    argv += [arg.replace("OUT", str(out)) for arg in outputs]
    assert svr.cli.main(argv) == 1
    assert message.replace("OUT", str(out)) in one_line_error(capsys)
    assert [p.name for p in out.iterdir()] == ["srr.nii.gz"]
    assert (out / "srr.nii.gz").read_text() == "keep me"


def test_unwritable_output_folder(case, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(svr.files.os, "access", lambda path, mode: False)  # tests run as root
    argv = ["register", *inputs(case), "--output-transforms", str(tmp_path / "t.csv"), "-q"]
    assert svr.cli.main(argv) == 1
    assert f"output folder {tmp_path} is not writable" in one_line_error(capsys, "register")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["0", "-0.5", "nan"])
def test_output_resolution_must_be_positive(case, value, tmp_path, capsys):
    argv = ["reconstruct", *inputs(case), "--output-volume", str(tmp_path / "v.nii.gz")]
    assert svr.cli.main([*argv, f"--output-resolution={value}"]) == 1
    err = one_line_error(capsys)
    assert f"--output-resolution must be a finite number > 0, got {float(value)}" in err
    assert list(tmp_path.iterdir()) == []


def test_register_needs_an_output(case, capsys):
    assert svr.cli.main(["register", *inputs(case), "-q"]) == 1
    assert "nothing to write: give --output-transforms" in one_line_error(capsys, "register")


def test_help_uses_nesvor_option_names(capsys):
    with pytest.raises(SystemExit) as info:
        svr.cli.main(["reconstruct", "--help"])
    assert info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    # What a user must give and what they get comes first, then the options in sections.
    assert text.index("You give the stacks") < text.index("options:") < text.index("inputs:")
    for section in ("outputs:", "initialisation:", "rounds:", "super-resolution:", "outliers:"):
        assert section in text
    for option in (
        "--input-stacks",
        "--stack-masks",
        "--thicknesses",
        "--output-volume",
        "--output-resolution",
        "--output-slices",
        "--registration {stack,cnn,atlas,none}",
        "--output-log",
        "(default: 0.8)",
        "svr reconstruct --input-stacks ax.nii.gz",
    ):
        assert option in text


def test_options_resolve_once_into_the_job() -> None:
    from svr.cli.recon_options import build_job

    parser = svr.cli.build_parser()
    base = ["reconstruct", "--input-stacks", "a.nii.gz", "--output-volume", "out.nii.gz"]

    def job(*extra):
        return build_job(parser.parse_args([*base, *extra]), ["a.nii.gz"], None, None, "cpu")

    default = job()
    assert default.config.packets == 2 and default.config.initialisation.kind == "stack"
    assert default.config.schedule.rounds == 16 and default.model is None
    assert job("--packets", "3").config.packets == 3
    # --registration cnn with the shipped stack-pose model: the learned start and its schedule.
    learned = job("--registration", "cnn")
    assert learned.config.initialisation.kind == "learned" and learned.model == "stack-pose"
    assert (learned.config.schedule.rounds, learned.config.schedule.converged_deg) == (24, 0.15)
    assert learned.config.schedule.polish == 0.5
    assert job("--registration", "cnn", "--polish", "1").config.schedule.polish == 1.0
    assert not learned.config.initialisation.slice_trajectory
    on = job("--registration", "cnn", "--slice-trajectory").config.initialisation
    assert on.slice_refinement and on.slice_trajectory
    assert job("--registration", "cnn", "--iterations", "3").config.schedule.rounds == 3
    slices = job("--registration", "cnn", "--model", "slice-pose")
    assert slices.config.initialisation.kind == "learned-slices"
    assert job("--registration", "none").config.initialisation.kind == "scanner"
    assert job("--schedule", "fixed").config.schedule.rounds == 5


def test_old_spellings_still_work_with_a_deprecation_message(caplog) -> None:
    from svr.cli.recon_options import initialisation_kind

    with caplog.at_level(logging.WARNING):
        assert initialisation_kind("cnn", "none") == "atlas"
    assert "--registration cnn --model none is deprecated" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert initialisation_kind("cnn", "default") == "learned-slices"
    assert "write --model slice-pose" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert initialisation_kind("cnn", "slice-pose") == "learned-slices"
        assert initialisation_kind("cnn", "stack-pose") == "learned"
    assert caplog.text == ""


@pytest.mark.parametrize("given", ["volumes", "folder"])
def test_reconstruct_takes_the_frame_of_an_atlas_that_fits_clearly_better(
    case, tmp_path, caplog, given
):
    # Two atlases: first a brain of the same mask with a texture unlike the fetus's, then the
    # fetus's own brain (as a neighbouring age that matches would be): it fits clearly better
    # (by more than 0.05 NCC), so the output takes its frame.
    truth, brain = load_nifti(case / "gt_volume.nii.gz"), load_nifti(case / "gt_mask.nii.gz")
    noise = torch.from_numpy(np.random.default_rng(0).random(truth.shape)).float()
    folder = tmp_path / "atlas"
    volumes = [folder / "GA20_unlike" / "srr.nii.gz", folder / "GA21_own" / "srr.nii.gz"]
    for path, data in zip(volumes, (noise * brain.data, truth.data), strict=True):
        path.parent.mkdir(parents=True)
        save_nifti(Image(data, truth.affine), path)
        save_nifti(brain, path.with_name("mask.nii.gz"))
    caplog.set_level(logging.INFO, logger="svr.reconstruction.atlas_frame")
    log = tmp_path / "srr.log"
    argv = ["reconstruct", *inputs(case), *FAST, "--registration", "atlas"]
    if given == "volumes":
        argv += ["--atlas-volume", *map(str, volumes)]
        argv += ["--atlas-mask", *(str(v.with_name("mask.nii.gz")) for v in volumes)]
    else:  # every age within a week of 20.4: GA20 (the nearest, preferred) and GA21
        argv += ["--atlas-dir", str(folder), "--gestational-age", "20.4"]
    argv += ["--output-volume", str(tmp_path / "srr.nii.gz"), "--output-log", str(log)]
    code, result = run_capturing_result(argv)
    assert code == 0 and result is not None
    assert "atlas frame: atlas 2 of 2 (final NCC" in caplog.text
    assert len(result.atlas_ncc) == 2 and result.atlas_ncc[1] > result.atlas_ncc[0] + 0.05
    assert result.atlas_chosen == 1
    summary = log.read_text()
    assert f"atlas frame: {volumes[1]}\n" in summary
    assert f"{volumes[0]}: NCC {result.atlas_ncc[0]:.3f}" in summary
