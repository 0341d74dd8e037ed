"""``svr bids``: a tiny BIDS dataset made here (2 subjects, one with a session), fast settings."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
from contextlib import redirect_stdout
from pathlib import Path

import pytest
import torch
from scipy import ndimage
from synthetic import small_phantom

import svr.cli
from svr.apps.bids import (
    BidsError,
    Participant,
    find_participants,
    participant_age,
    participant_outputs,
)
from svr.apps.bids_group import GROUP_HTML, GROUP_TISSUE_PNG, GROUP_TSV
from svr.image import load_nifti, save_nifti
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import canonicalize

# As tests/test_cli_reconstruct.py: three 26 x 26 x 13 stacks of a 20-week phantom at 2 mm.
FAST = [
    "--output-resolution", "2.5", "--iterations", "2", "--sr-iterations", "5",
    "--svr-iterations", "3", "--registration", "stack", "--device", "cpu", "-q",
]  # fmt: skip
SUBJECTS = (("01", None, 0), ("02", "1", 1))
"""(subject, session, simulation seed) of the dataset."""


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data), encoding="utf-8")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, Path]:
    """A BIDS dataset and a derivatives folder of its brain masks."""
    root = tmp_path_factory.mktemp("bids")
    bids_dir, masks_dir = root / "study", root / "study-masks"
    bids_dir.mkdir()
    _write_json(bids_dir / "dataset_description.json", {"Name": "tiny", "BIDSVersion": "1.9.0"})
    (bids_dir / "participants.tsv").write_text("participant_id\nsub-01\nsub-02\n")
    masks_dir.mkdir()
    _write_json(masks_dir / "dataset_description.json", {
        "Name": "masks", "BIDSVersion": "1.9.0", "DatasetType": "derivative",
        "GeneratedBy": [{"Name": "manual"}]})  # fmt: skip
    volume, mask = small_phantom()
    phantom = canonicalize(volume, mask, name="phantom")
    for subject, session, seed in SUBJECTS:
        config = SimulationConfig(
            thickness_mm=5.0, in_plane_mm=2.5, margin_mm=3.0, random_walk_rotation_deg=3.0,
            random_walk_translation_mm=1.5, noise=0.01, seed=seed,
        )  # fmt: skip
        case = simulate_case(phantom, config)
        prefix = f"sub-{subject}" + (f"_ses-{session}" if session else "")
        rel = Path(f"sub-{subject}") / (f"ses-{session}" if session else "") / "anat"
        (bids_dir / rel).mkdir(parents=True)
        (masks_dir / rel).mkdir(parents=True)
        for run, stack in enumerate(case.stacks, start=1):
            save_nifti(stack.image, bids_dir / rel / f"{prefix}_run-{run}_T2w.nii.gz")
            _write_json(bids_dir / rel / f"{prefix}_run-{run}_T2w.json", {"SliceThickness": 5.0})
            save_nifti(stack.mask, masks_dir / rel / f"{prefix}_run-{run}_desc-brain_mask.nii.gz")
    return bids_dir, masks_dir


def _main(argv: list[str]) -> tuple[int, str]:
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = svr.cli.main(argv)
    return code, buffer.getvalue()


@pytest.fixture(scope="module")
def participant_run(dataset, tmp_path_factory) -> Path:
    """The participant level for sub-01 (given masks)."""
    bids_dir, masks_dir = dataset
    out = tmp_path_factory.mktemp("out") / "derivatives"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        code, _ = _main([
            "bids", str(bids_dir), str(out), "participant", "--participant-label", "01",
            "--masks-dir", str(masks_dir), *FAST])  # fmt: skip
        # In this process, the participant's thread count is not left behind (a caller that
        # runs one thread beside other processes would be slowed many times over).
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    assert code == 0
    return out


def test_finds_stacks_masks_and_thicknesses_with_pybids(dataset):
    bids_dir, masks_dir = dataset
    found = find_participants(bids_dir, masks_dir=masks_dir)
    assert [p.label for p in found] == ["sub-01", "sub-02_ses-1"]
    assert [p.folder.as_posix() for p in found] == ["sub-01", "sub-02/ses-1"]
    for participant in found:
        assert len(participant.stacks) == 3
        for stack in participant.stacks:
            assert stack.thickness_mm == 5.0
            assert stack.mask is not None
            assert stack.mask.name == stack.path.name.replace("_T2w", "_desc-brain_mask")
    # Labels with or without the prefix; a session filter.
    assert [p.label for p in find_participants(bids_dir, ["sub-02"], ["ses-1"])] == ["sub-02_ses-1"]
    assert find_participants(bids_dir, ["01"])[0].stacks[0].mask is None


def test_participant_level_writes_bids_derivatives(participant_run, dataset):
    out = participant_run
    (participant,) = find_participants(dataset[0], ["01"], masks_dir=dataset[1])
    names = participant_outputs(participant)
    folder = out / "sub-01"
    for path in (names.volume, names.mask, names.transforms, names.qa, names.sidecar):
        assert (folder / path).is_file(), path
    assert (folder / names.volume).name == "sub-01_rec-svr_T2w.nii.gz"
    assert not (out / "sub-02").exists()
    description = json.loads((out / "dataset_description.json").read_text())
    assert description["DatasetType"] == "derivative"
    assert description["GeneratedBy"][0]["Name"] == "fetal-svr"
    sidecar = json.loads((folder / names.sidecar).read_text())
    svr_info = sidecar["svr"]
    assert sidecar["Sources"] == [
        f"bids:raw:sub-01/anat/sub-01_run-{r}_T2w.nii.gz" for r in (1, 2, 3)
    ]
    assert svr_info["software"]["fetal-svr"] == svr.__version__
    assert svr_info["options"]["start"] == "stack"
    assert svr_info["options"]["reconstruction"]["initialisation"]["kind"] == "stack"
    # Every option of the reconstruction with its value, as the command line names it.
    assert svr_info["options"]["options"]["--svr-iterations"] == 3
    assert svr_info["options"]["masks"] == "given"
    assert [len(i["sha256"]) for i in svr_info["inputs"]] == [64] * 3
    assert len(svr_info["initialisation"]) == 3 and svr_info["slices"] > 0
    assert svr_info["device"] == "cpu" and "total_seconds" in svr_info
    assert set(svr_info["timings_s"]) and svr_info["model"] is None
    # The brain's mirror plane, the verdict's evidence, searched in every orientation for a
    # scanner-frame output (no tilt from a canonical x = 0).
    assert -1 <= svr_info["mirror_correlation"] <= 1 and svr_info["mirror_tilt_deg"] is None
    # No atlas: no atlas fit, no turn.
    assert svr_info["atlas_turn_deg"] is None and svr_info["atlas_turn_applied"] is None
    # No temporary folders are left behind.
    assert not [p for p in out.rglob(".*")]
    volume = load_nifti(folder / names.volume)
    mask = load_nifti(folder / names.mask)
    assert torch.allclose(volume.affine, mask.affine) and float(mask.data.sum()) > 0


def test_results_are_those_of_svr_reconstruct(participant_run, dataset, tmp_path):
    bids_dir, masks_dir = dataset
    stacks = sorted((bids_dir / "sub-01" / "anat").glob("*_T2w.nii.gz"))
    masks = [
        masks_dir / "sub-01" / "anat" / s.name.replace("_T2w", "_desc-brain_mask") for s in stacks
    ]
    out = tmp_path / "srr.nii.gz"
    code, _ = _main([
        "reconstruct", "--input-stacks", *map(str, stacks), "--stack-masks", *map(str, masks),
        "--thicknesses", "5", "--output-volume", str(out), *FAST])  # fmt: skip
    assert code == 0
    ours = load_nifti(participant_run / "sub-01" / "anat" / "sub-01_rec-svr_T2w.nii.gz")
    reference = load_nifti(out)
    assert torch.equal(ours.data, reference.data)
    assert torch.equal(ours.affine, reference.affine)


def test_rerun_skips_and_group_level_reports_every_participant(participant_run, dataset, caplog):
    bids_dir, masks_dir = dataset
    out = participant_run
    before = (out / "sub-01" / "anat" / "sub-01_rec-svr_T2w.json").stat().st_mtime_ns
    # All participants: sub-01 is done and skipped, sub-02 (its session) is reconstructed.
    code, stdout = _main(["bids", str(bids_dir), str(out), "participant", "--masks-dir",
                          str(masks_dir), *FAST])  # fmt: skip
    assert code == 0 and "1 of 1 participants reconstructed" in stdout
    assert (out / "sub-01" / "anat" / "sub-01_rec-svr_T2w.json").stat().st_mtime_ns == before
    assert (out / "sub-02" / "ses-1" / "anat" / "sub-02_ses-1_rec-svr_T2w.nii.gz").is_file()
    code, stdout = _main(["bids", str(bids_dir), str(out), "participant", *FAST])
    assert code == 0 and "nothing to do" in stdout
    code, stdout = _main(["bids", str(bids_dir), str(out), "group"])
    assert code == 0 and "2 participants" in stdout
    rows = (out / GROUP_TSV).read_text().splitlines()
    assert rows[0].split("\t")[:2] == ["participant_id", "session_id"]
    assert [r.split("\t")[:2] for r in rows[1:]] == [["sub-01", "n/a"], ["sub-02", "ses-1"]]
    page = (out / GROUP_HTML).read_text()
    for qa in (
        "sub-01/anat/sub-01_rec-svr_qa.png",
        "sub-02/ses-1/anat/sub-02_ses-1_rec-svr_qa.png",
    ):
        assert f"src='{qa}'" in page and (out / qa).is_file()


def test_a_killed_participant_leaves_no_partial_derivative(dataset, tmp_path, monkeypatch):
    bids_dir, masks_dir = dataset
    out = tmp_path / "derivatives"

    def crash(*args, **kwargs):
        raise KeyboardInterrupt  # as a job killed mid-write

    monkeypatch.setattr("svr.reconstruction.qa.qa_figure", crash)
    argv = ["bids", str(bids_dir), str(out), "participant", "--participant-label", "01",
            "--masks-dir", str(masks_dir), *FAST]  # fmt: skip
    code, _ = _main(argv)
    assert code == 130
    assert not (out / "sub-01").exists()
    assert [p.name for p in out.iterdir()] == ["dataset_description.json"]
    monkeypatch.undo()
    # The rerun redoes that participant.
    code, _ = _main(argv)
    assert code == 0 and (out / "sub-01" / "anat" / "sub-01_rec-svr_qa.png").is_file()


def _bad(argv: list[str], capsys) -> str:
    code = svr.cli.main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert len(err.splitlines()) == 1, err
    return err


def test_bad_inputs_give_one_line_and_write_nothing(dataset, tmp_path, capsys):
    bids_dir, masks_dir = dataset
    out = tmp_path / "out"
    # Not a BIDS folder.
    plain = tmp_path / "plain"
    shutil.copytree(bids_dir, plain)
    (plain / "dataset_description.json").unlink()
    err = _bad(["bids", str(plain), str(out), "participant", *FAST], capsys)
    assert "not a BIDS dataset" in err and "--skip-bids-validation" in err
    # An unknown participant label.
    err = _bad(["bids", str(bids_dir), str(out), "participant", "--participant-label", "07",
                *FAST], capsys)  # fmt: skip
    assert "--participant-label 07: no such participant" in err and "01, 02" in err
    # A subject with no T2w.
    empty = tmp_path / "empty"
    shutil.copytree(bids_dir, empty)
    (empty / "sub-03" / "anat").mkdir(parents=True)
    (empty / "sub-03" / "anat" / "sub-03_run-1_T1w.nii.gz").write_bytes(
        (bids_dir / "sub-01" / "anat" / "sub-01_run-1_T2w.nii.gz").read_bytes()
    )
    err = _bad(["bids", str(empty), str(out), "participant", *FAST], capsys)
    assert "sub-03: no T2w stack" in err
    # Masks for a different number of stacks.
    fewer = tmp_path / "fewer-masks"
    shutil.copytree(masks_dir, fewer)
    (fewer / "sub-01" / "anat" / "sub-01_run-3_desc-brain_mask.nii.gz").unlink()
    err = _bad(["bids", str(bids_dir), str(out), "participant", "--masks-dir", str(fewer),
                *FAST], capsys)  # fmt: skip
    assert "no brain mask (desc-brain_mask) for sub-01_run-3_T2w.nii.gz of sub-01" in err
    # An output folder inside the input dataset.
    err = _bad(["bids", str(bids_dir), str(bids_dir / "derivatives" / "svr"), "participant",
                *FAST], capsys)  # fmt: skip
    assert "inside the input dataset" in err
    assert not out.exists() and not (bids_dir / "derivatives").exists()
    # Group level before any participant.
    err = _bad(["bids", str(bids_dir), str(tmp_path), "group"], capsys)
    assert "no finished participant" in err


def test_participant_age_reads_the_session_then_the_participants_table(tmp_path):
    (tmp_path / "participants.tsv").write_text(
        "participant_id\tga\tsex\nsub-01\t27.5\tF\nsub-02\tn/a\tM\nsub-03\t31\tF\n"
    )
    (tmp_path / "sub-03").mkdir()
    (tmp_path / "sub-03" / "sub-03_sessions.tsv").write_text("session_id\tga\nses-1\t29.0\n")
    (tmp_path / "sub-01").mkdir()
    (tmp_path / "sub-01" / "sub-01_sessions.tsv").write_text("session_id\tscanner\nses-1\t3T\n")
    assert participant_age(tmp_path, Participant("01", None), "ga") == 27.5
    assert participant_age(tmp_path, Participant("03", "1"), "ga") == 29.0  # the session's
    assert participant_age(tmp_path, Participant("03", None), "ga") == 31.0
    # A sessions table without the column: the participants table's.
    assert participant_age(tmp_path, Participant("01", "1"), "ga") == 27.5
    with pytest.raises(BidsError, match=r"participants.tsv: sub-02's ga is 'n/a', not a"):
        participant_age(tmp_path, Participant("02", None), "ga")
    with pytest.raises(BidsError, match=r"participants.tsv: no row for sub-04"):
        participant_age(tmp_path, Participant("04", None), "ga")
    with pytest.raises(BidsError, match=r"participants.tsv: no column 'age' \(--age-column age\)"):
        participant_age(tmp_path, Participant("01", None), "age")
    with pytest.raises(BidsError, match=r"sub-03_sessions.tsv: no row for ses-2"):
        participant_age(tmp_path, Participant("03", "2"), "ga")
    (tmp_path / "participants.tsv").unlink()
    with pytest.raises(BidsError, match=r"participants.tsv: no such file"):
        participant_age(tmp_path, Participant("01", None), "ga")


def test_each_participant_is_fitted_to_the_atlases_of_its_own_age(dataset, tmp_path, capsys):
    bids_dir, masks_dir = dataset
    study = tmp_path / "study"
    shutil.copytree(bids_dir, study)
    (study / "participants.tsv").write_text("participant_id\tga\nsub-01\t25\nsub-02\t33\n")
    # An atlas folder: GA20 the subjects' own brain, GA30 a brain of noise in the same mask.
    volume, mask = small_phantom()
    atlas = tmp_path / "atlas"
    for name, image in (
        ("GA20_phantom", volume),
        ("GA30_noise", type(volume)(torch.rand(volume.shape) * mask.data, volume.affine)),
    ):
        (atlas / name).mkdir(parents=True)
        save_nifti(image, atlas / name / "srr.nii.gz")
        save_nifti(mask, atlas / name / "mask.nii.gz")
    out = tmp_path / "out"
    cnn = ["--registration", "cnn", "--atlas-dir", str(atlas), "--age-column", "ga"]
    code, _ = _main([
        "bids", str(study), str(out), "participant", "--participant-label", "01",
        "--masks-dir", str(masks_dir), *FAST, *cnn, "--atlas-age-window", "5"])  # fmt: skip
    assert code == 0
    (participant,) = find_participants(study, ["01"], masks_dir=masks_dir)
    sidecar = json.loads((out / "sub-01" / participant_outputs(participant).sidecar).read_text())
    info = sidecar["svr"]
    assert info["gestational_age_weeks"] == 25.0
    assert [Path(a["volume"]).parent.name for a in info["atlas"]] == ["GA20_phantom", "GA30_noise"]
    assert len(info["atlas_ncc"]) == 2 and info["atlas_ncc"][0] > info["atlas_ncc"][1]
    assert info["atlas_chosen"] == 0
    assert info["atlas_turn_deg"] >= 0 and isinstance(info["atlas_turn_applied"], bool)
    # Bad uses: one line, before any work.
    err = _bad(["bids", str(study), str(tmp_path / "o2"), "participant", *FAST,
                "--age-column", "ga"], capsys)  # fmt: skip
    assert "--age-column needs --atlas-dir" in err
    err = _bad(["bids", str(study), str(tmp_path / "o2"), "participant", *FAST, *cnn[:4],
                "--age-column", "age"], capsys)  # fmt: skip
    assert "participants.tsv: no column 'age'" in err
    err = _bad(["bids", str(study), str(tmp_path / "o2"), "participant", *FAST, *cnn,
                "--gestational-age", "25"], capsys)  # fmt: skip
    assert "give --gestational-age or --age-column, not both" in err
    err = _bad(["bids", str(study), str(tmp_path / "o2"), "participant", *FAST, *cnn[:4]],
               capsys)  # fmt: skip
    assert "--atlas-dir needs the fetus's --gestational-age" in err
    assert not (tmp_path / "o2").exists()


def test_extra_masks_are_refused(dataset, tmp_path):
    bids_dir, masks_dir = dataset
    more = tmp_path / "more-masks"
    shutil.copytree(masks_dir, more)
    extra = more / "sub-01" / "anat" / "sub-01_run-4_desc-brain_mask.nii.gz"
    shutil.copy(more / "sub-01" / "anat" / "sub-01_run-1_desc-brain_mask.nii.gz", extra)
    with pytest.raises(BidsError, match="sub-01 has 4 brain masks for 3 T2w stacks"):
        find_participants(bids_dir, ["01"], masks_dir=more)


SLURM_SCRIPT = Path(__file__).resolve().parents[1] / "docs" / "slurm" / "svr-bids-array.sh"


def test_the_documented_slurm_array_script_runs_one_participant_per_task(tmp_path):
    """Each task's participant comes from its row of participants.tsv; options pass through."""
    study = tmp_path / "study"
    study.mkdir()
    (study / "participants.tsv").write_text("participant_id\tage\nsub-01\t28\nsub-02\t30\n")
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "svr").write_text('#!/bin/sh\nprintf "%s\\n" "$@" > "$CALLED"\n')
    (fake / "svr").chmod(0o755)
    env = {
        "PATH": f"{fake}:/usr/bin:/bin",
        "BIDS_DIR": str(study),
        "OUTPUT_DIR": str(tmp_path / "out"),
        "CALLED": str(tmp_path / "called.txt"),
    }
    done = subprocess.run(
        ["bash", str(SLURM_SCRIPT), "--masks-dir", "study-masks"],
        env={**env, "SLURM_ARRAY_TASK_ID": "2"},
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "called.txt").read_text().splitlines() == [
        "bids", str(study), str(tmp_path / "out"), "participant", "--participant-label",
        "sub-02", "--masks-dir", "study-masks",
    ]  # fmt: skip
    # A task beyond the list, and a run outside an array, fail with a message.
    for extra in ({"SLURM_ARRAY_TASK_ID": "3"}, {}):
        done = subprocess.run(
            ["bash", str(SLURM_SCRIPT)], env={**env, **extra}, capture_output=True, text=True,
            check=False,
        )  # fmt: skip
        assert done.returncode != 0 and done.stderr.strip()


