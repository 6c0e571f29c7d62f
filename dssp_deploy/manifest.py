"""Reading ``dssp_model.json`` — what a model directory holds and how to run it — without torch.

``export.to_onnx`` writes the manifest (``export/manifest_writer.py``) with the names, constants and graph
interface defined here; this module reads it and trusts nothing in it unchecked. :func:`read_manifest`
(the one reader: the runtime, ``dssp-run``, ``dssp-profile``, the simulation and ``export.verify`` all
use it) returns a typed :class:`Manifest` or refuses, with one :class:`ModelDirError` line naming the field, its value and what to do:
- a fact of the wrong type or out of range, or facts that contradict each other: the model's contract
  (``contract``: :class:`~dssp_data.model_contract.ModelContract`, which validates itself once: 1 <= H_a <= H,
  the DDIM timesteps strictly decreasing, the observation contract against the dimensions), the architecture
  (``model_config``: :class:`ModelFacts`), the source (:class:`SourceFacts`), the timesteps against the trained
  ones;
- graph inputs/outputs other than the interface the facts give (:func:`graph_io`), normalisers of the wrong
  size;
- a file name that does not stay inside the model directory (absolute, ``..``, or a symbolic link out),
  or a graph file without a size and sha256 in ``files``.
The runtime then checks each graph file it opens against that size and sha256 (:func:`read_graph`: a
file from another export is refused), every file of external data an ONNX graph names the same way
(:func:`read_graph_files`: inside the model directory, listed with its own size and sha256), and each
ONNX session against the declared interface (:func:`check_session`).

Shapes of the graph interface (E = expand * d_model, n = d_state, W = d_conv):
    history_step: point_cloud (B, P, point_dim), agent_pos (B, S), conv_state_i (B, E, W), ssm_state_i (B, E, n)
                  → z_t (B, d), c_t (B, d), conv_state_i_out (B, E, W), ssm_state_i_out (B, E, n)
    denoiser:     c_t (B, d), z_recent (B, N, d), noise (B, H, A) → action (B, H, A)
"""

from __future__ import annotations

import contextlib
import hashlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, ClassVar

import numpy as np

from dssp_core.errors import ConfigError, DSSPError
from dssp_core.files import read_input_bytes, read_regular_text
from dssp_core.schema import (
    MAX_LAYERS,
    MAX_STEPS,
    MAX_WIDTH,
    Settings,
    Spec,
    check_value,
    parse_json,
    read_json,
    setting,
)
from dssp_data.model_contract import ModelContract
from dssp_deploy.external_data import MalformedGraph, external_locations

FORMAT_VERSION = "2"
KIND = "dssp-model"
MANIFEST_NAME = "dssp_model.json"
HISTORY_GRAPH = "history_step"
DENOISER_GRAPH = "denoiser"
GRAPHS = (HISTORY_GRAPH, DENOISER_GRAPH)
ONNX_TYPES = {"float32": "tensor(float)", "int64": "tensor(int64)"}
PRECISIONS = {
    "fp32": "onnx",
    "int8": "onnx_int8",
    "int4": "onnx_int4",
}  # the runtime's precision → the manifest's file kind
FUSED = "_fused"  # file kind suffix of the graphs with the fused Mamba operators (dssp_deploy.mamba_kernel)


def file_kind(precision: str, fused: bool = False) -> str:
    """The manifest's file kind of one precision's graphs: ``onnx``, ``onnx_int8_fused``, ..."""
    return PRECISIONS[precision] + (FUSED if fused else "")


def file_suffix(kind: str) -> str:
    """The file name suffix of a file kind: ``onnx`` → ``.onnx``, ``onnx_int8_fused`` → ``.int8.fused.onnx``."""
    if kind == "torchscript":
        return ".pt"
    parts = kind.split("_")[1:]
    return "".join(f".{p}" for p in parts) + ".onnx"


NORMALIZER_STATS = ("scale", "offset", "input_min", "input_max")
AGAIN = "export the model again (python -m export.to_onnx RUN_DIR -o MODEL_DIR)"
_SHA256 = re.compile(r"[0-9a-f]{64}")


class ModelDirError(DSSPError):
    """A model directory is missing, incomplete, or does not match its manifest."""


