"""The robot side: cameras and point clouds, AgileX Piper arms on CAN, the safety layer, ``dssp-run``,
and recording teleoperated demonstrations (``dssp-record``: ``leader``, ``bus_monitor``, ``recorder``,
``record_session``) and replaying them (``episode_replay``, ``dssp-replay``). The robot's clock is ``clock``.

Depends on ``dssp_deploy``, ``dssp_data``, numpy, python-can and pyrealsense2 — never on torch, ``dssp_train``,
``export`` or ``dssp_sim`` (import-linter contracts in pyproject.toml).
"""
