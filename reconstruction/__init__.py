"""Slice-to-volume reconstruction: stacks to slices, pose initialisation, SVR, super-resolution."""
