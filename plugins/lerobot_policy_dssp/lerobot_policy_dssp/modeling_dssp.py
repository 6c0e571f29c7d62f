"""The DSSP policy in LeRobot: ``dssp_train``'s model, trained by ``lerobot-train``, saved as a dssp-train run too.

Training: LeRobot samples frames; each sample carries its episode's frames from ``history`` - 1 before the current
one to ``horizon`` - 1 after it (:class:`~lerobot_policy_dssp.configuration_dssp.DSSPConfig`). The frames of a
sample that lie inside its episode (the ``*_is_pad`` masks) are one trajectory, and the loss is dssp-train's
:meth:`dssp_train.model.policy.DSSPPolicy.compute_loss` on it with the window starting at the current frame:
the history encoder runs causally over the trajectory, the dynamics loss covers its transitions. The batch's loss
is the mean over its samples.

Normalisation stays inside the model: its min/max normalisers are fitted once from the dataset's statistics
(``meta/stats.json``), and LeRobot's processors pass the features through (IDENTITY). On a dataset of depth
(:mod:`lerobot_policy_dssp.depth`) the depth feature is replaced by a cloud feature (P, 3), made by a processor
step, and the cloud normaliser is fitted on the crop box of the point-cloud settings (the clouds lie inside it).

Saving: every LeRobot checkpoint (``pretrained_model/``) also holds ``dssp_run/``, a dssp-train run directory
(config.json, model.safetensors with the EMA weights, checkpoint/model.safetensors with the raw ones) that
``python -m export.to_onnx`` exports. LeRobot's own ``model.safetensors`` holds the raw weights and the count of
optimizer steps (what ``--resume`` continues; the EMA starts again from the resumed weights).

Inference (``select_action``, ``predict_action_chunk``): every call is the episode's next frame, taken into the
history by dssp_train's streaming path (one history-encoder step per frame, as the robot's runtime runs it).
"""

from __future__ import annotations

import logging
from collections import deque
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.pretrained import PreTrainedPolicy

from dssp_data.bounded import check_budget, human_size
from dssp_data.lerobot.layout import feature_layout
from dssp_train.config import RunConfig
from dssp_train.model.policy import DSSPPolicy as Model
from dssp_train.model.streaming import StreamingPolicy
from dssp_train.training import checkpoint as ckpt
from dssp_train.training.ema import EMA
from dssp_train.training.trainer import resolve_data_facts
from lerobot_policy_dssp.configuration_dssp import ACTION_KEY, CLOUD_KEY, STATE_KEY, DSSPConfig
from lerobot_policy_dssp.depth import cloud_range, resolve_depth_camera

RUN_DIR = "dssp_run"


def _facts(config: DSSPConfig, dataset_meta) -> SimpleNamespace:
    """What :func:`dssp_train.training.trainer.resolve_data_facts` reads of a dataset, from a LeRobot dataset's
    features: the sizes, the fps and the observation contract (the attributes dssp-data export wrote as the
    features' info and names)."""
    features = dataset_meta.features
    p, c = config.input_features[CLOUD_KEY].shape
    s = config.input_features[STATE_KEY].shape[0]
    a = config.output_features[ACTION_KEY].shape[0]
    cloud = (features[CLOUD_KEY].get("info") or {}) if CLOUD_KEY in features else {}
    attrs = {}
    if config.depth_camera:  # clouds made from the depth: the settings they are made with, in the robot's base
        attrs["pointcloud"] = config.depth_camera["pointcloud"]
        attrs["pointcloud_frame"] = config.depth_camera["frame"]
    elif isinstance(cloud.get("pointcloud"), dict):
        attrs["pointcloud"] = cloud["pointcloud"]
        if cloud.get("frame") is not None:
            attrs["pointcloud_frame"] = cloud["frame"]
    for key, name, dim in ((STATE_KEY, "state_layout", s), (ACTION_KEY, "action_layout", a)):
        layout = feature_layout(features[key], dim)
        if layout is not None:
            attrs[name] = layout.to_dict()
    return SimpleNamespace(
        point_dim=c, state_dim=s, action_dim=a, n_points=p, control_rate_hz=float(dataset_meta.fps), attrs=attrs
    )


def resolve_run_config(config: DSSPConfig, dataset_meta) -> RunConfig:
    """The preset with its overrides, its data facts filled from the LeRobot dataset (as dssp-train fills them)."""
    if dataset_meta is None:
        raise ValueError("a new DSSP policy is built from a dataset (--dataset.repo_id / --dataset.root)")
    user_set = {item.split("=", 1)[0] for item in config.overrides}
    return resolve_data_facts(
        config.run(), _facts(config, dataset_meta), str(dataset_meta.root), None, user_set=user_set
    )