# ------------------------------------------------------------------------------- the schema
def _width(default: int):
    return setting(default, ge=1, le=MAX_WIDTH)


@dataclass(frozen=True)
class ModelFacts(Settings):
    """The architecture the runtime and ``dssp-profile`` use, from ``model_config`` (the rest of it is left to
    training; what the model promises the robot is its :class:`~dssp_data.model_contract.ModelContract`)."""

    SECTION: ClassVar[str] = f"{MANIFEST_NAME} model_config"

    d_model: int = _width(64)
    d_state: int = _width(16)
    d_conv: int = setting(4, ge=1, le=64)
    expand: int = setting(2, ge=1, le=16)
    n_history_layers: int = setting(2, ge=1, le=MAX_LAYERS)
    n_denoiser_layers: int = setting(4, ge=1, le=MAX_LAYERS)
    point_widths: list[int] = setting(
        default_factory=lambda: [32, 64, 128], ge=1, le=MAX_WIDTH, min_length=1, max_length=16
    )
    point_feature_dim: int = _width(64)
    state_widths: list[int] = setting(default_factory=lambda: [32, 32], ge=1, le=MAX_WIDTH, min_length=1, max_length=16)
    use_history: bool = setting(True)
    use_recent_states: bool = setting(True)
    timestep_decoupled: bool = setting(True)
    history_window: int = setting(0, ge=0, le=MAX_STEPS)  # 0: the full history

    def validate(self) -> None:
        if not (self.use_history or self.use_recent_states):
            raise ConfigError(
                f"{self.SECTION}.use_history and use_recent_states are both false: the denoiser would see "
                "no observation"
            )


@dataclass(frozen=True)
class SourceFacts(Settings):
    """Where the model came from: the run's name (not its path), the weights file in it, their sha256, step."""

    SECTION: ClassVar[str] = f"{MANIFEST_NAME} source"
    OPTIONAL: ClassVar[tuple[str, ...]] = ("run",)  # older exports recorded a path instead (ignored)

    weights: str = setting("model.safetensors")
    sha256: str = setting("0" * 64)
    ema: bool = setting(True)
    step: int | None = setting(None, ge=0, le=2**63 - 1)  # the training step of the weights
    run: str | None = setting(None)  # the training run's folder name

    def validate(self) -> None:
        s = self.SECTION
        if not _SHA256.fullmatch(self.sha256):
            raise ConfigError(f"{s}.sha256 must be 64 lowercase hex digits, got {self.sha256!r}")
        if not _is_inside_name(self.weights):
            raise ConfigError(f"{s}.weights must be a file name inside the run directory, got {self.weights!r}")
        if self.run is not None and (not self.run or "/" in self.run or "\\" in self.run or self.run in (".", "..")):
            raise ConfigError(f"{s}.run must be the run directory's name (no path), got {self.run!r}")


def facts_from(cls, values: Any):
    """``cls`` from the keys of ``values`` it knows (others are left alone); a missing key is a ConfigError."""
    if not isinstance(values, Mapping):
        raise ConfigError(f"{cls.SECTION} must be a JSON object, got {type(values).__name__}")
    missing = [name for name in cls.field_names() if name not in values and name not in getattr(cls, "OPTIONAL", ())]
    if missing:
        raise ConfigError(
            f"{', '.join(f'{cls.SECTION}.{name}' for name in missing)} {'is' if len(missing) == 1 else 'are'} missing"
        )
    return cls.from_dict({k: values[k] for k in cls.field_names() if k in values})


# ---------------------------------------------------------------------- the graph interface
def tensor_spec(name: str, shape: list[int | str], dtype: str = "float32") -> dict[str, Any]:
    return {"name": name, "shape": list(shape), "dtype": dtype}


def history_state_specs(m, suffix: str = "") -> list[dict[str, Any]]:
    """conv_state_i (B, E, W) and ssm_state_i (B, E, n) for every history layer, in graph order; with a window of
    T_h steps (``history_window``), the window z_window (B, T_h, d) and the count of observations seen z_seen (B, 1).

    ``m``: anything with the model's attributes (``dssp_train.config.ModelConfig``, :class:`ModelFacts`)."""
    if getattr(m, "history_window", 0):
        return [
            tensor_spec(f"z_window{suffix}", ["B", m.history_window, m.d_model]),
            tensor_spec(f"z_seen{suffix}", ["B", 1]),
        ]
    inner = m.expand * m.d_model
    specs = []
    for i in range(m.n_history_layers):
        specs.append(tensor_spec(f"conv_state_{i}{suffix}", ["B", inner, m.d_conv]))
        specs.append(tensor_spec(f"ssm_state_{i}{suffix}", ["B", inner, m.d_state]))
    return specs


