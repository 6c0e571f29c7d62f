"""``dssp_model.json``: what a model directory holds and how to run it, readable without torch.

The manifest names every graph input and output with its shape (symbolic dims as strings: "B" batch,
"P" points) and dtype, and records what the runtime needs besides the graphs: the normaliser statistics
(already applied inside the graphs; kept for reports and sanity checks), the model's contract once
(``contract``: :class:`~dssp_data.model_contract.ModelContract` — N, H, H_a, K and the DDIM timesteps, the
control rate of the training data, the observation contract), the architecture (``model_config``: the training
ModelConfig without the contract's fields), where the weights came from (the run's name — not its path on the
training machine —, the weights file, its sha256, the step, EMA or raw) and the versions of everything that
produced the files. Each ONNX file's ``metadata_props`` (:func:`metadata_props`) says what it is and carries the
contract's sha256.

Shapes of the graph interface (E = expand * d_model, n = d_state, W = d_conv):
    history_step: point_cloud (B, P, point_dim), agent_pos (B, S), conv_state_i (B, E, W), ssm_state_i (B, E, n)
                  → z_t (B, d), c_t (B, d), conv_state_i_out (B, E, W), ssm_state_i_out (B, E, n)
    denoiser:     c_t (B, d), z_recent (B, N, d), noise (B, H, A) → action (B, H, A)
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from dssp_core.files import atomic_write_text
from dssp_data.model_contract import CONTRACT_FIELDS, ModelContract
from dssp_deploy.manifest import FORMAT_VERSION, GRAPHS, KIND, MANIFEST_NAME, graph_io
from dssp_train.config import ModelConfig, RunConfig


def architecture(model: ModelConfig) -> dict[str, Any]:
    """The training ModelConfig as ``model_config`` records it: everything but what the contract holds."""
    return {k: v for k, v in dataclasses.asdict(model).items() if k not in CONTRACT_FIELDS}


def build_manifest(
    config: RunConfig,
    contract: ModelContract,
    *,
    normalizers: dict[str, dict[str, list[float]]],
    files: dict[str, dict[str, str]],
    source: dict[str, Any],
    exporter: dict[str, Any],
    versions: dict[str, str],
) -> dict[str, Any]:
    """The manifest as a JSON-ready dict: each fact once.

    Args:
        contract: what the model promises the robot (``config.contract(...)`` with the sampler export chose).
        files: per graph, the file of each format, e.g. ``{"history_step": {"onnx": "history_step.onnx"}}``.
        source: the checkpoint: run name (the run directory's name, no path), weights file, EMA or raw, sha256,
            training step.
        exporter: exporter name and version, ONNX opset, ONNX exporter used.
        versions: library versions (dssp, torch, onnx, onnxruntime, python).
    """
    m = config.model
    graphs = {}
    for name in GRAPHS:
        inputs, outputs = graph_io(contract, m, name)
        graphs[name] = {"files": files.get(name, {}), "inputs": inputs, "outputs": outputs}
    return {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "preset": config.preset,
        "contract": contract.to_json(),
        "model_config": architecture(m),
        "graphs": graphs,
        "normalizers": normalizers,
        "runtime": {
            "units": "point_cloud, agent_pos and action are raw (unnormalised); the graphs normalise inside",
            "point_cloud": "the first contract.point_dim channels of each point (xyz, then rgb when it is 6)",
            "history_state": "all zeros at the start of an episode; feed each *_out back as the next tick's input",
            "z_recent": "the last N z_t outputs, oldest first; at the start of an episode the first z_t repeats",
            "noise": "standard normal (B, H, A)",
            **(
                {
                    "committed": "the actions already committed (B, H, A), raw units, and committed_weight (B, H, 1) in "
                    "[0, 1]: every DDIM step's clean prediction is pulled to them (all zero: the plain chain)"
                }
                if contract.inpainting
                else {}
            ),
            "act_every": "one denoiser call every H_a history steps; execute the H_a actions from index "
            "contract.action_offset, at contract.control_rate_hz",
        },
        "source": source,
        "exporter": exporter,
        "versions": versions,
        "files": {},  # file name → bytes, sha256 (and node count for ONNX), filled in by the exporter
        "verification": None,  # the parity report, filled in by the exporter unless --skip-verify
    }


def metadata_props(manifest: dict[str, Any], graph: str) -> dict[str, str]:
    """One ONNX file's ``metadata_props`` (string values): what it is, its interface and the sha256 of the
    contract of the manifest it belongs to (the facts themselves are in the manifest, once)."""
    return {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "graph": graph,
        "inputs": json.dumps(manifest["graphs"][graph]["inputs"]),
        "outputs": json.dumps(manifest["graphs"][graph]["outputs"]),
        "contract_sha256": ModelContract.from_json(manifest["contract"]).digest(),
        "source_sha256": manifest["source"]["sha256"],
        "exporter": json.dumps(manifest["exporter"], sort_keys=True),
        "versions": json.dumps(manifest["versions"], sort_keys=True),
    }


def write_manifest(model_dir: Path, manifest: dict[str, Any]) -> Path:
    """Write ``MODEL_DIR/dssp_model.json`` (temporary name, then rename)."""
    path = Path(model_dir) / MANIFEST_NAME
    atomic_write_text(path, json.dumps(manifest, indent=2) + "\n")
    return path
