"""The exported graphs streamed one tick at a time, as the robot runs them, for :mod:`export.verify`.

``GraphStream`` runs a pair of graph functions (ONNX Runtime sessions or TorchScript traces) with the streaming history of
:class:`dssp_data.streaming_history.StreamingHistory`; ``RuntimeStream`` runs a model directory through the robot's
runtime (:class:`dssp_deploy.onnx_policy.OnnxPolicy`); ``torchscript_graph`` loads a ``.pt`` trace as a graph function.
Shapes: point cloud (B, P, C), agent_pos (B, S), the chunk (B, H, A).
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dssp_core.errors import ParityError
from dssp_data.streaming_history import StreamingHistory
from dssp_deploy.manifest import DENOISER_GRAPH, HISTORY_GRAPH, Manifest, no_inpainting
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import ChunkOutOfRange

GraphFn = Callable[[dict[str, np.ndarray]], list[np.ndarray]]
"""One exported graph as a function: named inputs in, its outputs in order."""


class GraphStream:
    """The runtime loop over two exported graph functions, numpy in and out.

    The history (zero state at the start, the last N ``z_t``, the first one repeated until N exist) is
    :class:`dssp_data.streaming_history.StreamingHistory`, as in the robot's runtime; the denoiser gets
    the inputs the manifest lists. observe: point_cloud (B, P, C), agent_pos (B, S) → z_t (B, d);
    ``context`` c_t (B, d); ``states`` the history state in manifest order; act: noise (B, H, A) → chunk
    (B, H, A) in raw units.
    """

    def __init__(self, manifest: Manifest, history: GraphFn, denoiser: GraphFn):
        self.manifest = manifest
        self.history_fn, self.denoiser_fn = history, denoiser
        self.state_specs = manifest.graphs[HISTORY_GRAPH]["inputs"][2:]
        self.denoiser_names = [s["name"] for s in manifest.graphs[DENOISER_GRAPH]["inputs"]]
        self.history = StreamingHistory(
            manifest.contract.n_obs_steps, self._step, lambda ts: np.stack(ts, axis=1), self.zero_state
        )

    def zero_state(self, batch: int) -> list[np.ndarray]:
        """The history state at an episode start: zeros, one array per manifest state input."""
        return [np.zeros([batch, *s["shape"][1:]], dtype=np.float32) for s in self.state_specs]

    def _step(self, point_cloud: np.ndarray, agent_pos: np.ndarray, states: list[np.ndarray]):
        feeds = {"point_cloud": point_cloud, "agent_pos": agent_pos}
        feeds.update({s["name"]: v for s, v in zip(self.state_specs, states)})
        out = self.history_fn(feeds)
        if not self.manifest.model.use_history:
            return out[0], None, states
        return out[0], out[1], list(out[2:])

    def observe(self, point_cloud: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        return self.history.observe(point_cloud, agent_pos)

    @property
    def context(self) -> np.ndarray | None:
        return self.history.context

    @property
    def states(self) -> list[np.ndarray] | None:
        return self.history.state

    def denoiser_inputs(self) -> dict[str, np.ndarray]:
        available = {"c_t": self.history.context, "z_recent": self.history.recent}
        feeds = {name: available[name] for name in self.denoiser_names if name in available}
        return {**feeds, **no_inpainting(self.manifest.contract, self.history.recent.shape[0])}

    def act(self, noise: np.ndarray) -> np.ndarray:
        return self.denoiser_fn({**self.denoiser_inputs(), "noise": noise})[0]


class RuntimeStream:
    """The robot's runtime, :class:`dssp_deploy.onnx_policy.OnnxPolicy`, with the interface of :class:`GraphStream`.

    The ONNX graphs (fp32, int8 or int4 with ``precision``; standard or fused with ``kernel``) are streamed through it, so parity covers the
    runtime's state handling too; it checks the files against the manifest itself.
    """

    def __init__(self, model_dir: Path, threads: int, precision: str = "fp32", kernel: str = "standard"):
        self.policy = OnnxPolicy(model_dir, threads=threads, warmup=0, precision=precision, kernel=kernel)
        self.name = f"{self.policy.precision} {self.policy.kernel}"

    def observe(self, point_cloud: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        return self.policy.observe(point_cloud, agent_pos)

    @property
    def context(self) -> np.ndarray | None:
        return self.policy.context

    @property
    def states(self) -> list[np.ndarray] | None:
        return None if self.policy.state is None else list(self.policy.state.values())

    def denoiser_inputs(self) -> dict[str, np.ndarray]:
        return self.policy.denoiser_inputs()

    def act(self, noise: np.ndarray) -> np.ndarray:
        """The chunk; one the runtime refuses (NaN/inf, outside the action range) on the trajectory fails parity."""

        try:
            return self.policy.act(noise=noise)
        except ChunkOutOfRange as exc:
            raise ParityError(
                f"the {self.name} graphs give a chunk the runtime refuses: {exc}; export the model again "
                "from finite weights, and report it with the run's config.json if it persists"
            ) from None


def torchscript_graph(path: Path, data: bytes | None = None) -> GraphFn:
    """A TorchScript graph as a function; ``data``: the file's bytes, already checked against the manifest."""

    import torch  # deferred: loads torch, tqdm

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)  # torch.jit is deprecated, still the .pt reader
        source = str(path) if data is None else io.BytesIO(data)
        module = torch.jit.load(source, map_location="cpu").eval()

    def run(feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        with torch.no_grad():
            out = module(*[torch.from_numpy(np.ascontiguousarray(v)) for v in feeds.values()])
        return [t.numpy() for t in (out if isinstance(out, tuple) else (out,))]

    return run