def test_the_help_points_to_the_job_array_and_n_jobs():
    help_text = svr.cli.build_parser()._subparsers._group_actions[0].choices["bids"].description
    assert "SLURM_ARRAY_TASK_ID" in help_text and "--n-jobs" in help_text
    assert "docs/slurm/svr-bids-array.sh" in help_text


def test_participants_run_side_by_side_with_n_jobs(dataset, tmp_path):
    bids_dir, masks_dir = dataset
    out = tmp_path / "derivatives"
    fast = [*FAST, "--iterations", "1", "--registration", "none"]
    code, stdout = _main(["bids", str(bids_dir), str(out), "participant", "--n-jobs", "2",
                          "--masks-dir", str(masks_dir), *fast])  # fmt: skip
    assert code == 0 and "2 of 2 participants reconstructed" in stdout
    for label, folder in (("sub-01", "sub-01"), ("sub-02_ses-1", "sub-02/ses-1")):
        sidecar = json.loads((out / folder / "anat" / f"{label}_rec-svr_T2w.json").read_text())
        assert sidecar["svr"]["threads"] >= 1 and sidecar["svr"]["slices"] > 0


@pytest.mark.slow
def test_the_real_scan_as_a_bids_dataset_matches_svr_reconstruct(shared_data, tmp_path):
    """The real clinical scan copied into a BIDS layout: svr bids == svr reconstruct."""
    real = shared_data / "stacks" / "real-mialsrtk-sub01"
    bids_dir, masks_dir = tmp_path / "real", tmp_path / "real-masks"
    for root in (bids_dir, masks_dir):
        (root / "sub-01" / "anat").mkdir(parents=True)
        _write_json(root / "dataset_description.json", {"Name": "real", "BIDSVersion": "1.9.0"})
    stacks, masks = [], []
    for run in range(1, 7):
        name = f"sub-01_run-{run}_T2w"
        for suffix in (".nii.gz", ".json"):
            shutil.copy(real / f"{name}{suffix}", bids_dir / "sub-01" / "anat" / f"{name}{suffix}")
        mask = masks_dir / "sub-01" / "anat" / f"sub-01_run-{run}_desc-brain_mask.nii.gz"
        shutil.copy(real / f"{name}_desc-brain_mask.nii.gz", mask)
        stacks.append(str(bids_dir / "sub-01" / "anat" / f"{name}.nii.gz"))
        masks.append(str(mask))
    out = tmp_path / "derivatives"
    code, _ = _main(["bids", str(bids_dir), str(out), "participant", "--masks-dir",
                     str(masks_dir), "-q"])  # fmt: skip
    assert code == 0
    single = tmp_path / "single.nii.gz"
    code, _ = _main(["reconstruct", "--input-stacks", *stacks, "--stack-masks", *masks,
                     "--thicknesses", "3", "--output-volume", str(single), "-q"])  # fmt: skip
    assert code == 0
    ours = load_nifti(out / "sub-01" / "anat" / "sub-01_rec-svr_T2w.nii.gz")
    reference = load_nifti(single)
    assert torch.equal(ours.data, reference.data) and torch.equal(ours.affine, reference.affine)


