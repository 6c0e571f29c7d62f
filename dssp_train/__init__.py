"""DSSP training package: model, data and training for the Diffusion State Space Policy."""

import os

# Back large CPU tensors with transparent huge pages (PyTorch reads this at its first large
# allocation). Trajectory-wise training allocates (T, d_inner, d_state) scan tensors of ~150 MB
# per layer; page-faulting them in 4 KiB pages cost more than the arithmetic (2x slower
# forward+backward measured on a 2-core VM). Set THP_MEM_ALLOC_ENABLE=0 to opt out.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

__version__ = "0.1.0"