def history_io(c: ModelContract, m) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Inputs and outputs of the history-step graph (no state and z_t only without a history encoder); ``c`` the
    contract, ``m`` the architecture (``dssp_train.config.ModelConfig``, :class:`ModelFacts`)."""
    inputs = [tensor_spec("point_cloud", ["B", "P", c.point_dim]), tensor_spec("agent_pos", ["B", c.state_dim])]
    outputs = [tensor_spec("z_t", ["B", m.d_model])]
    if m.use_history:
        inputs += history_state_specs(m)
        outputs += [tensor_spec("c_t", ["B", m.d_model])] + history_state_specs(m, "_out")
    return inputs, outputs


def no_inpainting(c: ModelContract, batch: int) -> dict[str, np.ndarray]:
    """The denoiser's extra inputs when exported with ``--inpainting`` — the committed actions (B, H, A) raw units and
    their weights (B, H, 1) in [0, 1] — committing nothing (all zero: the plain chain); {} for a plain denoiser."""
    if not c.inpainting:
        return {}
    h, a = c.horizon, c.action_dim
    return {"committed": np.zeros((batch, h, a), np.float32), "committed_weight": np.zeros((batch, h, 1), np.float32)}


def denoiser_io(c: ModelContract, m) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Inputs and outputs of the denoiser graph (with those of :func:`no_inpainting` when ``c.inpainting``)."""
    inputs = []
    if m.use_history:
        inputs.append(tensor_spec("c_t", ["B", m.d_model]))
    if m.use_recent_states:
        inputs.append(tensor_spec("z_recent", ["B", c.n_obs_steps, m.d_model]))
    inputs.append(tensor_spec("noise", ["B", c.horizon, c.action_dim]))
    if c.inpainting:
        inputs.append(tensor_spec("committed", ["B", c.horizon, c.action_dim]))
        inputs.append(tensor_spec("committed_weight", ["B", c.horizon, 1]))
    return inputs, [tensor_spec("action", ["B", c.horizon, c.action_dim])]


def graph_io(c: ModelContract, m, graph: str) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    return history_io(c, m) if graph == HISTORY_GRAPH else denoiser_io(c, m)


def _depends(name: str) -> tuple[str, ...]:
    """The facts a tensor's shape comes from (for messages)."""
    base = name.removesuffix("_out")
    if base.startswith("conv_state_"):
        return ("expand", "d_model", "d_conv")
    if base.startswith("ssm_state_"):
        return ("expand", "d_model", "d_state")
    if base == "z_window":
        return ("history_window", "d_model")
    return {
        "point_cloud": ("point_dim",),
        "agent_pos": ("state_dim",),
        "z_t": ("d_model",),
        "c_t": ("d_model",),
        "z_recent": ("n_obs_steps", "d_model"),
        "noise": ("horizon", "action_dim"),
        "action": ("horizon", "action_dim"),
        "committed": ("horizon", "action_dim"),
        "committed_weight": ("horizon",),
    }.get(base, ())


# ------------------------------------------------------------------------------- the reader
@dataclass(frozen=True)
class Manifest:
    """A model directory's ``dssp_model.json``, every fact the runtime uses checked (:func:`read_manifest`).

    contract: what the model promises the robot; model: the architecture facts; source: where the weights came
    from; graphs: per graph its files {kind: name} and interface (inputs, outputs: [{name, shape, dtype}]); files:
    {name: {bytes, sha256, onnx_nodes?, weight_reads?}}; normalizers: per normalised tensor its per-channel statistics; data: the
    whole JSON as read (``model_config``: the training architecture; ``verification``, ``exporter``, ...)."""

    contract: ModelContract
    model: ModelFacts
    source: SourceFacts
    graphs: dict[str, Any]
    files: dict[str, dict[str, Any]]
    normalizers: dict[str, dict[str, list[float]]]
    data: dict[str, Any]

    @cached_property
    def history_state(self) -> list[str]:
        """The history graph's state inputs, in order ([] without a history encoder)."""
        return [s["name"] for s in history_state_specs(self.model)] if self.model.use_history else []

    @property
    def verification(self) -> dict[str, Any] | None:
        return self.data.get("verification")

    @property
    def model_config(self) -> dict[str, Any]:
        """The training ModelConfig as a dict: ``model_config`` with the contract's fields put back (FLOP counts)."""
        return {**self.data["model_config"], **self.contract.model_fields()}


