"""What decides the action on each tick of the control loop: policy sources.

    runner = Runner(ModelPolicy(onnx_policy, control_rate_hz=10), rig, cloud_config, settings)   # dssp-run, dssp-sim eval
    runner = Runner(RecordedEpisode.load("pick.zarr", 3), rig, None, settings)             # dssp-replay
    runner = Runner(open_policy("hold"), rig, cloud_config, settings)                      # dssp-run --policy hold
    runner = Runner(LeaderArm(monitors), rig, None, settings, subscribers=[session])       # dssp-record

The loop (:class:`hardware.run_loop.Runner`) reads the camera and the arms, asks its source for an action, passes
the action through the safety layer and sends the command; what the source is — the exported model, a recorded
episode, the arm held where it is — changes nothing else. A source says whether it needs the point cloud
(:attr:`PolicySource.needs_cloud`: the loop then builds it every tick, and holds while the camera is stale), refuses
a robot it does not fit before anything opens (:meth:`~PolicySource.check`), is reset with the arm's measured
position when the loop starts (:meth:`~PolicySource.reset`), gives one :class:`Act` per tick
(:meth:`~PolicySource.act`), and may run out (:attr:`~PolicySource.done`: the loop then ends, ``ended by: done``).
A source whose arms are driven by something else (:attr:`PolicySource.commands` false: the teleoperation leader
arm, :mod:`hardware.policies.leader_arm`) only reports what that is: the loop then commands nothing.

``dssp-run --policy NAME[:ARG]`` runs the sources of :data:`REGISTRY` by name; a new one is one file in this
folder and one line in :data:`REGISTRY` (hardware/README.md, "Policy sources", has the worked example,
:mod:`hardware.policies.hold`). Shapes: cloud (P, C) float32, state and action (dof,) in policy units (per arm
[J1..J6 rad, gripper 0..1]).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from dssp_core.errors import ConfigError

if TYPE_CHECKING:  # annotations only: checking --policy (split_spec) loads neither
    from dssp_data.pointcloud import PointCloudConfig
    from hardware.robot import RobotDescription


@dataclass
class Act:
    """A source's answer for one tick.

    action: (dof,) float64 in policy units, or None (nothing this tick: the safety layer holds);
    observe_ms / chunk_ms: what the model's history step and a chunk that started on this tick cost (None: none);
    chunk: a new chunk's actions to come (H - offset, A) when this tick started one, else None;
    over_budget: the source missed the tick's deadline (the safety layer holds, ``deadline_hold``);
    events: lines for the tick's log record.
    """

    action: np.ndarray | None
    observe_ms: float | None = None
    chunk_ms: float | None = None
    chunk: np.ndarray | None = None
    over_budget: bool = False
    events: list[str] = field(default_factory=list)


class PolicySource:
    """Gives the loop an action each tick. Override :meth:`act`; the rest has defaults.

    ``name`` goes into the run's log; ``needs_cloud``: the loop builds the point cloud for :meth:`act` (and holds
    while the camera is stale or the cloud empty); without it ``act`` gets None and the camera does not gate the
    tick; ``control_rate_hz``: the rate the source was made for (a model's training data, a recording), or None;
    ``commands``: the loop sends the action through the safety layer to the arms (False: the arms are driven by
    something else, the action is a report — the loop enables, sends and holds nothing).
    :meth:`act` may raise the runtime's refusals (``NonFiniteObservation``, ``ObservationOutOfRange``: no
    observation; ``ChunkOutOfRange``: no action): the loop holds and goes on; any other exception is a fault.
    """

    name: str = "policy"
    needs_cloud: bool = True
    control_rate_hz: float | None = None
    commands: bool = True

    def check(self, description: RobotDescription, cloud_config: PointCloudConfig | None) -> None:
        """Refuse (ConfigError, one line) a robot or point-cloud pipeline this source does not fit — called before
        any device opens. The default takes any robot."""

    def reset(self, state: np.ndarray | None) -> None:
        """The loop starts: ``state`` (dof,) is the arm's measured position (None only for a source that commands
        nothing, started before any feedback came)."""

    def act(self, cloud: np.ndarray | None, state: np.ndarray) -> Act:
        """The action for this tick from ``cloud`` (P, C) float32 (None unless :attr:`needs_cloud`) and the measured
        ``state`` (dof,)."""
        raise NotImplementedError

    @property
    def done(self) -> bool:
        """True once the source has nothing more to give (a recorded episode played to its end)."""
        return False

    def describe(self) -> dict:
        """What the run's log says the source was."""
        return {"policy": self.name}


REGISTRY: dict[str, str] = {
    "hold": "hardware.policies.hold:Hold",  # the arm held where it starts: the rig checked end to end, nothing moves
    "episode": "hardware.policies.recorded:RecordedEpisode",  # episode:PATH.zarr@K, a recorded episode's actions
}
"""``dssp-run --policy NAME[:ARG]``: the source's class as ``module:Class``, built with ``from_spec(ARG)`` (ARG None
when the spec has no colon). ``dssp-run --model DIR`` is the model's source
(:class:`hardware.policies.exported_model.ModelPolicy`)."""


def split_spec(spec: str) -> tuple[str, str | None]:
    """``NAME[:ARG]`` → (NAME, ARG or None); an unknown NAME is refused with one line."""
    name, colon, arg = spec.partition(":")
    name = name.strip()
    if name not in REGISTRY:
        raise ConfigError(
            f"--policy {spec}: no such policy source; choose from {', '.join(sorted(REGISTRY))} "
            "(or --model DIR for an exported model)"
        )
    return name, (arg if colon else None)


def open_policy(spec: str) -> PolicySource:
    """The source ``NAME[:ARG]`` of :data:`REGISTRY`, built from its argument."""
    name, arg = split_spec(spec)
    module, _, cls = REGISTRY[name].partition(":")
    return getattr(importlib.import_module(module), cls).from_spec(arg)
