"""``dssp_model.json``: what a model directory holds and how to run it, readable without torch.

The manifest names every graph input and output with its shape (symbolic dims as strings: "B" batch,
"P" points) and dtype, and records what the runtime needs besides the graphs: the normaliser statistics
(already applied inside the graphs; kept for reports and sanity checks), N, H, H_a, K and the DDIM
timesteps, the control rate of the training data, where the weights came from (the run's name — not its
path on the training machine —, the weights file, its sha256, the step, EMA or raw) and the versions of
everything that produced the files. The key facts are also written into each ONNX file's
``metadata_props`` (:func:`metadata_props`), so a lone ``.onnx`` file still says what it is.

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

from dssp_train.config import RunConfig
from dssp_core.files import atomic_write_text

from dssp_deploy.manifest import FORMAT_VERSION, GRAPHS, KIND, MANIFEST_NAME, graph_io, history_state_specs


def build_manifest(
    config: RunConfig,
    *,
    denoise_steps: int,
    ddim_timesteps: list[int],
    normalizers: dict[str, dict[str, list[float]]],
    files: dict[str, dict[str, str]],
    source: dict[str, Any],
    exporter: dict[str, Any],
    versions: dict[str, str],
    inpainting: bool = False,
) -> dict[str, Any]:
    """The manifest as a JSON-ready dict.

    Args:
        files: per graph, the file of each format, e.g. ``{"history_step": {"onnx": "history_step.onnx"}}``.
        source: the checkpoint: run name (the run directory's name, no path), weights file, EMA or raw, sha256,
            training step.
        exporter: exporter name and version, ONNX opset, ONNX exporter used.
        versions: library versions (dssp, torch, onnx, onnxruntime, python).
        inpainting: the denoiser takes the committed actions and their weights (``--inpainting``).
    """
    m = config.model
    graphs = {}
    for name in GRAPHS:
        inputs, outputs = graph_io(m, name, inpainting)
        graphs[name] = {"files": files.get(name, {}), "inputs": inputs, "outputs": outputs}
    return {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "preset": config.preset,
        "model_config": dataclasses.asdict(m),
        "graphs": graphs,
        "point_dim": m.point_dim,
        "state_dim": m.state_dim,
        "action_dim": m.action_dim,
        "d_model": m.d_model,
        "n_obs_steps": m.n_obs_steps,
        "horizon": m.horizon,
        "n_action_steps": m.n_action_steps,
        "action_offset": m.action_offset,
        "denoise_steps": denoise_steps,
        "ddim_timesteps": list(ddim_timesteps),
        "use_history": m.use_history,
        "use_recent_states": m.use_recent_states,
        "history_state": [s["name"] for s in history_state_specs(m)] if m.use_history else [],
        "control_rate_hz": config.control_rate_hz,
        "inpainting": inpainting,
        "observation": config.observation.to_manifest(),
        "normalizers": normalizers,
        "runtime": {
            "units": "point_cloud, agent_pos and action are raw (unnormalised); the graphs normalise inside",
            "point_cloud": f"the first {m.point_dim} channels of each point (xyz{' + rgb' if m.point_dim == 6 else ''})",
            "history_state": "all zeros at the start of an episode; feed each *_out back as the next tick's input",
            "z_recent": "the last N z_t outputs, oldest first; at the start of an episode the first z_t repeats",
            "noise": "standard normal (B, H, A)",
            **({"committed": "the actions already committed (B, H, A), raw units, and committed_weight (B, H, 1) in "
                             "[0, 1]: every DDIM step's clean prediction is pulled to them (all zero: the plain chain)"}
               if inpainting else {}),
            "act_every": f"one denoiser call every H_a = {m.n_action_steps} history steps; execute the H_a actions from "
                         f"index action_offset = {m.action_offset}",
            "tick_rate_hz": config.control_rate_hz,
        },
        "source": source,
        "exporter": exporter,
        "versions": versions,
        "files": {},  # file name → bytes, sha256 (and node count for ONNX), filled in by the exporter
        "verification": None,  # the parity report, filled in by the exporter unless --skip-verify
    }


def metadata_props(manifest: dict[str, Any], graph: str) -> dict[str, str]:
    """The key facts for one ONNX file's ``metadata_props`` (string values; structured ones as JSON)."""
    facts = {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "graph": graph,
        "model_config": json.dumps(manifest["model_config"], sort_keys=True),
        "inputs": json.dumps(manifest["graphs"][graph]["inputs"]),
        "outputs": json.dumps(manifest["graphs"][graph]["outputs"]),
        "n_obs_steps": str(manifest["n_obs_steps"]),
        "horizon": str(manifest["horizon"]),
        "n_action_steps": str(manifest["n_action_steps"]),
        "denoise_steps": str(manifest["denoise_steps"]),
        "ddim_timesteps": json.dumps(manifest["ddim_timesteps"]),
        "control_rate_hz": json.dumps(manifest["control_rate_hz"]),
        "source_sha256": manifest["source"]["sha256"],
        "exporter": json.dumps(manifest["exporter"], sort_keys=True),
        "versions": json.dumps(manifest["versions"], sort_keys=True),
    }
    return facts


def write_manifest(model_dir: Path, manifest: dict[str, Any]) -> Path:
    """Write ``MODEL_DIR/dssp_model.json`` (temporary name, then rename)."""
    path = Path(model_dir) / MANIFEST_NAME
    atomic_write_text(path, json.dumps(manifest, indent=2) + "\n")
    return path
