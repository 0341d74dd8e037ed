"""Slices per second of the slice sampler, against SimpleITK and scipy cutting the same slices.

Run from the repository root::

    python benchmarks/bench_sampler.py [--volume SRR --mask MASK] [--batch 256] [--repeats 7]
        [--threads 2] [--device cpu|cuda|all]

Each method cuts a batch of ``--batch`` 128 x 128 slices (1.0 mm in-plane spacing) at random poses
(uniform random rotations, translations uniform within +-20 mm of the brain centre, from a seeded
``torch.Generator``) from a canonical brain volume, and the table gives slices per second (batch
size over the median wall time of ``--repeats`` calls, after one warm-up call; the methods take
turns, call by call, so that changes in the machine's load hit them alike) and how many times
faster our thin-slice sampler is than each row on the same device:

* ``ours``: ``svr.sampling.slicer.sample_slices`` with thin slices (trilinear, no PSF);
* ``ours thick 3 mm (no peer)``: the same with a 3 mm through-plane Gaussian PSF (5 Gauss-Hermite
  samples); no peer computes it, so it is only compared with our thin slices;
* ``SimpleITK``: ``ResampleImageFilter`` per slice, into a (128, 128, 1) output image whose
  origin, direction and spacing encode the slice plane in LPS coordinates, linear interpolator,
  default value 0, with ``SetGlobalDefaultNumberOfThreads(--threads)``;
* ``scipy``: ``ndimage.map_coordinates(order=1, mode="constant", cval=0)`` on the float32 volume
  at the slices' voxel coordinates, the batch split over ``--threads`` Python threads (ndimage
  releases the GIL).

Every method turns the poses into slices inside the timed call. Before timing, the script checks
that the three CPU methods (and ours on CUDA, float32) cut the same slices: max abs difference
below 1e-3 of the intensity maximum and correlation above 0.9999 on the pixels that are non-zero
in either. On CUDA (when available) it also times ours in float16, bracketing each call with
``torch.cuda.synchronize``. Finally it reports the peak memory of one call of ours: on the CPU the
rise of the process's peak resident set (``VmHWM``, reset through ``/proc/self/clear_refs``) over
one call in a fresh process, on CUDA ``torch.cuda.max_memory_allocated``, and the sizes of the
sampler's largest temporaries worked out from the batch shape.

The volume is ``--volume``/``--mask`` (NIfTI), by default the GA28 atlas under ``../shared/data``
when present, else ``svr.sampling.phantom.make_phantom`` when that module exists, else a smooth
random 128^3 volume at 0.8 mm inside a ball mask.
"""

from __future__ import annotations

import argparse
import gc
import itertools
import multiprocessing as mp
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import scipy
import SimpleITK as sitk  # noqa: N813 (the usual alias)
import torch
from bench_common import add_device_options, resolve_devices
from scipy import ndimage
from torch import Tensor

from svr.geometry import quat_to_matrix
from svr.image import Image
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume, canonicalize, load_canonical_volume

REPO_ROOT = Path(__file__).resolve().parents[1]
ATLAS_DIR = REPO_ROOT.parent / "shared/data/atlas/sb-fidon2021/GA28_operated"
SIZE = (128, 128)
SPACING_MM = 1.0
TRANSLATION_MM = 20.0
THIN = SliceConfig(size=SIZE, spacing_mm=SPACING_MM)
THICK = SliceConfig(size=SIZE, spacing_mm=SPACING_MM, thickness_mm=3.0, psf_samples=5)
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])
MAX_DIFF_FRACTION = 1e-3
MIN_CORRELATION = 0.9999

Slicer = Callable[[], object]


def random_volume(seed: int = 0, n: int = 128, spacing_mm: float = 0.8) -> tuple[Image, Image]:
    """A smooth random volume (Gaussian-filtered noise) and a ball mask that keeps its borders 0."""
    rng = np.random.default_rng(seed)
    data = ndimage.gaussian_filter(rng.standard_normal((n, n, n)), sigma=3.0)
    data = data - data.min()
    radius = np.linalg.norm(np.indices((n, n, n)) - (n - 1) / 2, axis=0)
    mask = (radius < 0.4 * n).astype(np.float64)
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= spacing_mm
    affine[:3, 3] = -spacing_mm * (n - 1) / 2
    return Image(torch.from_numpy(data), affine), Image(torch.from_numpy(mask), affine)


