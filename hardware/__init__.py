"""The robot side: cameras and point clouds, AgileX Piper arms on CAN, the safety layer, ``dssp-run``,
and recording teleoperated demonstrations (``dssp-record``: ``leader``, ``bus_monitor``, ``recorder``,
``record_session``) and replaying them (``replay``).

Depends on numpy, onnxruntime (through ``dssp_deploy``), python-can and pyrealsense2 — never on torch;
recording also needs zarr and numcodecs (the dataset writer).
"""
