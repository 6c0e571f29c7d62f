"""``dssp-run --policy hold``: the arm held where it starts — the worked example of a policy source.

A first check of a rig before any model runs: the camera, the point-cloud pipeline, the extrinsics, the CAN
bus, the safety layer, the log and the Rerun views all run as they will with a model, every tick, and the
command is the position the arm was measured at when the loop started. The cloud is built (and the camera
gates the tick) so that its latency, an empty crop box or a stale camera show in the log as they would with
a model.
"""

from __future__ import annotations

import numpy as np

from dssp_core.errors import ConfigError
from hardware.policies import Act, PolicySource


class Hold(PolicySource):
    name = "hold"
    needs_cloud = True

    @classmethod
    def from_spec(cls, arg: str | None) -> Hold:
        if arg:
            raise ConfigError(f"--policy hold:{arg}: hold takes no argument")
        return cls()

    def reset(self, state: np.ndarray) -> None:
        self.target = np.array(state, dtype=np.float64)

    def act(self, cloud, state) -> Act:
        return Act(self.target.copy())
