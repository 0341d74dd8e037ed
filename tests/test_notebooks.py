"""The notebooks in notebooks/ are stored clean and run top to bottom in a fresh kernel.

Each notebook runs in small mode (``SVR_NOTEBOOK_SMALL=1``) with nbclient in a new kernel of this
interpreter (a kernel spec written to a temporary folder and found through ``JUPYTER_PATH``, so
the tests never use another Python's kernel), writing its results into a temporary folder
(``SVR_NOTEBOOK_OUTPUT_DIR``) that the tests then check.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = ("01_loss.ipynb", "02_alignment.ipynb", "03_reconstruction_qa.ipynb")
KERNEL_NAME = "fetal-svr-tests"
CELL_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def jupyter_path(tmp_path_factory) -> Path:
    """A folder holding a kernel spec that starts ``sys.executable``'s ipykernel."""
    root = tmp_path_factory.mktemp("jupyter")
    spec = root / "kernels" / KERNEL_NAME
    spec.mkdir(parents=True)
    kernel = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "fetal-svr (tests)",
        "language": "python",
        "metadata": {"debugger": False},
    }
    (spec / "kernel.json").write_text(json.dumps(kernel))
    return root


def execute(name: str, tmp_path: Path, jupyter_path: Path, monkeypatch, **env: str):
    """Run a notebook in small mode; return the executed notebook and its output folder."""
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setenv("JUPYTER_PATH", str(jupyter_path))
    monkeypatch.setenv("SVR_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("SVR_NOTEBOOK_OUTPUT_DIR", str(out))
    monkeypatch.setenv("SVR_NOTEBOOK_DEVICE", "cpu")
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's inline backend shows figures
    # One torch thread: the small runs are too small to gain from more, and on a busy machine
    # (CI beside a training job) contended OpenMP threads made them several times slower.
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    nb = nbformat.read(NOTEBOOK_DIR / name, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name=KERNEL_NAME,
        resources={"metadata": {"path": str(tmp_path)}},
    )
    start = time.perf_counter()
    client.execute()
    print(f"{name}: {time.perf_counter() - start:.1f} s")
    return nb, out


def outputs(nb) -> list[dict]:
    return [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]


def check_ran_cleanly(nb, min_figures: int) -> None:
    """Every code cell ran, none failed, and the figures were displayed."""
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert all(cell.execution_count is not None for cell in code)
    assert not [o for o in outputs(nb) if o.output_type == "error"]
    figures = [o for o in outputs(nb) if "image/png" in o.get("data", {})]
    assert len(figures) >= min_figures


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_clean(name):
    """nbformat v4, no outputs or execution counts, a first 'parameters' cell read from env."""
    nb = nbformat.read(NOTEBOOK_DIR / name, as_version=4)
    nbformat.validate(nb)
    assert nb.nbformat == 4
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert all(cell.outputs == [] and cell.execution_count is None for cell in code)
    first = code[0]
    assert "parameters" in first.metadata.get("tags", [])
    assert 'SMALL = os.environ.get("SVR_NOTEBOOK_SMALL", "0") == "1"' in first.source
    assert "SVR_NOTEBOOK_OUTPUT_DIR" in first.source
    assert nb.metadata["kernelspec"]["name"] == "python3"


def test_loss_notebook(tmp_path, jupyter_path, monkeypatch):
    nb, out = execute("01_loss.ipynb", tmp_path, jupyter_path, monkeypatch)
    check_ran_cleanly(nb, min_figures=5)
    summary = json.loads((out / "loss_summary.json").read_text())
    # The geodesic distance of a pure rotation error is its angle, wherever the target is.
    assert summary["geodesic_minus_angle_max"] < 1e-9
    # Near pi, a 10 degree error: L2 on the 6-vector wraps (~2 pi), quaternions flip (~2).
    assert summary["near_pi_geodesic_max"] == pytest.approx(math.radians(10), rel=1e-6)
    assert summary["near_pi_l2_max"] > 6.0
    assert summary["near_pi_quaternion_max"] > 1.9
    assert summary["screw_log_stretch"]["90"] == pytest.approx(1.11, abs=0.01)
    # The data-adaptive weights recover diag(cov^-1) of the simulated errors.
    assert summary["max_relative_weight_error"] < 0.25
    for figure in ("sweep_rotation_error", "near_pi", "left_invariance", "coupling"):
        assert (out / f"{figure}.png").stat().st_size > 0
    assert (out / "adaptive_weights.png").stat().st_size > 0


def test_alignment_notebook(tmp_path, jupyter_path, monkeypatch):
    # "train": the tiny model trained in the notebook (whether or not a shipped model exists).
    nb, out = execute(
        "02_alignment.ipynb", tmp_path, jupyter_path, monkeypatch, SVR_NOTEBOOK_CHECKPOINT="train"
    )
    check_ran_cleanly(nb, min_figures=3)
    summary = json.loads((out / "alignment_summary.json").read_text())
    assert len(summary["methods"]) == 3 and summary["methods"][2] == "identity"
    assert summary["num_slices"] == 24
    table3 = ("cc", "mse", "psnr", "ssim", "geodesic", "rotation_deg", "euler_x_deg")
    for method in summary["methods"]:
        stats = summary["summary"][method]
        assert all(math.isfinite(stats[k]["mean"]) for k in (*table3, "translation_mm"))
        assert -1 <= stats["cc"]["mean"] <= 1 and stats["geodesic"]["mean"] >= 0
    tests = summary["paired_tests"]
    assert {t["metric"] for t in tests} == {"geodesic", "rotation_deg", "translation_mm", "cc"}
    assert all(0 <= t["t_pvalue"] <= 1 and t["n"] == 24 for t in tests)
    report = out / "report"
    for name in ("summary.md", "summary.csv", "per_slice.csv", "paired_tests.csv"):
        assert (report / name).is_file()
    assert (out / "worst_cases.png").is_file() and (out / "histograms.png").is_file()
    assert len(list((out / "training" / "checkpoints").glob("step_*"))) == 2
    # section 9: a small simulated case, each slice placed by its stack and by its packet
    assert (out / "packet-case" / "truth_slices.json").is_file()
    assert (out / "packet_starts.png").is_file()


@pytest.fixture(scope="module")
def qa_run(tmp_path_factory, jupyter_path):
    """The reconstruction QA notebook run once on its own simulated case."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        return execute(
            "03_reconstruction_qa.ipynb",
            tmp_path_factory.mktemp("qa"),
            jupyter_path,
            monkeypatch,
        )


def test_reconstruction_qa_notebook(qa_run):
    nb, out = qa_run
    check_ran_cleanly(nb, min_figures=4)
    qa = json.loads((out / "qa_summary.json").read_text())
    assert qa["frame"] == "scanner" and qa["num_slices"] > 10
    assert sum(s["slices"] for s in qa["per_stack"].values()) == qa["num_slices"]
    for scores in qa["comparison"].values():
        assert 0 < scores["ncc"] <= 1 and math.isfinite(scores["psnr_db"])
        assert -1 <= scores["ssim"] <= 1
    assert set(qa["comparison"]) == {
        "initial estimate",
        "reconstruction",
        "reconstruction, global offset removed",
    }
    errors = qa["pose_errors"]
    assert errors["relative_rotation_deg_median"] <= errors["raw_rotation_deg_median"] + 1e-9
    assert errors["relative_rotation_deg_median"] < 10 and errors["global_offset_deg"] < 10
    assert qa["recomputed_ncc"]
    for name in ("recon.nii.gz", "transforms.csv", "qa.png", "orthogonal_views.png"):
        assert (out / name).is_file()
    assert (out / "case" / "truth_slices.json").is_file()


def test_reconstruction_qa_notebook_reads_given_files(qa_run, tmp_path, jupyter_path, monkeypatch):
    """RECON/TRANSFORMS/REFERENCE point the notebook at existing outputs: nothing is rerun."""
    _, made = qa_run
    nb, out = execute(
        "03_reconstruction_qa.ipynb",
        tmp_path,
        jupyter_path,
        monkeypatch,
        SVR_NOTEBOOK_RECON=str(made / "recon.nii.gz"),
        SVR_NOTEBOOK_TRANSFORMS=str(made / "transforms.csv"),
        SVR_NOTEBOOK_REFERENCE=str(made / "case" / "gt_volume.nii.gz"),
        SVR_NOTEBOOK_TRUTH=str(made / "case" / "truth_slices.json"),
    )
    check_ran_cleanly(nb, min_figures=3)
    qa = json.loads((out / "qa_summary.json").read_text())
    before = json.loads((made / "qa_summary.json").read_text())
    assert not (out / "recon.nii.gz").exists()
    assert set(qa["comparison"]) == {"reconstruction", "reconstruction, global offset removed"}
    assert qa["num_excluded"] == before["num_excluded"]
    assert qa["recomputed_ncc"] == before["recomputed_ncc"]
    assert qa["pose_errors"] == before["pose_errors"]
