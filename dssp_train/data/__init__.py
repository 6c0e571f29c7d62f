"""Training-only data: the synthetic tap-count task (the dataset format itself lives in :mod:`dssp_data`)."""