def read_manifest(model_dir: Path) -> Manifest:
    """The manifest of a model directory, checked (see the module docstring), or a :class:`ModelDirError`."""
    model_dir = Path(model_dir)
    path = model_dir / MANIFEST_NAME
    if not model_dir.is_dir():
        raise ModelDirError(
            f"model directory {model_dir} does not exist; create one with python -m export.to_onnx RUN_DIR -o {model_dir}"
        )
    if not (path.exists() or path.is_symlink()):
        raise ModelDirError(
            f"{path} is missing: {model_dir} is not a DSSP model directory (python -m export.to_onnx makes one)"
        )
    data = read_json(path, str(path), error=ModelDirError, hint=AGAIN)
    if not isinstance(data, dict) or data.get("kind") != KIND:
        raise ModelDirError(f'{path} is not a DSSP model manifest (no "kind": "{KIND}"); {AGAIN}')
    if data.get("format_version") != FORMAT_VERSION:
        raise ModelDirError(
            f"{path} has format version {data.get('format_version')!r}, this runtime reads {FORMAT_VERSION!r}; "
            "export the model again with this version of dssp"
        )
    try:
        return check_manifest(data, model_dir)
    except ConfigError as exc:
        raise ModelDirError(f"{model_dir}: {exc}; {AGAIN}") from None


def check_manifest(data: dict[str, Any], model_dir: Path) -> Manifest:
    """Check every fact the runtime uses: the contract, the architecture, the files, the graphs' interface they
    give, the normalisers, the source. Raises ConfigError (a fact: one line naming it) or ModelDirError (a path)."""
    for key in ("contract", "model_config"):
        if key not in data:
            raise ConfigError(f"{MANIFEST_NAME}.{key} is missing")
    try:
        contract = ModelContract.from_json(data["contract"])
    except ConfigError as exc:
        raise ConfigError(f"{MANIFEST_NAME} {exc}") from None
    model = facts_from(ModelFacts, data["model_config"])
    diffusion = data["model_config"].get("diffusion")
    trained = diffusion.get("num_train_timesteps") if isinstance(diffusion, Mapping) else None
    if isinstance(trained, int) and not isinstance(trained, bool) and max(contract.ddim_timesteps) >= trained:
        raise ConfigError(
            f"{MANIFEST_NAME} contract.ddim_timesteps reach {max(contract.ddim_timesteps)}, but the model was "
            f"trained on timesteps 0..{trained - 1} (model_config.diffusion.num_train_timesteps)"
        )
    files = _check_files(data.get("files"), model_dir)
    graphs = _check_graphs(data.get("graphs"), contract, model, files, model_dir)
    normalizers = _check_normalizers(data.get("normalizers"), contract)
    source = facts_from(SourceFacts, data.get("source"))
    return Manifest(contract, model, source, graphs, files, normalizers, data)


def _check_files(files: Any, model_dir: Path) -> dict[str, dict[str, Any]]:
    """``files``: {file name: {bytes, sha256, onnx_nodes?, weight_reads?}}, every name inside the model directory
    (weight_reads: how often one run of an ONNX graph reads its weights, counted by the exporter)."""
    where = f"{MANIFEST_NAME} files"
    files = check_value(files, dict[str, Any], Spec(), where)
    for name, info in files.items():
        model_file(model_dir, name, f"{where} entry")
        entry = f"{where}[{name!r}]"
        info = check_value(info, dict[str, Any], Spec(), entry)
        for key in ("bytes", "sha256"):
            if key not in info:
                raise ConfigError(f"{entry}.{key} is missing")
        check_value(info["bytes"], int, Spec(ge=0), f"{entry}.bytes")
        if not isinstance(info["sha256"], str) or not _SHA256.fullmatch(info["sha256"]):
            raise ConfigError(f"{entry}.sha256 must be 64 lowercase hex digits, got {info['sha256']!r}")
        for key in ("onnx_nodes", "weight_reads"):
            if key in info:
                check_value(info[key], int, Spec(ge=0), f"{entry}.{key}")
    return files


