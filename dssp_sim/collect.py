"""Expert demonstrations in the simulation, written as a DP3 zarr dataset the trainer reads.

Per control tick (10 Hz): the env is rendered through :class:`~dssp_sim.mujoco_camera.MujocoCamera` and the
point-cloud pipeline (``dssp_data.pointcloud``, the one the robot runs) into point_cloud (P, 3); the
measured arm state (7,) [J1..J6 rad, gripper opening 0..1] is ``state``; the expert's target for this
tick (7,), the command sent to the arm, is ``action``. Only successful episodes are kept; each kept
episode is appended as soon as it ends (crash-safe: ``ReplayBufferWriter``).

``metaworld/NAME`` (:mod:`dssp_sim.metaworld_env`): DP3's protocol instead — MetaWorld's scripted expert, whole
200-step episodes kept when the task's success flag held for 5 steps, clouds (512, 3) in DP3's cloud frame, state (9,)
and action (4,) as DP3 stores them; the dataset's ``benchmark`` attribute names the task and protocol.

``out`` is a new dataset, or one this module wrote for the same task (its ``generator`` and ``task``
attributes), which is appended to; anything else there (a recorded dataset, another task's, a folder or a
file, a dataset folder holding a symbolic link) is refused before the simulation starts, and left as it is.
A collect holds the dataset's writer lock (:func:`dssp_data.replay_buffer_writer.dataset_lock`) from before the
simulation starts until it ends: a second collect (or a recording, a repair) of the same dataset is refused
with one line, and nothing of the first is touched.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dssp_core.errors import OutputError
from dssp_core.output_guard import OWN, OutputKind, check_append
from dssp_data.attributes import zarr_attrs, zarr_generator
from dssp_data.pointcloud import frame_to_cloud
from dssp_sim.mujoco_camera import MujocoCamera
from dssp_sim.settings import cloud_config_for, sim_attrs

SIM_DATASET = OutputKind(
    "a simulation dataset",
    "dssp-sim collect",
    marker=False,
    signature=lambda p: zarr_generator(p) == "dssp_sim.collect",
)
"""``dssp-sim collect --out``: a zarr dataset whose ``generator`` attribute is ``dssp_sim.collect`` (appended to)."""


@dataclass
class CollectResult:
    kept: int = 0
    attempted: int = 0
    failures: Counter = field(default_factory=Counter)
    steps: list[int] = field(default_factory=list)


def expert_episode(env, expert, camera: MujocoCamera, cloud_config, seed: int):
    """Run the expert for one episode; returns (point_cloud (T, P, 3), state (T, S), action (T, A), status): S = A = 7
    on the Piper, S = 9 and A = 4 on MetaWorld."""
    clouds, states, actions = [], [], []
    while True:
        frame = camera.capture()
        cloud, _ = frame_to_cloud(frame, cloud_config, camera.camera_to_base)
        state = env.state()
        action = expert.act(env)
        clouds.append(cloud)
        states.append(state)
        actions.append(action)
        env.step(action)
        status = env.status()
        if status.done:
            break
    return (
        np.stack(clouds).astype(np.float32),
        np.stack(states).astype(np.float32),
        np.stack(actions).astype(np.float32),
        status,
    )


def check_collect_output(out: Path, task: str) -> None:
    """Refuse an ``out`` that is neither new nor a dataset of ``task`` written by ``dssp-sim collect``."""
    if check_append(out, kind=SIM_DATASET, flag="--out") == OWN:
        have = (zarr_attrs(out) or {}).get("task")
        if have != task:
            raise OutputError(
                f"{out} holds {have!r} demonstrations, not {task!r}; collect {task!r} into another --out "
                "(nothing is changed)"
            )


def first_seed(out: Path, seed: int | None) -> int:
    """The scene seed to start from: ``seed``, else 0 for a new dataset, else the one after the last episode
    tried in ``out`` (its ``next_seed`` attribute), so appending never repeats a demonstration."""
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise OutputError(f"--seed must be an integer >= 0, got {seed!r}")
        return seed
    attrs = zarr_attrs(out) if Path(out).exists() else None
    if not attrs:
        return 0
    next_seed = attrs.get("next_seed")
    if isinstance(next_seed, bool) or not isinstance(next_seed, int) or next_seed < 0:
        raise OutputError(
            f"{out} does not record which scene seeds it holds; give --seed S, a seed past those "
            "already collected (or collect into another --out)"
        )
    return next_seed


def collect(
    task: str,
    n_episodes: int,
    out: Path,
    seed: int | None = None,
    n_points: int | None = None,
    max_attempts: int | None = None,
    progress: bool = True,
) -> CollectResult:
    """Append ``n_episodes`` successful expert episodes of ``task`` to ``out`` (seeds seed, seed+1, ...).

    ``seed`` None: 0 for a new dataset, the seed after the last one tried when appending (``first_seed``).
    """
    from dssp_data.replay_buffer_writer import dataset_lock  # deferred: loads msgpack, numcodecs, zarr

    check_collect_output(out, task)
    first_seed(out, seed)  # a bad --seed is refused before anything is created
    lock = dataset_lock(out, flag="--out")  # one writer per dataset: a second collect is refused here
    try:
        check_collect_output(out, task)  # again: another writer may have changed it meanwhile
        return _collect(task, n_episodes, out, first_seed(out, seed), n_points, max_attempts, progress)
    finally:
        lock.release()


def _task_env(task: str, seed: int, n_points: int | None):
    """(env, expert factory, point-cloud settings) for ``task``: a Piper memory task or ``metaworld/NAME``."""
    from dssp_sim import metaworld_env  # deferred: loads mujoco

    if metaworld_env.is_metaworld(task):  # DP3's protocol: whole 200-step episodes, kept at 5 successful steps
        env = metaworld_env.MetaWorldEnv(
            task, seed=seed, success_steps=metaworld_env.DEMO_SUCCESS_STEPS, stop_on_success=False
        )
        return env, metaworld_env.MetaWorldExpert, metaworld_env.cloud_config(n_points)
    from dssp_sim.env import PiperEnv  # deferred: loads mujoco
    from dssp_sim.experts import make_expert  # deferred: loads mujoco

    return PiperEnv(task, seed=seed), make_expert, cloud_config_for(n_points, task)


def _collect(
    task: str, n_episodes: int, out: Path, seed: int, n_points: int | None, max_attempts: int | None, progress: bool
) -> CollectResult:
    env, make_expert, cloud_config = _task_env(task, seed, n_points)
    try:
        return _collect_episodes(
            env, make_expert, cloud_config, task, n_episodes, out, seed, max_attempts or 2 * n_episodes + 5, progress
        )
    finally:
        env.close()


def _collect_episodes(
    env, make_expert, cloud_config, task: str, n_episodes: int, out: Path, seed: int, max_attempts: int, progress: bool
) -> CollectResult:
    from dssp_data.dataset_layout import Episode  # deferred: loads mujoco
    from dssp_data.replay_buffer_writer import ReplayBufferWriter  # deferred: loads mujoco
    from dssp_sim import metaworld_env  # deferred: loads mujoco

    result = CollectResult()
    bar = None
    if progress:
        bar = tqdm(total=n_episodes, desc=f"collect {task}", unit="episode")
    camera = MujocoCamera(env)
    attrs = (
        metaworld_env.dataset_attrs(env, camera, cloud_config)
        if metaworld_env.is_metaworld(task)
        else sim_attrs(task, env, camera, cloud_config)
    )
    with camera, ReplayBufferWriter(out, attrs=attrs, lock=False) as writer:
        episode_seed = seed
        while result.kept < n_episodes and result.attempted < max_attempts:
            env.reset(seed=episode_seed)
            expert = make_expert(env)
            clouds, states, actions, status = expert_episode(env, expert, camera, cloud_config, episode_seed)
            result.attempted += 1
            episode_seed += 1
            if status.success:
                writer.add_episode(
                    Episode(point_cloud=clouds, state=states, action=actions), attrs={"next_seed": episode_seed}
                )
                result.kept += 1
                result.steps.append(len(states))
                if bar is not None:
                    bar.update(1)
            else:
                result.failures[status.reason or "failed"] += 1
            if bar is not None:
                bar.set_postfix(attempted=result.attempted, failed=sum(result.failures.values()))
    if bar is not None:
        bar.close()
    return result
