"""Slice-pose CNNs: backbones, pose heads, training, prediction and evaluation."""