def load_volume(volume_path: Path | None, mask_path: Path | None) -> tuple[CanonicalVolume, str]:
    """The canonical volume to cut, and a description of where it came from."""
    if volume_path is None and (ATLAS_DIR / "srr.nii.gz").exists():
        volume_path, mask_path = ATLAS_DIR / "srr.nii.gz", ATLAS_DIR / "mask.nii.gz"
    if volume_path is not None:
        return load_canonical_volume(volume_path, mask_path), str(volume_path.resolve())
    try:
        from svr.sampling.phantom import PhantomConfig, make_phantom
    except ImportError:
        return canonicalize(*random_volume()), "smooth random volume (built in)"
    return canonicalize(*make_phantom(PhantomConfig())), "svr.sampling.phantom.make_phantom"


def random_poses(n: int, generator: torch.Generator) -> Tensor:
    """(n, 4, 4) float64 poses: uniform random rotations, translations uniform in +-20 mm."""
    quat = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    unit = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, :3, :3] = quat_to_matrix(quat)
    poses[:, :3, 3] = (2 * unit - 1) * TRANSLATION_MM
    return poses


def slice_corner(poses: np.ndarray) -> np.ndarray:
    """(B, 3) world position (mm) of each slice's pixel (0, 0), from (B, 4, 4) poses."""
    h, w = SIZE
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    return t - SPACING_MM * ((h - 1) / 2 * R[:, :, 0] + (w - 1) / 2 * R[:, :, 1])


def to_sitk(image: Image) -> sitk.Image:
    """The image as a SimpleITK image: index (x, y, z) = array (i, j, k), LPS physical space."""
    data = image.data.cpu().numpy().astype(np.float32)
    out = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)))
    affine = image.affine.cpu().numpy()
    linear = RAS_TO_LPS @ affine[:3, :3]
    spacing = np.linalg.norm(linear, axis=0)
    out.SetSpacing(spacing.tolist())
    out.SetDirection((linear / spacing).ravel().tolist())
    out.SetOrigin((RAS_TO_LPS @ affine[:3, 3]).tolist())
    return out


def sitk_slices(volume: sitk.Image, poses: np.ndarray) -> np.ndarray:
    """(B, H, W) slices cut by ``ResampleImageFilter``, one output image per slice."""
    resampler = sitk.ResampleImageFilter()
    resampler.SetSize([SIZE[0], SIZE[1], 1])
    resampler.SetOutputSpacing([SPACING_MM] * 3)
    resampler.SetInterpolator(sitk.sitkLinear)
    resampler.SetDefaultPixelValue(0.0)
    resampler.SetOutputPixelType(sitk.sitkFloat32)
    origins = slice_corner(poses) @ RAS_TO_LPS.T
    directions = RAS_TO_LPS @ poses[:, :3, :3]
    out = np.empty((len(poses), *SIZE), dtype=np.float32)
    for n in range(len(poses)):
        resampler.SetOutputOrigin(origins[n].tolist())
        resampler.SetOutputDirection(directions[n].ravel().tolist())
        image = resampler.Execute(volume)  # keep it alive while its array view is read
        out[n] = sitk.GetArrayViewFromImage(image)[0].T  # sitk arrays are (z, y, x) = (1, W, H)
    return out


def scipy_slices(
    data: np.ndarray, affine: np.ndarray, poses: np.ndarray, pool: ThreadPoolExecutor, chunks: int
) -> np.ndarray:
    """(B, H, W) slices from ``map_coordinates`` at their voxel coordinates, in ``chunks`` parts."""
    inverse = np.linalg.inv(affine)[:3]
    steps = SPACING_MM * np.einsum("ij,bjk->bik", inverse[:, :3], poses[:, :3, :2])  # (B, 3, 2)
    corners = slice_corner(poses) @ inverse[:, :3].T + inverse[:, 3]
    a = np.arange(SIZE[0], dtype=np.float64)[:, None]
    b = np.arange(SIZE[1], dtype=np.float64)[None, :]

    def cut(part: slice) -> np.ndarray:
        coords = (
            corners[part, :, None, None]
            + steps[part, :, 0, None, None] * a
            + steps[part, :, 1, None, None] * b
        )  # (n, 3, H, W)
        return ndimage.map_coordinates(
            data, coords.transpose(1, 0, 2, 3), order=1, mode="constant", cval=0.0
        )

    bounds = np.linspace(0, len(poses), chunks + 1).round().astype(int)
    parts = [slice(lo, hi) for lo, hi in itertools.pairwise(bounds)]
    return np.concatenate(list(pool.map(cut, parts)))


