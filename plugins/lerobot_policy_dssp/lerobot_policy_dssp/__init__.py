"""DSSP as a LeRobot policy (``lerobot-train --policy.type=dssp``).

LeRobot's ``register_third_party_plugins()`` imports every installed distribution named ``lerobot_policy_*``;
importing this package registers the policy type ``dssp`` (:mod:`.configuration_dssp`). LeRobot finds the
policy class in :mod:`.modeling_dssp` and the processors in :mod:`.processor_dssp` by its naming convention;
importing the package registers the depth-to-cloud processor step too, so a saved preprocessor that holds it
reloads.
"""

from lerobot_policy_dssp import processor_dssp  # noqa: F401  (registers the step dssp_depth_to_cloud)
from lerobot_policy_dssp.configuration_dssp import DSSPConfig

__all__ = ["DSSPConfig"]
