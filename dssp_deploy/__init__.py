"""DSSP runtime for the robot: ONNX Runtime and numpy only (importing it never imports torch)."""

from dssp_deploy.onnx_policy import OnnxPolicy

__all__ = ["OnnxPolicy"]
