"""Test-wide settings: one intra-op thread, so results do not depend on the machine's core count
and small tensor ops do not stall when another process shares the cores."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

try:
    import torch
except ImportError:  # a deploy-only environment
    torch = None

if torch is not None:
    torch.set_num_threads(1)
