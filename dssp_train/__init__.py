"""DSSP training package: model, data and training for the Diffusion State Space Policy."""

__version__ = "0.1.0"
