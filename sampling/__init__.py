"""Sampling: canonical volumes, slices, poses, training data and stack simulation."""
