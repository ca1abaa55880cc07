"""Data providers (``data=NAME``): what a run registers. Each returns a :class:`~scanreg.types.Problem`: the
source, the target, and what is known about them (ground truth, landmarks, labelled parts)."""

from scanreg.stages.data import datasets, dental, files, scanset, synthetic, views  # noqa: F401  (registers the providers)