def _check_graphs(
    graphs: Any, contract: ModelContract, model: ModelFacts, files: dict[str, Any], model_dir: Path
) -> dict[str, Any]:
    """Both graphs, their files (inside the directory, listed in ``files``) and the interface the facts give."""
    where = f"{MANIFEST_NAME} graphs"
    graphs = check_value(graphs, dict[str, Any], Spec(), where)
    missing = [g for g in GRAPHS if g not in graphs]
    if missing:
        raise ConfigError(
            f"{', '.join(f'{where}.{g}' for g in missing)} {'is' if len(missing) == 1 else 'are'} missing"
        )
    for graph in GRAPHS:
        spec = check_value(graphs[graph], dict[str, Any], Spec(), f"{where}.{graph}")
        for key in ("files", "inputs", "outputs"):
            if key not in spec:
                raise ConfigError(f"{where}.{graph}.{key} is missing")
        kinds = check_value(spec["files"], dict[str, Any], Spec(), f"{where}.{graph}.files")
        for kind, name in kinds.items():
            field = f"{where}.{graph}.files.{kind}"
            check_value(name, str, Spec(), field)
            model_file(model_dir, name, field)
            if name not in files:
                raise ConfigError(f"{field} is {name!r}, which has no size and sha256 in {MANIFEST_NAME} files")
        want = dict(zip(("inputs", "outputs"), graph_io(contract, model, graph)))
        for io in ("inputs", "outputs"):
            field = f"{where}.{graph}.{io}"
            declared = check_value(spec[io], list[dict[str, Any]], Spec(), field)
            names = [check_value(d.get("name"), str, Spec(), f"{field}[{i}].name") for i, d in enumerate(declared)]
            want_names = [w["name"] for w in want[io]]
            if names != want_names:
                raise ConfigError(
                    f"{field} are {names}, but use_history={str(model.use_history).lower()}, "
                    f"use_recent_states={str(model.use_recent_states).lower()}, n_history_layers={model.n_history_layers} "
                    f"give {want_names}"
                )
            for d, w in zip(declared, want[io]):
                shape = check_value(d.get("shape"), list[int | str], Spec(max_length=16), f"{field}.{w['name']}.shape")
                dtype = check_value(d.get("dtype"), str, Spec(choices=tuple(ONNX_TYPES)), f"{field}.{w['name']}.dtype")
                if shape != w["shape"] or dtype != w["dtype"]:
                    given = ", ".join(
                        f"{k}={getattr(model, k, None) or getattr(contract, k)}" for k in _depends(w["name"])
                    )
                    raise ConfigError(
                        f"{field}.{w['name']} is {dtype} {shape}, but {given} give {w['dtype']} {w['shape']}"
                    )
    return graphs


def _check_normalizers(normalizers: Any, contract: ModelContract) -> dict[str, Any]:
    """Per-channel statistics of the three normalised tensors, as many as the tensor has channels, finite, with
    scale > 0 and input_min <= input_max: the training ranges the runtime refuses observations and chunks outside
    of (:mod:`dssp_deploy.ranges`)."""
    where = f"{MANIFEST_NAME} normalizers"
    normalizers = check_value(normalizers, dict[str, Any], Spec(), where)
    for name, size in (
        ("point_cloud", contract.point_dim),
        ("agent_pos", contract.state_dim),
        ("action", contract.action_dim),
    ):
        if name not in normalizers:
            raise ConfigError(f"{where}.{name} is missing")
        stats = check_value(normalizers[name], dict[str, Any], Spec(), f"{where}.{name}")
        for key in NORMALIZER_STATS:
            field = f"{where}.{name}.{key}"
            values = check_value(stats.get(key), list[float], Spec(), field)
            if len(values) != size:
                raise ConfigError(f"{field} must hold {size} values (one per channel), got {len(values)}")
        for c, (scale, low, high) in enumerate(zip(stats["scale"], stats["input_min"], stats["input_max"])):
            if not scale > 0:
                raise ConfigError(
                    f"{where}.{name}.scale must be > 0 (y = x * scale + offset), got {scale!r} for channel {c}"
                )
            if not low <= high:
                raise ConfigError(f"{where}.{name}: channel {c} has input_min {low!r} > input_max {high!r}")
    return normalizers


