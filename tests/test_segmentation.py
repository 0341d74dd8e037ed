"""The brain-mask U-Net: shapes, input checks, size, and that it can fit a mask."""

from __future__ import annotations

import pytest
import torch

from svr.models.pretrained import MAX_MODEL_BYTES
from svr.models.segmentation import BrainUNet, SegmentationConfig, parameter_bytes


def test_output_has_the_input_shape():
    model = BrainUNet(SegmentationConfig(width=4, depth=3)).eval()
    with torch.no_grad():
        out = model(torch.randn(3, 1, 32, 40))
    assert out.shape == (3, 1, 32, 40) and bool(out.isfinite().all())


@pytest.mark.parametrize("shape", [(1, 2, 32, 32), (1, 1, 30, 32), (32, 32)])
def test_bad_input_shapes_are_named(shape):
    with pytest.raises(ValueError, match=r"BrainUNet: input must be \(B, 1, H, W\)"):
        BrainUNet(SegmentationConfig(width=4, depth=2))(torch.randn(*shape))


def test_a_multi_channel_unet_takes_its_channels_only():
    model = BrainUNet(SegmentationConfig(width=4, depth=2, in_channels=3)).eval()
    with torch.no_grad():
        out = model(torch.randn(2, 3, 16, 20))
    assert out.shape == (2, 1, 16, 20)
    with pytest.raises(ValueError, match=r"input must be \(B, 3, H, W\)"):
        model(torch.randn(2, 1, 16, 20))


@pytest.mark.parametrize(
    ("field", "value"),
    [("width", 0), ("depth", 0), ("depth", True), ("in_channels", 0), ("in_channels", 1.0)],
)
def test_config_errors(field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        SegmentationConfig(**{field: value})


def test_default_model_fits_the_shipping_limit():
    model = BrainUNet()
    size = parameter_bytes(model)
    count = sum(p.numel() for p in model.parameters()) + sum(
        b.numel() for b in model.buffers() if b.is_floating_point()
    )
    assert size == 2 * count
    assert size < MAX_MODEL_BYTES


def test_a_tiny_unet_learns_a_disc_mask():
    torch.manual_seed(0)
    y, x = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    centres = torch.rand(16, 2) * 12 + 10
    masks = ((y - centres[:, :1, None]) ** 2 + (x - centres[:, 1:, None]) ** 2 < 36).float()
    images = (masks * 0.8 + 0.1 * torch.randn(16, 32, 32))[:, None]
    model = BrainUNet(SegmentationConfig(width=4, depth=2))
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(60):
        optimiser.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(model(images), masks[:, None])
        loss.backward()
        optimiser.step()
    model.eval()
    with torch.no_grad():
        predicted = model(images)[:, 0] > 0
    dice = 2 * (predicted & (masks > 0)).sum() / (predicted.sum() + masks.sum())
    assert float(dice) > 0.8
