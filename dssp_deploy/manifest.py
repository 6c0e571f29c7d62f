"""Reading ``dssp_model.json`` — what a model directory holds and how to run it — without torch.

``export.to_onnx`` writes the manifest (``export/manifest.py``) with the names and constants defined
here; this module reads it and checks every graph against it (input/output names, shapes, dtypes).

Shapes of the graph interface (E = expand * d_model, n = d_state, W = d_conv):
    history_step: point_cloud (B, P, point_dim), agent_pos (B, S), conv_state_i (B, E, W), ssm_state_i (B, E, n)
                  → z_t (B, d), c_t (B, d), conv_state_i_out (B, E, W), ssm_state_i_out (B, E, n)
    denoiser:     c_t (B, d), z_recent (B, N, d), noise (B, H, A) → action (B, H, A)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dssp_train.errors import DSSPError

FORMAT_VERSION = "1"
KIND = "dssp-model"
MANIFEST_NAME = "dssp_model.json"
HISTORY_GRAPH = "history_step"
DENOISER_GRAPH = "denoiser"
GRAPHS = (HISTORY_GRAPH, DENOISER_GRAPH)
ONNX_TYPES = {"float32": "tensor(float)", "int64": "tensor(int64)"}


class ModelDirError(DSSPError):
    """A model directory is missing, incomplete, or does not match its manifest."""


def read_manifest(model_dir: Path) -> dict[str, Any]:
    """The manifest of a model directory, or a :class:`ModelDirError` that says what is wrong."""
    model_dir = Path(model_dir)
    path = model_dir / MANIFEST_NAME
    if not model_dir.is_dir():
        raise ModelDirError(f"model directory {model_dir} does not exist; create one with python -m export.to_onnx RUN_DIR -o {model_dir}")
    if not path.is_file():
        raise ModelDirError(f"{path} is missing: {model_dir} is not a DSSP model directory (python -m export.to_onnx makes one)")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelDirError(f"{path} is unreadable ({exc}); export the model again") from None
    if not isinstance(manifest, dict) or manifest.get("kind") != KIND:
        raise ModelDirError(f"{path} is not a DSSP model manifest (no \"kind\": \"{KIND}\"); export the model again")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ModelDirError(
            f"{path} has format version {manifest.get('format_version')!r}, this runtime reads {FORMAT_VERSION!r}; "
            "export the model again with this version of dssp"
        )
    return manifest


def is_model_dir(path: Path) -> bool:
    """True when ``path`` holds a previous export of any format version (a manifest of this kind)."""
    try:
        manifest = json.loads((Path(path) / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and manifest.get("kind") == KIND


PRECISIONS = {"fp32": "onnx", "int8": "onnx_int8"}  # the runtime's precision → the manifest's file kind


def graph_file(model_dir: Path, manifest: dict[str, Any], graph: str, fmt: str = "onnx") -> Path:
    """Path of one graph's file in a model directory; a clear error when it is not there."""
    name = manifest["graphs"][graph]["files"].get(fmt)
    if name is None:
        how = "--quantize int8" if fmt == "onnx_int8" else f"--format {fmt} (or both)"
        raise ModelDirError(f"{model_dir} has no {fmt} file for {graph}; export it with {how}")
    path = Path(model_dir) / name
    if not path.is_file():
        raise ModelDirError(f"{path} is listed in {MANIFEST_NAME} but missing; export the model again")
    return path


def check_session(session, manifest: dict[str, Any], graph: str, where: Path) -> None:
    """The session's inputs and outputs must be the manifest's, in name, rank, fixed dims and dtype."""
    spec = manifest["graphs"][graph]
    for kind, declared, actual in (
        ("input", spec["inputs"], session.get_inputs()),
        ("output", spec["outputs"], session.get_outputs()),
    ):
        want = [d["name"] for d in declared]
        have = [a.name for a in actual]
        if want != have:
            raise ModelDirError(f"{where}: {kind}s are {have}, {MANIFEST_NAME} says {want}; export the model again")
        for d, a in zip(declared, actual):
            fixed = [s for s in d["shape"] if isinstance(s, int)]
            got = [s for s, w in zip(a.shape, d["shape"]) if isinstance(w, int)]
            if len(a.shape) != len(d["shape"]) or fixed != got or ONNX_TYPES.get(d["dtype"]) != a.type:
                raise ModelDirError(
                    f"{where}: {kind} {a.name} is {a.type} {list(a.shape)}, {MANIFEST_NAME} says "
                    f"{d['dtype']} {d['shape']}; export the model again"
                )
