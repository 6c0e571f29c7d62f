"""The robot side: cameras and point clouds, AgileX Piper arms on CAN, the safety layer, ``dssp-run``.

Depends on numpy, onnxruntime (through ``dssp_deploy``), python-can and pyrealsense2 — never on torch.
"""
