""":mod:`svr.models.resume`, the one checkpoint-and-resume mechanism of every training loop: the
states a loop has are saved and restored, a missing one is a named error, and the optional
generator and loss-scaler states are left out where a loop has none."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from svr.errors import CheckpointError
from svr.models.checkpoint import load_checkpoint
from svr.models.resume import (
    cosine_schedule,
    restart_as_new_run,
    resume_training,
    save_training_checkpoint,
)

Run = tuple[nn.Module, torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]


def _run(seed: int = 0) -> Run:
    torch.manual_seed(seed)
    net = nn.Linear(3, 2)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-2)
    return net, optimiser, cosine_schedule(optimiser, 10)


def _steps(net, optimiser, schedule, generator, count: int) -> None:
    for _ in range(count):
        x = torch.randn(4, 3, generator=generator)
        loss = net(x).square().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()


def test_a_resumed_run_continues_as_if_it_had_not_stopped(tmp_path):
    straight = _run()
    _steps(*straight, torch.Generator().manual_seed(1), 5)
    first = _run()
    generator = torch.Generator().manual_seed(1)
    _steps(*first, generator, 3)
    save_training_checkpoint(tmp_path, 3, *first, generator, {"architecture": "test"})
    resumed, generator = _run(seed=5), torch.Generator().manual_seed(7)
    assert resume_training(tmp_path, *resumed, generator) == 3
    _steps(*resumed, generator, 2)
    for a, b in zip(straight[0].parameters(), resumed[0].parameters(), strict=True):
        assert torch.equal(a, b)
    assert resumed[2].get_last_lr() == straight[2].get_last_lr()


def test_the_states_a_loop_has_are_saved_and_those_it_lacks_are_named(tmp_path):
    net, optimiser, schedule = _run()
    scaler = torch.amp.GradScaler("cuda", enabled=False)
    path = save_training_checkpoint(tmp_path, 1, net, optimiser, schedule, None, {}, scaler=scaler)
    state = load_checkpoint(path, with_training_state=True).training_state
    assert sorted(state) == ["optimizer", "scaler", "scheduler", "step"]  # the slice-pose layout
    assert resume_training(tmp_path, *_run(), None, scaler=scaler) == 1
    with pytest.raises(CheckpointError, match="no 'generator' state"):
        resume_training(tmp_path, *_run(), torch.Generator())
    assert resume_training(None, *_run(), None) == 0
    assert resume_training(tmp_path / "new", *_run(), None) == 0
    assert (tmp_path / "new").is_dir()
    (tmp_path / "file").write_text("not a run folder")
    with pytest.raises(CheckpointError, match="not a folder of checkpoints"):
        resume_training(tmp_path / "file", *_run(), None)


def test_only_the_newest_checkpoints_are_kept_and_a_step_is_replaced(tmp_path):
    net, optimiser, schedule = _run()
    for step in (1, 2, 3, 3):
        save_training_checkpoint(tmp_path, step, net, optimiser, schedule, None, {}, keep=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_000000002", "step_000000003"]


def test_a_restart_as_a_new_run_resets_the_moments_and_sets_the_rate():
    net, optimiser, _ = _run()
    schedule = cosine_schedule(optimiser, 10, restart_at=4)
    _steps(net, optimiser, schedule, torch.Generator().manual_seed(0), 4)
    assert optimiser.state
    restart_as_new_run(optimiser, schedule, 3e-4)
    assert not optimiser.state
    assert optimiser.param_groups[0]["lr"] == pytest.approx(3e-4)
    assert schedule.base_lrs == [3e-4]