def use_depth(config: DSSPConfig, dataset_meta) -> None:
    """A dataset of depth: record what the depth-to-cloud step needs (``config.depth_camera``) and replace the depth
    feature by the cloud feature (P, 3) it makes (so the model's sizes and the run's facts are a cloud's)."""
    if dataset_meta is None:
        raise ValueError("a new DSSP policy is built from a dataset (--dataset.repo_id / --dataset.root)")
    config.depth_camera = resolve_depth_camera(config, dataset_meta)
    features = {k: v for k, v in config.input_features.items() if k != config.depth_key}
    n_points = config.depth_camera["pointcloud"]["n_points"]
    features[CLOUD_KEY] = PolicyFeature(type=FeatureType.STATE, shape=(n_points, 3))
    config.input_features = features


def _longest_episode(dataset_meta) -> int:
    """The longest episode's frames (0 when the metadata does not say)."""
    try:
        return int(max(dataset_meta.episodes["length"]))
    except (AttributeError, KeyError, TypeError, ValueError):
        return 0


def check_sample_memory(config: DSSPConfig, dataset_meta) -> None:
    """Refuse, before LeRobot loads a sample, a window whose frames take more than the read budget
    (``DSSP_READ_BUDGET``, :func:`dssp_data.bounded.check_budget`): LeRobot loads ``config.window`` frames of every
    ``observation.*`` feature and the action for each sample — outside the episode too, as padding — each element
    at least a float32. A ValueError of one line naming the history, the size and what to do."""
    frame = sum(
        int(np.prod(feature["shape"])) * 4
        for key, feature in dataset_meta.features.items()
        if key.startswith("observation.") or key == ACTION_KEY
    )
    longest = _longest_episode(dataset_meta)
    check_budget(
        config.window * frame,
        f"a training sample of --policy.history={config.history} frames (and the chunk's {config.horizon - 1} "
        f"after it; {human_size(frame)} per frame)",
        "lower --policy.history" + (f" (the longest episode has {longest} frames)" if longest else ""),
        error=ValueError,
    )


def _range(stats: dict, key: str) -> np.ndarray:
    """(2, ...) the feature's min and max from LeRobot's statistics: what the min/max normalisers are fitted on."""
    return np.stack([np.asarray(stats[key]["min"], dtype=np.float64), np.asarray(stats[key]["max"], dtype=np.float64)])


