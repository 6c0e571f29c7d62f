"""LeRobot v3 datasets <-> DP3 zarr datasets, read and written with pyarrow and JSON (no lerobot, no torch).

    dssp-data convert LEROBOT_ROOT --out OUT.zarr --extrinsics calib.json [--pointcloud FILE] [--depth-key K]
                      [--state-key observation.state] [--action-key action]
    dssp-data export PATH --to lerobot --out DIR [--repo-id local/NAME] [--force]

``layout.py``: what both directions share (the v3 layout, ``meta/info.json``, the files of a root, columns between
numpy and arrow); ``read.py``: :func:`convert` (a LeRobot dataset -> a zarr dataset); ``write.py``: :func:`export`
(a zarr dataset -> a LeRobot dataset).
"""

from dssp_data.lerobot.layout import CODEBASE_VERSION, is_lerobot_root
from dssp_data.lerobot.read import convert
from dssp_data.lerobot.write import LEROBOT_DATASET, export

__all__ = ["is_lerobot_root", "convert", "export", "LEROBOT_DATASET", "CODEBASE_VERSION"]