def check_same(name: str, reference: np.ndarray, other: np.ndarray) -> str:
    """Raise if ``other`` is not the same slices as ``reference``; else describe the agreement."""
    scale = float(np.abs(reference).max())
    max_diff = float(np.abs(reference - other).max())
    nonzero = (reference != 0) | (other != 0)
    correlation = float(np.corrcoef(reference[nonzero], other[nonzero])[0, 1])
    summary = f"{name}: max |diff| {max_diff:.2e} (max {scale:.3g}), CC {correlation:.7f}"
    if not (max_diff < MAX_DIFF_FRACTION * scale and correlation > MIN_CORRELATION):
        raise RuntimeError(f"different slices, the comparison would not be fair; {summary}")
    return summary


def median_seconds(
    cases: list[tuple[str, Slicer]], repeats: int, device: torch.device
) -> list[tuple[str, float]]:
    """Median wall time of each case; the cases take turns so that load changes hit them alike."""
    sync = torch.cuda.synchronize if device.type == "cuda" else lambda: None

    def step(call: Slicer) -> float:
        sync()
        start = time.perf_counter()
        call()
        sync()
        return time.perf_counter() - start

    for _, call in cases:
        step(call)
    times: list[list[float]] = [[] for _ in cases]
    for _ in range(repeats):
        for case_times, (_, call) in zip(times, cases, strict=True):
            case_times.append(step(call))
    return [(label, statistics.median(t)) for (label, _), t in zip(cases, times, strict=True)]


def status_kib(field: str) -> int:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``) in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    raise KeyError(field)


def probe_cpu_peak(
    data: np.ndarray,
    affine: np.ndarray,
    poses: np.ndarray,
    config: SliceConfig,
    threads: int,
    conn: Connection,
) -> None:
    """In a fresh process: send the rise of peak RSS (bytes) over one call of ours."""
    torch.set_num_threads(threads)
    image = Image(torch.from_numpy(data), torch.from_numpy(affine))
    pose_tensor = torch.from_numpy(poses)
    sample_slices(image, pose_tensor[:1], config)  # thread pool and kernels, not the batch
    gc.collect()
    Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
    before = status_kib("VmRSS")
    sample_slices(image, pose_tensor, config)
    conn.send((status_kib("VmHWM") - before) * 1024)


def cpu_peak_bytes(image: Image, poses: Tensor, config: SliceConfig, threads: int) -> int:
    """Rise of peak RSS over one call of ours on the CPU, measured in a spawned process."""
    context = mp.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    args = (image.data.numpy(), image.affine.numpy(), poses.numpy(), config, threads, send)
    process = context.Process(target=probe_cpu_peak, args=args)
    process.start()
    send.close()  # so that recv() raises EOFError, not hangs, if the probe fails
    peak = receive.recv()
    process.join()
    return peak


def cuda_peak_bytes(image: Image, poses: Tensor, config: SliceConfig) -> int:
    """Peak CUDA memory allocated by one call of ours, above what was allocated before it."""
    torch.cuda.synchronize()
    before = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    sample_slices(image, poses, config)
    torch.cuda.synchronize()
    return torch.cuda.max_memory_allocated() - before