class DSSPPolicy(PreTrainedPolicy):
    config_class = DSSPConfig
    name = "dssp"

    def __init__(self, config: DSSPConfig, dataset_stats=None, dataset_meta=None, **kwargs):
        super().__init__(config)
        if (
            config.run_config is None
            and CLOUD_KEY not in config.input_features
            and config.depth_key in config.input_features
        ):
            use_depth(config, dataset_meta)
        config.validate_features()
        if dataset_meta is not None:
            check_sample_memory(config, dataset_meta)
        if config.run_config is None:
            config.run_config = resolve_run_config(config, dataset_meta).to_dict()
            longest = _longest_episode(dataset_meta)
            if longest > config.history:
                logging.warning(
                    "the dataset's episodes run up to %d frames, more than --policy.history=%d: a sample's "
                    "trajectory starts at most %d frames before it (--policy.history=%d trains on whole "
                    "histories)",
                    longest,
                    config.history,
                    config.history - 1,
                    longest,
                )
            elif longest and config.history > 2 * longest:
                logging.warning(
                    "--policy.history=%d is more than twice the longest episode (%d frames): LeRobot loads "
                    "every sample's %d frames, the padding beyond the episode included; "
                    "--policy.history=%d trains on whole histories at a fraction of the cost",
                    config.history,
                    longest,
                    config.window,
                    longest,
                )
        self.run_config = RunConfig.from_dict(config.run_config)
        self.model = Model(self.run_config.model)
        if dataset_stats is not None:
            clouds = cloud_range(config.depth_camera) if config.depth_camera else _range(dataset_stats, CLOUD_KEY)
            self.model.fit_normalizers(clouds, *(_range(dataset_stats, k) for k in (STATE_KEY, ACTION_KEY)))
        self._ema: EMA | None = None
        # optimizer steps so far: in LeRobot's weights, so a resumed run's dssp_run/ records its true step
        self.register_buffer("optimizer_steps", torch.zeros((), dtype=torch.long))
        self.reset()

    # ------------------------------------------------------------------ training
    def get_optim_params(self) -> list[dict]:
        """dssp-train's groups: no weight decay on the parameters that ask for none."""
        decay, no_decay = [], []
        for p in self.model.parameters():
            if p.requires_grad:
                (no_decay if getattr(p, "_no_weight_decay", False) else decay).append(p)
        return [
            {"params": decay, "weight_decay": self.run_config.train.weight_decay},
            {"params": no_decay, "weight_decay": 0.0},
        ]

    def forward(self, batch: dict[str, torch.Tensor], reduction: str = "mean") -> tuple[torch.Tensor, dict]:
        clouds, states, actions = batch[CLOUD_KEY], batch[STATE_KEY], batch[ACTION_KEY]
        inside = ~(batch[f"{CLOUD_KEY}_is_pad"] | batch[f"{STATE_KEY}_is_pad"] | batch[f"{ACTION_KEY}_is_pad"])
        current = self.config.history - 1  # the sample's own frame
        results = []
        for b in range(actions.shape[0]):
            frames = torch.nonzero(inside[b]).flatten()
            first, last = int(frames[0]), int(frames[-1]) + 1  # the episode's frames are contiguous
            start = torch.tensor([current - first], device=actions.device)
            results.append(
                self.model.compute_loss(clouds[b, first:last], states[b, first:last], actions[b, first:last], start)
            )
        per_sample = torch.stack([r["loss"] for r in results])
        info = {k: float(torch.stack([r[k].detach() for r in results]).mean()) for k in ("diffusion", "dynamics")}
        return (per_sample if reduction == "none" else per_sample.mean()), info

    def update(self) -> None:
        """After every optimizer step (lerobot-train calls it): dssp-train's EMA of the weights."""
        if self._ema is None:  # (after --resume: from the resumed weights, its decay at the resumed step)
            t = self.run_config.train
            self._ema = EMA(self.model, t.ema_power, t.ema_max_decay)
            self._ema.step = int(self.optimizer_steps)
        self._ema.update(self.model)
        self.optimizer_steps += 1

    # -------------------------------------------------------------------- saving
    def _save_pretrained(self, save_directory: Path) -> None:
        super()._save_pretrained(save_directory)
        save_run(self, Path(save_directory) / RUN_DIR)

    # ----------------------------------------------------------------- inference
    def reset(self) -> None:
        """A new episode: the history is forgotten."""
        self._stream: StreamingPolicy | None = None
        self._queue: deque[torch.Tensor] = deque()

    def _observe(self, batch: dict[str, torch.Tensor]) -> None:
        """One frame into the history: the cloud (B, P, C) or (P, C) (LeRobot's batching step leaves 2-D features
        as they are), the state (B, S) or (S,)."""
        if self._stream is None:
            self._stream = StreamingPolicy(self.model)
        self._stream.observe(batch[CLOUD_KEY], batch[STATE_KEY])

    @torch.no_grad()
    def predict_action_chunk(
        self, batch: dict[str, torch.Tensor], noise: torch.Tensor | None = None, **kwargs
    ) -> torch.Tensor:
        """The batch is the episode's next frame (since :meth:`reset`): the history takes it, one step of the
        streaming path (:mod:`dssp_train.model.streaming`, what the exported graphs run); returns the chunk
        (B, H, A) in raw units, from ``noise`` (B, H, A) or a fresh draw."""
        self._observe(batch)
        recent = self._stream.recent
        m = self.run_config.model
        if noise is None:
            noise = torch.randn((recent.shape[0], m.horizon, m.action_dim), device=recent.device)
        chunk = self.model.sample_normalized(self.model.build_prefix(self._stream.context, recent), noise)
        return self.model.normalizers["action"].unnormalize(chunk)

    @torch.no_grad()
    def select_action(self, batch: dict[str, torch.Tensor], **kwargs) -> torch.Tensor:
        """(B, A): the next action of the current chunk; a new chunk every H_a frames. Every call is a frame."""
        if self._queue:
            self._observe(batch)
        else:
            m = self.run_config.model
            chunk = self.predict_action_chunk(batch, **kwargs)[:, m.action_offset : m.action_offset + m.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()


def save_run(policy: DSSPPolicy, run_dir: Path) -> None:
    """A dssp-train run directory of the policy: config.json, model.safetensors (the EMA weights; the raw ones
    before the first optimizer step), checkpoint/model.safetensors (the raw weights), each recording the config."""
    config = policy.run_config
    step = int(policy.optimizer_steps)
    meta = {"format_version": ckpt.FORMAT_VERSION, "step": str(step), **ckpt.config_record(config)}
    raw = policy.model.state_dict()
    (run_dir / "checkpoint").mkdir(parents=True, exist_ok=True)
    ckpt.save_tensors(run_dir / "model.safetensors", policy._ema.model.state_dict() if policy._ema else raw, meta)
    ckpt.save_tensors(run_dir / "checkpoint" / "model.safetensors", raw, meta)
    ckpt.save_config(run_dir, config)
