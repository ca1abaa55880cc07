"""scanreg's Hydra configs (package data): found as ``pkg://scanreg.conf``."""