# ----------------------------------------------------------------------------- the files
def _is_inside_name(name: str) -> bool:
    """A relative path that names something below its directory: not absolute, no '..', no drive."""
    if not name or "\x00" in name or "\\" in name:
        return False
    posix, windows = PurePosixPath(name), PureWindowsPath(name)
    if posix.is_absolute() or windows.is_absolute() or windows.drive:
        return False
    parts = posix.parts
    return bool(parts) and ".." not in parts and parts != (".",)


def model_file(model_dir: Path, name: Any, field: str) -> Path:
    """``model_dir / name`` for a file name read from the manifest, refused unless it stays inside the model
    directory: no absolute path, no '..', no symbolic link that leads out of it."""
    if not isinstance(name, str) or not _is_inside_name(name):
        raise ModelDirError(
            f"{model_dir}: {field} is {name!r}, which is not a file name inside the model directory "
            f"(absolute paths and '..' are refused); {AGAIN}"
        )
    path = Path(model_dir) / name
    try:
        root = Path(model_dir).resolve(strict=True)
        real = path.resolve()
    except (OSError, RuntimeError) as exc:  # a symbolic-link loop
        raise ModelDirError(f"{path} ({field}) cannot be resolved ({exc}); {AGAIN}") from None
    if real != root and not real.is_relative_to(root):
        raise ModelDirError(
            f"{path} ({field}) is a symbolic link to {real}, outside the model directory {root}; "
            "copy the file into the model directory or export the model again"
        )
    return path


def is_model_dir(path: Path) -> bool:
    """True when ``path`` holds a previous export of any format version (a manifest of this kind)."""
    try:
        manifest = parse_json(read_regular_text(Path(path) / MANIFEST_NAME) or "null")
    except ValueError:
        return False
    return isinstance(manifest, dict) and manifest.get("kind") == KIND


def graph_file(model_dir: Path, manifest: Manifest, graph: str, fmt: str = "onnx") -> Path:
    """Path of one graph's file in a model directory (inside it); a clear error when it is not there."""
    field = f"{MANIFEST_NAME} graphs.{graph}.files.{fmt}"
    name = manifest.graphs[graph]["files"].get(fmt)
    if name is None:
        quantized = next((p for p, kind in PRECISIONS.items() if fmt.startswith(kind) and p != "fp32"), None)
        if fmt.endswith(FUSED):
            how = "the fused Mamba kernel built (make kernel)"
        elif quantized:
            how = f"--quantize {quantized}"
        else:
            how = f"--format {fmt} (or both)"
        raise ModelDirError(f"{model_dir} has no {fmt} file for {graph}; export it with {how}")
    path = model_file(model_dir, name, field)
    if not path.is_file():
        raise ModelDirError(f"{path} is listed in {MANIFEST_NAME} but missing; {AGAIN}")
    return path


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_digest(path: Path, data: bytes, manifest: Manifest, name: str) -> None:
    """``data`` (the bytes of the manifest's file ``name``, read from ``path``) must have its size and sha256."""
    want = manifest.files.get(name)
    if want is None:
        raise ModelDirError(f"{path} has no size and sha256 in {MANIFEST_NAME} files; {AGAIN}")
    got = sha256_hex(data)
    if got != want["sha256"] or len(data) != want["bytes"]:
        raise ModelDirError(
            f"{path} is not the file this manifest was written for (sha256 {got[:12]}…, {len(data)} bytes; "
            f"{MANIFEST_NAME} says {want['sha256'][:12]}…, {want['bytes']} bytes): it comes from another export or "
            f"was changed; {AGAIN}, and copy model directories whole"
        )


