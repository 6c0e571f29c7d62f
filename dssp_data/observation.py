"""The observation contract a model carries from its dataset to the robot.

- :class:`PointCloudConfig`: how a depth frame becomes the model's cloud (crop box, depth range, voxel,
  sampler, points, channels), stored as plain JSON. The same settings build a dataset and run on the
  robot, so a policy sees identical clouds in both. Lengths are metres; the crop box is in the
  robot-base frame (after the camera->base extrinsic).
- :class:`VectorLayout`: what the state / action vector holds, per arm (left first): joint order and units.
- :class:`ObservationContract`: both, read from a dataset's attributes (:meth:`ObservationContract.from_attrs`),
  copied into the run's ``config.json`` (``observation``) and the model's ``dssp_model.json``
  (``observation``, beside ``control_rate_hz``). A field the dataset does not record (DP3 / RoboTwin files)
  is ``null`` in the run and ``"unknown"`` in the manifest: nothing is invented.
- :func:`contract_mismatches` / :func:`check_contract`: what ``dssp-run`` and ``dssp-record`` compare a
  camera/robot setup against before anything moves; ``--allow-mismatch FIELD`` overrides one field (and
  the override is written to the run's log).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from dssp_core.errors import ConfigError
from dssp_core.files import atomic_write_text
from dssp_core.schema import MAX_DIM, Settings, parse_json, setting

SAMPLING_METHODS = ("fps",)
MAX_RANGE_M = 20.0  # no depth camera of the toolkit measures farther; a larger value is a unit mistake (mm)
MAX_CROP_M = 100.0  # a crop corner this far out keeps everything; beyond it the box was given in millimetres


@dataclass(frozen=True)
class PointCloudConfig(Settings):
    """How a depth frame becomes a fixed-size cloud.

    n_points: points per cloud (P), default 1024.
    depth_near, depth_far: keep camera depths in [near, far] metres (0 = no measurement is always dropped).
    crop_min, crop_max: workspace box (x, y, z) metres in the robot-base frame; points outside are dropped.
      The default is a tabletop workspace in front of the arm base (base at the origin, x forward, z up,
      table surface at z = 0) and keeps the table surface.
    voxel_size: metres, 0 = off. One measured point is kept per occupied voxel before sampling.
      1 cm is about a third of the spacing of 1024 points spread over a 0.8 m x 0.8 m table, so it does
      not change what farthest point sampling picks, and it makes sampling several times faster.
    use_color: append RGB in [0, 1] as channels 3..5 (the frames must carry colour).
    sampling: 'fps' (farthest point sampling).
    """

    SECTION: ClassVar[str] = "pointcloud"

    n_points: int = setting(1024, ge=1, le=1_000_000)
    depth_near: float = setting(0.1, ge=0, le=MAX_RANGE_M, unit="m")
    depth_far: float = setting(2.0, gt=0, le=MAX_RANGE_M, unit="m")
    crop_min: tuple[float, float, float] = setting((0.0, -0.4, -0.02), ge=-MAX_CROP_M, le=MAX_CROP_M, unit="m")
    crop_max: tuple[float, float, float] = setting((0.8, 0.4, 0.5), ge=-MAX_CROP_M, le=MAX_CROP_M, unit="m")
    voxel_size: float = setting(0.01, ge=0, le=1.0, unit="m (0 = off)")
    use_color: bool = setting(False)
    sampling: str = setting("fps", choices=SAMPLING_METHODS)

    def validate(self) -> None:
        if not self.depth_near < self.depth_far:
            raise ConfigError(
                f"pointcloud.depth_near ({self.depth_near}) must be below depth_far ({self.depth_far}), metres"
            )
        if not all(a < b for a, b in zip(self.crop_min, self.crop_max)):
            raise ConfigError(
                f"pointcloud.crop_min {list(self.crop_min)} must be below crop_max {list(self.crop_max)} on every axis"
            )

    @property
    def point_dim(self) -> int:
        """Channels per point: 3 (xyz) or 6 (xyz + rgb)."""
        return 6 if self.use_color else 3

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "PointCloudConfig":
        try:
            data = parse_json(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"point cloud config is not valid JSON (line {e.lineno}: {e.msg})") from None
        except ValueError as e:  # a key given twice, nesting too deep
            raise ConfigError(f"point cloud config is not usable JSON ({e})") from None
        return cls.from_dict(data)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        atomic_write_text(path, self.to_json() + "\n")
        return path


UNKNOWN = "unknown"
FRAME_ROBOT_BASE = "robot_base: metres, x forward, z up, the arm's base at the origin"
PIPER_CHANNELS = ("J1 rad", "J2 rad", "J3 rad", "J4 rad", "J5 rad", "J6 rad", "gripper opening 0..1")


@dataclass(frozen=True)
class VectorLayout(Settings):
    """The state or action vector: ``arms`` blocks of ``channels`` ("name unit"), left arm first.

    The Piper's (RoboTwin order): per arm [J1..J6 rad, gripper opening 0..1]; dim = arms x 7."""

    SECTION: ClassVar[str] = "layout"

    arms: int = setting(1, ge=1, le=16)
    channels: tuple[str, ...] = setting(PIPER_CHANNELS, min_length=1, max_length=MAX_DIM)

    @property
    def dim(self) -> int:
        return self.arms * len(self.channels)