def temporaries_bytes(batch: int, config: SliceConfig, itemsize: int) -> int:
    """Largest live buffers of ours, worked out from the shapes.

    The (B, H, W) output, plus the grid (3 values a pixel) and the sampled values of one chunk of
    about 2**20 pixels: the sampler works chunk by chunk.
    """
    per_slice = config.size[0] * config.size[1]
    chunk_pixels = min(batch, max(1, 2**20 // per_slice)) * per_slice
    return (batch * per_slice + 4 * chunk_pixels) * itemsize


def time_cpu(
    volume: CanonicalVolume, poses: Tensor, threads: int, repeats: int
) -> list[tuple[str, float]]:
    """Verify the three CPU methods agree, then time them; (label, seconds) rows."""
    cpu = torch.device("cpu")
    image = volume.image
    poses_np = poses.numpy()
    data_np = image.data.numpy()
    affine_np = image.affine.numpy()
    sitk_volume = to_sitk(image)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)
    with ThreadPoolExecutor(threads) as pool:
        cases: list[tuple[str, Slicer]] = [
            ("ours", lambda: sample_slices(image, poses, THIN)),
            ("ours thick 3 mm (no peer)", lambda: sample_slices(image, poses, THICK)),
            ("SimpleITK ResampleImageFilter", lambda: sitk_slices(sitk_volume, poses_np)),
            (
                f"scipy map_coordinates ({threads} thr)",
                lambda: scipy_slices(data_np, affine_np, poses_np, pool, threads),
            ),
        ]
        reference = sample_slices(image, poses, THIN).numpy()
        for label, call in (cases[2], cases[3]):
            print("check", check_same(label, reference, np.asarray(call())))
        return median_seconds(cases, repeats, cpu)


def time_cuda(volume: CanonicalVolume, poses: Tensor, repeats: int) -> list[tuple[str, float]]:
    """Verify ours on CUDA against the CPU, then time it in float32, float16 and thick."""
    cuda = torch.device("cuda")
    image32 = volume.image.to(cuda)
    image16 = volume.image.to(cuda, torch.float16)
    on_cuda = poses.to(cuda)
    reference = sample_slices(volume.image, poses, THIN).numpy()
    print(
        "check",
        check_same("ours cuda", reference, sample_slices(image32, on_cuda, THIN).cpu().numpy()),
    )
    cases: list[tuple[str, Slicer]] = [
        ("ours", lambda: sample_slices(image32, on_cuda, THIN)),
        ("ours float16", lambda: sample_slices(image16, on_cuda, THIN)),
        ("ours thick 3 mm (no peer)", lambda: sample_slices(image32, on_cuda, THICK)),
    ]
    return median_seconds(cases, repeats, cuda)


def print_table(device: str, rows: list[tuple[str, float]], batch: int) -> None:
    ours = rows[0][1]
    for label, seconds in rows:
        print(f"{label:<32}{device:<7}{batch / seconds:>12.0f}{seconds / ours:>14.2f}")


def print_memory(volume: CanonicalVolume, poses: Tensor, threads: int, devices: list[str]) -> None:
    batch = len(poses)
    print(f"\npeak memory of one call of ours, {batch} slices, float32 (MiB):")
    print("  temporaries: output + one chunk's grid and samples, from the shapes")
    print("  cpu: rise of VmHWM over the call in a fresh process, VmHWM reset by clear_refs")
    header = f"  {'config':<12}{'temporaries':>12}{'cpu':>8}"
    print(header + (f"{'cuda max_memory_allocated':>27}" if "cuda" in devices else ""))
    for label, config in (("thin", THIN), ("thick 3 mm", THICK)):
        mib = temporaries_bytes(batch, config, 4) / 2**20
        rss = cpu_peak_bytes(volume.image, poses, config, threads) / 2**20
        line = f"  {label:<12}{mib:>12.1f}{rss:>8.1f}"
        if "cuda" in devices:
            cuda = torch.device("cuda")
            peak = cuda_peak_bytes(volume.image.to(cuda), poses.to(cuda), config) / 2**20
            line += f"{peak:>27.1f}"
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volume", type=Path, default=None, help="NIfTI volume (needs --mask)")
    parser.add_argument("--mask", type=Path, default=None, help="NIfTI brain mask of --volume")
    parser.add_argument("--batch", type=int, default=256, help="slices per call")
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per method")
    parser.add_argument("--seed", type=int, default=0, help="seed of the pose generator")
    add_device_options(parser, cuda_note=" (ours only)")
    args = parser.parse_args()
    if (args.volume is None) != (args.mask is None):
        parser.error("--volume and --mask go together")
    devices = resolve_devices(parser, args)

    volume, source = load_volume(args.volume, args.mask)
    poses = random_poses(args.batch, torch.Generator().manual_seed(args.seed))
    print(f"volume: {source}, shape {volume.image.shape}")
    print(
        f"torch {torch.__version__}, SimpleITK {sitk.Version.VersionString()}, scipy "
        f"{scipy.__version__}; {args.threads} CPU threads; {args.batch} slices of "
        f"{SIZE[0]}x{SIZE[1]} at {SPACING_MM} mm a call; median of {args.repeats}"
    )
    results = {}
    if "cpu" in devices:
        results["cpu"] = time_cpu(volume, poses, args.threads, args.repeats)
    if "cuda" in devices:
        results["cuda"] = time_cuda(volume, poses, args.repeats)
    print(f"\n{'method':<32}{'device':<7}{'slices/s':>12}{'ours x faster':>14}")
    for device, timed in results.items():
        print_table(device, timed, args.batch)
    print_memory(volume, poses, args.threads, devices)


if __name__ == "__main__":
    main()