def test_the_provenance_names_the_model_by_its_weights_hash():
    from svr.apps.bids_participant import model_digest
    from svr.files import file_sha256
    from svr.models.pretrained import stack_pose_model_path

    expected = file_sha256(stack_pose_model_path() / "model.safetensors")
    assert model_digest("stack-pose") == expected and len(expected) == 64


def test_tissue_labels_are_derivatives_and_the_group_tabulates_them(dataset, tmp_path, capsys):
    """--tissue-labels: each participant's labels, numbers and report; the group's cohort table."""
    bids_dir, masks_dir = dataset
    study = tmp_path / "study"
    shutil.copytree(bids_dir, study)
    (study / "participants.tsv").write_text("participant_id\tga\nsub-01\t20\nsub-02\t21\n")
    # An atlas folder of the subjects' own phantom brain at two ages (two atlases to fuse), its
    # labels cut from its intensities (the bright core "ventricles", the rest "white matter", the
    # rim "cortex").
    volume, mask = small_phantom()
    inside = mask.data > 0.5
    labels = torch.zeros(volume.shape)
    labels[inside] = 1.0
    labels[inside & (volume.data > volume.data[inside].quantile(0.8))] = 2.0
    rim = inside & ~torch.from_numpy(ndimage.binary_erosion(inside.numpy(), iterations=2))
    labels[rim] = 5.0
    atlas = tmp_path / "atlas"
    for age in (20, 21):
        (atlas / f"GA{age}_phantom").mkdir(parents=True)
        save_nifti(volume, atlas / f"GA{age}_phantom" / "srr.nii.gz")
        save_nifti(mask, atlas / f"GA{age}_phantom" / "mask.nii.gz")
        save_nifti(
            type(volume)(labels, volume.affine), atlas / f"GA{age}_phantom" / "parcellation.nii.gz"
        )
    out = tmp_path / "out"
    cnn = ["--registration", "cnn", "--atlas-dir", str(atlas), "--age-column", "ga"]
    code, _ = _main([
        "bids", str(study), str(out), "participant", "--participant-label", "01",
        "--masks-dir", str(masks_dir), *FAST, *cnn, "--tissue-labels"])  # fmt: skip
    assert code == 0
    (participant,) = find_participants(study, ["01"], masks_dir=masks_dir)
    names = participant_outputs(participant)
    folder = out / "sub-01"
    sidecar = json.loads((folder / names.sidecar).read_text())["svr"]
    tissue = sidecar["tissue"]
    assert "error" not in tissue, tissue
    written = load_nifti(folder / names.labels)
    recon = load_nifti(folder / names.volume)
    assert torch.allclose(written.affine, recon.affine)
    assert set(written.data.unique().tolist()) <= {0.0, 1.0, 2.0, 5.0}
    assert tissue["volumes_ml"]["white_matter"] > 0 and tissue["atlases"]
    assert (folder / names.report).read_text().startswith("<!DOCTYPE html>")
    rows = (folder / names.measures).read_text().splitlines()
    assert rows[0].startswith("key\tname\tvalue") and len(rows) == 18
    assert json.loads((folder / names.measures).with_suffix(".json").read_text())["measures"]
    # the group level: the tissue columns and the cohort plot
    code, _ = _main(["bids", str(study), str(out), "group"])
    assert code == 0
    table = (out / GROUP_TSV).read_text().splitlines()
    header = table[0].split("\t")
    row = dict(zip(header, table[1].split("\t"), strict=True))
    assert {"tissue", "intracranial_ml", "brain_bpd_mm", "gestational_age_weeks"} <= set(header)
    assert row["tissue"] in ("trusted", "not trusted") and row["gestational_age_weeks"] == "20"
    assert float(row["intracranial_ml"]) == pytest.approx(
        tissue["volumes_ml"]["intracranial"], rel=1e-3
    )
    assert (out / GROUP_TISSUE_PNG).is_file()
    assert GROUP_TISSUE_PNG in (out / GROUP_HTML).read_text()
    # --tissue-labels needs the atlases
    err = _bad(["bids", str(study), str(tmp_path / "o2"), "participant", *FAST, "--tissue-labels"],
               capsys)  # fmt: skip
    assert "--tissue-labels needs --atlas-dir" in err
