"""Sampling: canonical volumes, the slice sampler, poses for training and evaluation, stack simulation."""