def piper_layout(arms: int) -> VectorLayout:
    """The Piper's state/action layout for one or two arms (what dssp-record and the simulation record)."""
    return VectorLayout(arms=arms, channels=PIPER_CHANNELS)


@dataclass(frozen=True)
class ObservationContract(Settings):
    """What the model's inputs were in training; ``None``: the dataset does not say.

    pointcloud: the point-cloud settings (shape (P, 3) or (P, 6) clouds in ``frame``).
    frame: the clouds' coordinate frame.
    state, action: the layouts of agent_pos (S,) and action (A,).
    (The control rate travels beside it as ``control_rate_hz``.)"""

    SECTION: ClassVar[str] = "observation"

    pointcloud: PointCloudConfig | None = setting(None)
    frame: str | None = setting(None)
    state: VectorLayout | None = setting(None)
    action: VectorLayout | None = setting(None)

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any], where: str) -> "ObservationContract":
        """The contract recorded in a dataset's attributes (``pointcloud``, ``state_layout``, ``action_layout``);
        a present but invalid attribute is a one-line ConfigError naming ``where`` and the attribute."""
        values: dict[str, Any] = {}
        for key, field, kind in (
            ("pointcloud", "pointcloud", PointCloudConfig),
            ("state_layout", "state", VectorLayout),
            ("action_layout", "action", VectorLayout),
        ):
            if attrs.get(key) is None:
                continue
            try:
                values[field] = kind.from_dict(attrs[key])
            except ConfigError as exc:
                raise ConfigError(f"{where}'s {key} attribute: {exc}; fix or remove the attribute") from None
        if "pointcloud" in values:  # a dataset names its clouds' frame when it is not the robot's base
            frame = attrs.get("pointcloud_frame", FRAME_ROBOT_BASE)
            if not isinstance(frame, str) or not frame:
                raise ConfigError(
                    f"{where}'s pointcloud_frame attribute must be a non-empty string, got {frame!r}; "
                    "fix or remove the attribute"
                )
            values["frame"] = frame
        return cls(**values)

    def to_manifest(self) -> dict[str, Any]:
        """JSON for ``dssp_model.json``: an unknown field is the string ``"unknown"``."""
        return {k: (UNKNOWN if v is None else v) for k, v in self.to_dict().items()}

    @classmethod
    def from_manifest(cls, values: Any) -> "ObservationContract":
        if values is None:  # a model directory written before the contract travelled with the model
            return cls()
        if not isinstance(values, dict):
            raise ConfigError(f"observation must be a JSON object, got {type(values).__name__}")
        return cls.from_dict({k: (None if v == UNKNOWN else v) for k, v in values.items()})

    def attrs(self) -> dict[str, Any]:
        """The dataset attributes that record this contract (what recorders write)."""
        out: dict[str, Any] = {}
        if self.pointcloud is not None:
            out["pointcloud"] = self.pointcloud.to_dict()
            if self.frame not in (None, FRAME_ROBOT_BASE):
                out["pointcloud_frame"] = self.frame
        if self.state is not None:
            out["state_layout"] = self.state.to_dict()
        if self.action is not None:
            out["action_layout"] = self.action.to_dict()
        return out