def read_listed(path: Path, manifest: Manifest, name: str, label: str) -> bytes:
    """The bytes of the manifest's file ``name`` at ``path``, read as :func:`~dssp_core.files.read_input_bytes`
    reads (a regular file, never more than the size the manifest gives it), their size and sha256 checked."""
    want = manifest.files.get(name)
    if want is None:
        raise ModelDirError(f"{path} has no size and sha256 in {MANIFEST_NAME} files; {AGAIN}")
    if not (path.exists() or path.is_symlink()):
        raise ModelDirError(f"{label} is missing; {AGAIN}")
    with contextlib.suppress(OSError):
        if (size := path.stat().st_size) > want["bytes"]:  # larger than it was written: never read whole
            raise ModelDirError(
                f"{path} is not the file this manifest was written for ({size} bytes; {MANIFEST_NAME} "
                f"says sha256 {want['sha256'][:12]}…, {want['bytes']} bytes): it comes from another export or "
                f"was changed; {AGAIN}, and copy model directories whole"
            )
    data = read_input_bytes(path, label, limit=want["bytes"], error=ModelDirError)
    check_digest(path, data, manifest, name)
    return data


def read_graph(model_dir: Path, manifest: Manifest, graph: str, fmt: str = "onnx") -> tuple[Path, bytes]:
    """(path, bytes) of one graph's file, its size and sha256 checked against the manifest.

    Open the graph from these bytes: what runs is what was checked."""
    path = graph_file(model_dir, manifest, graph, fmt)
    return path, read_listed(path, manifest, manifest.graphs[graph]["files"][fmt], str(path))


def read_graph_files(
    model_dir: Path, manifest: Manifest, graph: str, fmt: str = "onnx"
) -> tuple[Path, bytes, dict[str, bytes]]:
    """(path, bytes, external data) of one ONNX graph: its file as :func:`read_graph` reads it, and the files its
    tensors' external data name, {location: bytes}. Each such file must be in the model directory (its location
    relative to the graph's folder: no absolute path, no '..', no symbolic link out) and have its own size and
    sha256 in the manifest's files, which its bytes must match; else a :class:`ModelDirError`.

    Give ONNX Runtime these bytes (``dssp_deploy.sessions.open_session``): what runs is what was checked."""
    path, data = read_graph(model_dir, manifest, graph, fmt)
    try:
        locations = external_locations(data)
    except MalformedGraph as exc:
        raise ModelDirError(f"{path} is not a well-formed ONNX graph ({exc}); {AGAIN}") from None
    folder = PurePosixPath(manifest.graphs[graph]["files"][fmt]).parent
    external = {}
    for location in locations:
        if location is None or not _is_inside_name(location):
            raise ModelDirError(
                f"{path} keeps tensors in external data at {location!r}, which is not a file name inside "
                f"the model directory (absolute paths and '..' are refused); {AGAIN}"
            )
        name = str(folder / location)
        file = model_file(model_dir, name, f"the external data of {path.name}")
        if name not in manifest.files:
            raise ModelDirError(
                f"{path} keeps tensors in {file}, which has no size and sha256 in {MANIFEST_NAME} files "
                f"(every file the runtime loads must); {AGAIN}"
            )
        external[location] = read_listed(file, manifest, name, f"{file} (the external data of {path.name})")
    return path, data, external


def check_session(session, manifest: Manifest, graph: str, where: Path) -> None:
    """The session's inputs and outputs must be the manifest's, in name, rank, fixed dims and dtype."""
    spec = manifest.graphs[graph]
    for kind, declared, actual in (
        ("input", spec["inputs"], session.get_inputs()),
        ("output", spec["outputs"], session.get_outputs()),
    ):
        want = [d["name"] for d in declared]
        have = [a.name for a in actual]
        if want != have:
            raise ModelDirError(f"{where}: {kind}s are {have}, {MANIFEST_NAME} says {want}; {AGAIN}")
        for d, a in zip(declared, actual):
            fixed = [s for s in d["shape"] if isinstance(s, int)]
            got = [s for s, w in zip(a.shape, d["shape"]) if isinstance(w, int)]
            if len(a.shape) != len(d["shape"]) or fixed != got or ONNX_TYPES.get(d["dtype"]) != a.type:
                raise ModelDirError(
                    f"{where}: {kind} {a.name} is {a.type} {list(a.shape)}, {MANIFEST_NAME} says "
                    f"{d['dtype']} {d['shape']}; {AGAIN}"
                )
