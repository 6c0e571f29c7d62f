"""The training loop behind ``dssp-train``.

One optimisation step = one whole training trajectory (per process), B action windows sampled
from it (paper Appendix C.1); AdamW, cosine schedule with warm-up, EMA weights for validation and
export, held-out validation episodes, seeded sampling, resumable checkpoints. Under ``torchrun``
(``WORLD_SIZE`` > 1) the model is wrapped in DistributedDataParallel (gloo on CPU, NCCL on CUDA);
each process draws its own trajectory, so a step sees ``world_size`` trajectories.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import shutil
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from tqdm.auto import tqdm

from dssp_core.errors import CheckpointError, ConfigError, DSSPError
from dssp_data.observation import ObservationContract
from dssp_data.replay_buffer import ReplayBuffer
from dssp_train.config import RunConfig, resolve_epochs
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training import checkpoint as ckpt
from dssp_train.training.dashboards import Dashboard, open_dashboard
from dssp_train.training.distillation import DistillObjective, init_student, load_teacher
from dssp_train.training.ema import EMA
from dssp_train.training.lr_schedule import cosine_with_warmup
from dssp_train.training.memory import check_memory
from dssp_train.training.train_log import RunLog, ValChunk, chunk_figure, plot_log

VAL_SEED = 1234567


@dataclass
class TrajectoryTensors:
    """One episode as tensors: point_cloud (T, P, C), agent_pos (T, S), action (T, A)."""

    point_cloud: torch.Tensor
    agent_pos: torch.Tensor
    action: torch.Tensor

    @property
    def length(self) -> int:
        return self.action.shape[0]


def split_episodes(n_episodes: int, val_ratio: float, seed: int) -> tuple[list[int], list[int]]:
    """Held-out validation episodes: round(n * val_ratio), at least 1 when val_ratio > 0 and n >= 2."""
    order = np.random.default_rng(seed).permutation(n_episodes).tolist()
    n_val = 0
    if val_ratio > 0 and n_episodes >= 2:
        n_val = min(n_episodes - 1, max(1, round(n_episodes * val_ratio)))
    return sorted(order[n_val:]), sorted(order[:n_val])


def resolve_data_facts(
    config: RunConfig,
    data: ReplayBuffer,
    data_path: str,
    control_rate_hz: float | None,
    *,
    resume: bool = False,
    user_set: Collection[str] = (),
) -> RunConfig:
    """Fill the dimensions, the control rate and the observation contract from the dataset; refuse what does not fit.

    ``control_rate_hz``: the rate the user gave (``--control-rate``); it must agree with the rate the dataset
    records, if any. ``resume``: ``config`` is a run's own config, continued on ``data``: nothing in it is
    replaced (its dataset path stays; a control rate it lacks may be filled in). ``user_set``: the
    ``section.field`` names the user set (``--set``), refused when the dataset says otherwise.
    """
    m = config.model
    if data.point_dim < m.point_dim:
        raise ConfigError(
            f"model.point_dim={m.point_dim} needs xyz+rgb clouds but {data_path} has {data.point_dim} channels per point; "
            + ("--resume continues a run on the same --data it was trained on" if resume else "use model.point_dim=3")
        )
    for name, have, what in (
        ("state_dim", data.state_dim, "state values"),
        ("action_dim", data.action_dim, "action values"),
        ("n_points", data.n_points, "points per cloud"),
    ):
        want = getattr(m, name)
        if want == have or (name != "n_points" and not want):
            setattr(m, name, have)
            continue
        if resume:
            raise ConfigError(
                f"the run's config has model.{name}={want} but {data_path} has {have} {what}: it was trained on "
                "other data; --resume continues it on the same --data"
            )
        if name != "n_points" or f"model.{name}" in user_set:
            raise ConfigError(
                f"--set model.{name}={want} but {data_path} has {have} {what}; drop the override to use the dataset's"
            )
        setattr(m, name, have)  # the preset's cloud size: the dataset's is used
    if not resume or config.dataset is None:
        config.dataset = str(data_path)
    recorded = data.control_rate_hz
    if (
        control_rate_hz is not None
        and recorded is not None
        and not math.isclose(control_rate_hz, recorded, rel_tol=1e-9)
    ):
        raise ConfigError(
            f"--control-rate {control_rate_hz:g} Hz contradicts the {recorded:g} Hz that {data_path} records; "
            "drop --control-rate (the recorded rate is used)"
        )
    rate = control_rate_hz if control_rate_hz is not None else recorded
    if resume and config.control_rate_hz is not None:  # the run's rate stays; a contradiction is refused
        if rate is not None and not math.isclose(rate, config.control_rate_hz, rel_tol=1e-9):
            if control_rate_hz is not None:
                raise ConfigError(
                    f"--control-rate {rate:g} Hz contradicts the run's control rate of "
                    f"{config.control_rate_hz:g} Hz; drop --control-rate"
                )
            raise ConfigError(
                f"{data_path} now records {rate:g} Hz but the run was trained at {config.control_rate_hz:g} Hz: "
                "the dataset changed since; start a new run (--force, or another --out)"
            )
    elif rate is not None:
        config.control_rate_hz = float(rate)
    recorded_contract = ObservationContract.from_attrs(data.attrs, str(data_path))
    if not resume or config.observation == ObservationContract():  # a resumed run keeps the contract it has
        config.observation = recorded_contract
    pointcloud = config.observation.pointcloud
    if pointcloud is not None and pointcloud.n_points != m.n_points:
        raise ConfigError(
            f"{data_path}'s pointcloud attribute says {pointcloud.n_points} points per cloud but its clouds "
            f"hold {m.n_points}: fix the attribute"
        )
    RunConfig.from_dict(config.to_dict())  # re-validate
    return config


def dataset_identity(data: ReplayBuffer, data_path: str | os.PathLike) -> dict[str, Any]:
    """What a checkpoint records of its dataset: the resolved path, episode count, steps and a digest of the
    episode boundaries (cheap, and changes when episodes are added, removed or cut)."""
    ends = np.asarray(data.episode_ends, dtype=np.int64)
    return {
        "path": os.path.realpath(data_path),
        "n_episodes": int(data.n_episodes),
        "n_steps": int(data.n_steps),
        "episode_ends_sha256": hashlib.sha256(ends.tobytes()).hexdigest(),
    }


def check_resume_data(run_dir: Path, config: RunConfig, data: ReplayBuffer, data_path: str | os.PathLike) -> None:
    """Refuse to continue a run on another dataset than the one it was trained on (or on one that changed)."""
    state = ckpt.read_trainer_state(run_dir) or {}
    recorded = state.get("dataset") if isinstance(state.get("dataset"), dict) else None
    trained_on = (recorded or {}).get("path") or config.dataset
    if trained_on is not None and os.path.realpath(trained_on) != os.path.realpath(data_path):
        raise ConfigError(
            f"{run_dir} was trained on {trained_on}; --resume continues it on the same --data (got {data_path})"
        )
    if recorded is not None:
        now = dataset_identity(data, data_path)
        if any(recorded.get(k) != now[k] for k in ("n_episodes", "n_steps", "episode_ends_sha256")):
            raise ConfigError(
                f"{data_path} changed since {run_dir} was trained on it ({recorded.get('n_episodes')} episodes, "
                f"{recorded.get('n_steps')} steps then; {now['n_episodes']} episodes, {now['n_steps']} steps now): "
                "its held-out episodes would not be the same; start a new run (--force, or another --out)"
            )


# Fewer training episodes than this and the validation holdout is warned about: it takes a real share of the data.
FEW_TRAINING_EPISODES = 20


def budget_notes(config: RunConfig, n_train: int, n_val: int) -> list[str]:
    """The lines a run prints at its start: its budget in steps (and epochs), and a warning about a costly holdout."""
    tc = config.train
    epochs = tc.steps / n_train
    how = (
        f"{tc.epochs} epochs x {n_train} training episodes"
        if tc.epochs
        else f"train.steps, {epochs:.4g} epochs of {n_train} training episodes"
    )
    notes = [f"budget: {tc.steps} steps ({how}), {tc.batch_size} windows per step"]
    if n_val and n_train < FEW_TRAINING_EPISODES:
        notes.append(
            f"warning: the validation holdout (train.val_ratio={tc.val_ratio}) takes {n_val} of {n_train + n_val} episodes, "
            f"leaving {n_train} to train on; --no-holdout trains on all of them (validation then reports on training episodes)"
        )
    return notes


class Trainer:
    """One training run into ``run_dir`` on the dataset at ``data_path`` (:meth:`run` trains it).

    ``resume``: continue the run's checkpoint (``config`` is then the run's own). ``progress``: a progress bar.
    ``control_rate_hz``: the rate the user gave (``--control-rate``). ``user_set``: the fields the user set with
    ``--set``. ``dashboard``: where the log goes besides ``log.jsonl`` (``--log``: tensorboard, wandb or none;
    :mod:`dssp_train.training.dashboards`), on the main process only.
    """

    def __init__(
        self,
        config: RunConfig,
        data_path: str | os.PathLike,
        run_dir: str | os.PathLike,
        device: str = "cpu",
        resume: bool = False,
        progress: bool = True,
        control_rate_hz: float | None = None,
        user_set: Collection[str] = (),
        dashboard: str = "none",
    ):
        self.world_size = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        if device == "cuda" and not torch.cuda.is_available():
            raise ConfigError("--device cuda was asked for but CUDA is not available here; use --device cpu")
        if self.world_size > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if device == "cuda" else "gloo")
        if device == "cuda" and self.world_size > 1:
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
        self.device = torch.device(device)
        self.run_dir = Path(run_dir)
        self.is_main = self.rank == 0
        self.progress = progress and self.is_main
        self.dashboard = dashboard
        self.val_chunk: ValChunk | None = None  # the last validation's first chunk (what the dashboards plot)

        self.data = ReplayBuffer.load(data_path)
        # On --resume the caller passes the run's own config (dssp-train does).
        if resume:
            check_resume_data(self.run_dir, config, self.data, data_path)
        self.config = config = resolve_data_facts(
            config, self.data, str(data_path), control_rate_hz, resume=resume, user_set=user_set
        )
        self.dataset_identity = dataset_identity(self.data, data_path)
        tc = config.train

        self.train_ids, self.val_ids = split_episodes(self.data.n_episodes, tc.val_ratio, tc.seed)
        if not self.train_ids:
            raise DSSPError(
                f"{data_path} has no training episodes left after the validation split; lower train.val_ratio"
            )
        if tc.epochs and not resume:  # a resumed run keeps the steps it resolved (or the --steps it was given)
            self.config = config = resolve_epochs(config, len(self.train_ids))
            tc = config.train
        self.notes = budget_notes(config, len(self.train_ids), len(self.val_ids))
        self.train_eps = [self._episode(i) for i in self.train_ids]
        self.val_eps = [self._episode(i) for i in self.val_ids] or self.train_eps
        self.val_on_train = not self.val_ids
        check_memory(config, max(ep.length for ep in self.train_eps), self.device)

        torch.manual_seed(tc.seed)
        self.policy = DSSPPolicy(config.model)
        cat = lambda key: np.concatenate([getattr(self.data.episode(i), key) for i in self.train_ids])  # noqa: E731
        self.policy.fit_normalizers(cat("point_cloud"), cat("state"), cat("action"))
        self.policy.to(self.device)
        self.teacher = None
        if config.distill.teacher:  # a few-step student: the teacher's weights and normalisers to start with
            self.teacher = load_teacher(config, self.device)
            init_student(self.policy, self.teacher, config.distill.freeze_encoders)

        decay, no_decay = [], []
        for p in self.policy.parameters():
            if not p.requires_grad:  # a student's frozen encoders
                continue
            (no_decay if getattr(p, "_no_weight_decay", False) else decay).append(p)
        self.optimizer = torch.optim.AdamW(
            [{"params": decay, "weight_decay": tc.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
            lr=tc.lr,
            betas=tuple(tc.betas),
        )
        self.lr_schedule = cosine_with_warmup(self.optimizer, tc.warmup_steps, tc.steps)
        self.ema = EMA(self.policy, tc.ema_power, tc.ema_max_decay)
        self.generator = torch.Generator().manual_seed((tc.seed * 1000 + self.rank) % 2**64)
        self.step = 0
        self.resumed = resume
        if resume:
            self._restore()
        self.start_step = self.step  # where this process began: 0, or the checkpoint's step on --resume
        self.model = self.policy
        if self.teacher is not None:
            self.model = DistillObjective(self.policy, self.teacher, config)
        if self.world_size > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )

    # ------------------------------------------------------------------ data
    def _episode(self, i: int) -> TrajectoryTensors:
        ep = self.data.episode(i)
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(self.device)  # noqa: E731
        return TrajectoryTensors(t(ep.point_cloud), t(ep.state), t(ep.action))

    def _window_count(self, length: int) -> int:
        """How many windows a trajectory of ``length`` steps has: starts 0 ... T - H_a (H_a real actions in each)."""
        return max(1, length - self.config.model.n_action_steps + 1)

    def _sample_starts(self, length: int, count: int) -> torch.Tensor:
        """Window starts t ~ U{0, ..., T - H_a} (at least H_a real actions in every window)."""
        return torch.randint(0, self._window_count(length), (count,), generator=self.generator).to(self.device)

    @functools.cached_property
    def _windows(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per training trajectory, its window count and the running total (E,), (E,): computed once."""
        counts = torch.tensor([self._window_count(ep.length) for ep in self.train_eps])
        return counts, counts.cumsum(0)

    def _sample_windows(self, count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``count`` windows drawn uniformly from every training trajectory's windows (DP3's sampling, with
        replacement where DP3 shuffles epochs: each window as likely, and a resumed run draws on from its generator's
        state): point_cloud (B, N, P, C), agent_pos (B, N, S), action (B, H, A), raw."""
        counts, ends = self._windows
        drawn = torch.randint(0, int(ends[-1]), (count,), generator=self.generator)
        which = torch.searchsorted(ends, drawn, right=True)
        parts = []
        for i in which.unique().tolist():
            ep, picked = self.train_eps[i], drawn[which == i]
            starts = (picked - (ends[i] - counts[i])).to(self.device)
            obs_idx, act_idx = self.policy.trajectory_windows(ep.length, starts)
            parts.append((ep.point_cloud[obs_idx], ep.agent_pos[obs_idx], ep.action[act_idx]))
        return tuple(torch.cat(x) for x in zip(*parts))

    # -------------------------------------------------------------- training
    def train_step(self) -> dict[str, float]:
        tc = self.config.train
        self.model.train()
        if tc.sampling == "windows":
            losses = self.model(*self._sample_windows(tc.batch_size), self.generator, windows=True)
        else:
            ep = self.train_eps[int(torch.randint(len(self.train_eps), (1,), generator=self.generator))]
            starts = self._sample_starts(ep.length, tc.batch_size)
            losses = self.model(ep.point_cloud, ep.agent_pos, ep.action, starts, self.generator)
        self.optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        self.optimizer.step()
        self.lr_schedule.step()
        self.ema.update(self.policy)
        self.step += 1
        values = {k: float(v.detach()) for k, v in losses.items()}
        if not all(math.isfinite(v) for v in values.values()):
            raise DSSPError(
                f"the loss became non-finite at step {self.step} ({values}); lower train.lr or check the data"
            )
        return values

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """EMA model on held-out episodes, with fixed windows, noise and timesteps: {val_diffusion, val_action_mse}.
        With a dashboard, the middle window of the first episode is kept in ``val_chunk`` (what it plots)."""
        policy = self.ema.model
        tc, mc = self.config.train, self.config.model
        gen = torch.Generator().manual_seed(VAL_SEED)
        per_ep = max(1, tc.val_windows // len(self.val_eps))
        diff, mse, weights = 0.0, 0.0, 0
        executed = slice(mc.action_offset, mc.action_offset + mc.n_action_steps)  # the actions the robot runs
        for i, ep in enumerate(self.val_eps):
            high = max(1, ep.length - mc.n_action_steps + 1)
            starts = torch.linspace(0, high - 1, min(per_ep, high)).round().long().to(self.device)
            losses = policy.compute_loss(ep.point_cloud, ep.agent_pos, ep.action, starts, gen)
            noise = torch.randn((len(starts), mc.horizon, mc.action_dim), generator=gen).to(self.device)
            pred = policy.sample_trajectory_windows(ep.point_cloud, ep.agent_pos, starts, noise)
            _, act_idx = policy.trajectory_windows(ep.length, starts)
            norm = policy.normalizers["action"].normalize
            err = (norm(pred) - norm(ep.action[act_idx]))[:, executed].pow(2).mean()
            if i == 0 and self.dashboard != "none":
                k = len(starts) // 2
                self.val_chunk = ValChunk(
                    episode=(self.val_ids or self.train_ids)[0],
                    start=int(starts[k]),
                    steps=act_idx[k].cpu().numpy(),
                    sampled=pred[k].cpu().numpy(),
                    expert=ep.action[act_idx[k]].cpu().numpy(),
                    executed=(executed.start, executed.stop),
                    held_out=not self.val_on_train,
                )
            diff += float(losses["diffusion"]) * len(starts)
            mse += float(err) * len(starts)
            weights += len(starts)
        return {"val_diffusion": diff / weights, "val_action_mse": mse / weights}

    def run(self) -> dict[str, Any]:
        """Train to ``train.steps``, logging, validating and saving on the way; returns the summary (step, run_dir
        and the last validation's values). ``log.jsonl`` gets every log row; the dashboard, if any, the same."""
        log: RunLog | None = None
        dashboard: Dashboard | None = None
        failed = True
        try:
            if self.is_main:
                self.run_dir.mkdir(parents=True, exist_ok=True)
                if not self.resumed:  # a resumed run's config.json changes with its next checkpoint (save)
                    ckpt.save_config(self.run_dir, self.config)
                resume_step = self.step if self.step > 0 else None
                log = RunLog(self.run_dir / "log.jsonl", resume_step=resume_step)
                dashboard = open_dashboard(self.dashboard, self.run_dir, self.config.to_dict(), resume_step)
            last_val = self._train_loop(log, dashboard)
            failed = False
        finally:
            if dashboard is not None:
                dashboard.close(failed=failed)
            if log is not None:
                log.close()
        if self.world_size > 1:
            self._log_param_checksums()
        if self.is_main:
            plot_log(self.run_dir / "log.jsonl", self.run_dir / "loss.png")
        if self.world_size > 1:
            dist.barrier()
        return {"step": self.step, "run_dir": str(self.run_dir), **last_val}

    def _train_loop(self, log: RunLog | None, dashboard: Dashboard | None) -> dict[str, float]:
        """The steps from ``self.step`` to ``train.steps``; ``log`` and ``dashboard`` (None on the other processes)
        receive each log and validation row. Returns the last validation's values."""
        tc = self.config.train
        bar = None
        if self.progress:
            bar = tqdm(total=tc.steps, initial=self.step, desc="dssp-train", unit="step", dynamic_ncols=True)
        last_val: dict[str, float] = {}
        t_log, n_log = time.perf_counter(), 0
        try:
            while self.step < tc.steps:
                values = self.train_step()
                n_log += 1
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(
                        {k: f"{values[k]:.4f}" for k in ("diffusion", "dynamics", "distill") if k in values}
                    )
                if self.step % tc.log_every == 0 or self.step == tc.steps:
                    elapsed = time.perf_counter() - t_log
                    rate = n_log / max(elapsed, 1e-9)
                    if log is not None:
                        row = {
                            "lr": self.lr_schedule.get_last_lr()[0],
                            "steps_per_s": rate,
                            "windows_per_s": rate * tc.batch_size * self.world_size,
                            **values,
                        }
                        log.write("train", step=self.step, **row)
                        dashboard.log_scalars(self.step, row)
                    t_log, n_log = time.perf_counter(), 0
                if self.is_main and (self.step % tc.val_every == 0 or self.step == tc.steps):
                    last_val = self.validate()
                    log.write("val", step=self.step, on_train_episodes=self.val_on_train, **last_val)
                    dashboard.log_scalars(self.step, last_val)
                    if self.val_chunk is not None:
                        dashboard.log_figure(self.step, "val_chunk", chunk_figure(self.val_chunk))
                    if bar is not None:
                        bar.write(f"step {self.step}: " + ", ".join(f"{k} {v:.5f}" for k, v in last_val.items()))
                if self.is_main and (self.step % tc.save_every == 0 or self.step == tc.steps):
                    self.save()
                if self.is_main and tc.keep_every and self.step % tc.keep_every == 0:
                    self.keep_snapshot()
        finally:
            if bar is not None:
                bar.close()
        return last_val

    def _log_param_checksums(self) -> None:
        """Under DDP: a SHA-256 of every process's weights, gathered into log.jsonl (they must all be equal)."""
        digest = hashlib.sha256()
        for value in self.policy.state_dict().values():
            digest.update(value.detach().cpu().contiguous().numpy().tobytes())
        checksums: list[str | None] = [None] * self.world_size
        dist.all_gather_object(checksums, digest.hexdigest())
        if self.is_main:
            log = RunLog(self.run_dir / "log.jsonl", append=True)
            log.write("ddp", world_size=self.world_size, param_checksums=checksums)
            log.close()

    # ----------------------------------------------------------- checkpoints
    def save(self) -> None:
        """The EMA weights, the checkpoint, then config.json: each records the config it was trained with
        (:func:`~dssp_train.training.checkpoint.config_record`), which config.json then is."""
        meta = {"format_version": ckpt.FORMAT_VERSION, "step": str(self.step), **ckpt.config_record(self.config)}
        ckpt.save_tensors(self.run_dir / "model.safetensors", self.ema.model.state_dict(), meta)
        ckpt.save_training_state(
            self.run_dir,
            self.policy,
            self.ema.model,
            self.optimizer,
            {
                "step": self.step,
                "ema_step": self.ema.step,
                "world_size": self.world_size,
                "dataset": self.dataset_identity,
            },
            {"generator": self.generator.get_state(), "torch": torch.get_rng_state()},
            config=self.config,
        )
        ckpt.save_config(self.run_dir, self.config)

    def keep_snapshot(self) -> Path:
        """RUN/snapshots/step_NNNNNNN/: this step's EMA weights and config.json, written to a temporary folder and
        renamed (a snapshot is whole or absent)."""
        folder = self.run_dir / "snapshots" / f"step_{self.step:07d}"
        staging = folder.with_name(folder.name + ".tmp")
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        meta = {"format_version": ckpt.FORMAT_VERSION, "step": str(self.step), **ckpt.config_record(self.config)}
        ckpt.save_tensors(staging / "model.safetensors", self.ema.model.state_dict(), meta)
        ckpt.save_config(staging, self.config)
        shutil.rmtree(folder, ignore_errors=True)
        staging.rename(folder)
        return folder

    def _restore(self) -> None:
        state = ckpt.load_training_state(self.run_dir)
        where = state["path"]
        ckpt.load_state_into(self.policy, state["model"], where / "model.safetensors")
        ckpt.load_state_into(self.ema.model, state["ema"], where / "ema.safetensors")
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except (ValueError, KeyError, RuntimeError) as exc:
            raise DSSPError(
                f"{where / 'optimizer.safetensors'} does not fit this model ({exc}); start a new run"
            ) from None
        try:
            self.step = int(state["trainer_state"]["step"])
            self.ema.step = int(state["trainer_state"]["ema_step"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{where / 'trainer_state.json'} lacks the step ({exc!r}); start a new run") from None
        if self.step > self.config.train.steps:
            raise ConfigError(
                f"train.steps={self.config.train.steps} is below the checkpoint's step {self.step}; "
                "continue with a larger --steps"
            )
        self.lr_schedule.last_epoch = self.step
        for group, factor in zip(self.optimizer.param_groups, self.lr_schedule.lr_lambdas):
            group["lr"] = group["initial_lr"] * factor(self.step)
        self.generator.set_state(state["rng"]["generator"])
        torch.set_rng_state(state["rng"]["torch"])