def _flat(prefix: str, value: Any) -> dict[str, Any]:
    if value is None:
        return {prefix: None}
    if isinstance(value, Settings):
        return {
            k: v for name in value.field_names() for k, v in _flat(f"{prefix}.{name}", getattr(value, name)).items()
        }
    return {prefix: value}


def contract_mismatches(trained: ObservationContract, given: ObservationContract) -> list[tuple[str, Any, Any]]:
    """``(field, trained value, given value)`` for every field both contracts know and that differ, e.g.
    ``("pointcloud.crop_min", (0.05, -0.35, 0.005), (0.0, -0.4, -0.02))``; fields either side does not know
    are not compared."""
    a = {k: v for name in trained.field_names() for k, v in _flat(name, getattr(trained, name)).items()}
    b = {k: v for name in given.field_names() for k, v in _flat(name, getattr(given, name)).items()}
    out = []
    for key in a:
        if key in b and a[key] is not None and b[key] is not None and _differs(a[key], b[key]):
            out.append((key, a[key], b[key]))
    return out


def _differs(a: Any, b: Any) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return abs(float(a) - float(b)) > 1e-9 * max(1.0, abs(float(a)))
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) != len(b) or any(_differs(x, y) for x, y in zip(a, b))
    return a != b


def check_contract(
    trained: ObservationContract,
    given: ObservationContract,
    *,
    trained_by: str,
    given_by: str | dict[str, str],
    allow: tuple[str, ...] | list[str] = (),
    remedy: str | None = None,
    extra: tuple[tuple[str, Any, Any], ...] | list[tuple[str, Any, Any]] = (),
) -> list[dict[str, Any]]:
    """Refuse a setup that contradicts the training contract, one line naming the field, both values and the
    flag that overrides; returns the overridden mismatches (``allow`` names them) for the log.

    ``trained_by``: whose values ``trained`` holds (e.g. "the model runs/x_model"); ``given_by``: where the
    setup's values come from (e.g. "--pointcloud cloud.json"; or one per top-level field: {"pointcloud": ...,
    "state": ...}); ``remedy``: the advice instead of the override
    (a dataset holds one contract: dssp-record has no override); ``extra``: ``(field, trained, given)`` facts
    that travel beside the contract (the control rate), judged by the same rule."""
    overridden = []
    beside = [(k, a, b) for k, a, b in extra if a is not None and b is not None and _differs(a, b)]
    for key, want, have in [*contract_mismatches(trained, given), *beside]:
        if key in allow:
            overridden.append({"field": key, "trained": _json(want), "given": _json(have)})
            continue
        by = given_by if isinstance(given_by, str) else given_by[key.split(".")[0]]
        raise ConfigError(
            f"{by} gives {key} = {_show(have)} but {trained_by} has {_show(want)}: "
            + (remedy or f"use the same settings, or pass --allow-mismatch {key} to run anyway (written to the log)")
        )
    return overridden


def contract_fields() -> list[str]:
    """Every field name :func:`check_contract` may name (what ``--allow-mismatch`` accepts)."""
    full = ObservationContract(pointcloud=PointCloudConfig(), frame="", state=VectorLayout(), action=VectorLayout())
    return [k for name in full.field_names() for k in _flat(name, getattr(full, name))]


def _json(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _show(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(_json(value))
