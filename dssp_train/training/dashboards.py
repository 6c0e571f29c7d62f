"""Training dashboards (``dssp-train --log tensorboard|wandb``): extra sinks beside ``log.jsonl``.

``log.jsonl`` stays the record of a run; a dashboard receives the same rows as it is written: every number
of a row under the row's own name (``loss``, ``diffusion``, ``lr``, ``val_action_mse``, ...; a flag such as
``on_train_episodes`` is not a number and is left out) at the row's ``step``, plus the validation figures
as images. One interface, :class:`Dashboard`; :func:`open_dashboard` makes the one asked for.

- ``tensorboard``: event files in ``RUN_DIR/tensorboard/`` (``torch.utils.tensorboard.SummaryWriter``). A
  resumed run appends to the same folder; events after the checkpoint it continues from (written by the
  interrupted process, and dropped from ``log.jsonl`` too) are purged from the display.
- ``wandb``: a W&B run in ``RUN_DIR/wandb/``, offline unless ``WANDB_MODE`` says otherwise; project
  ``dssp``, named after the run directory, the run's config as its config. Its id is kept in
  ``RUN_DIR/wandb/run_id``, and a resumed run opens the same id with ``resume="allow"``. The step is logged
  as the ``step`` metric, the x axis of every chart.

Both packages are optional (the ``viz`` extra); :func:`check_dashboard` refuses a dashboard whose package is
missing, with one line saying what to install, before anything is trained.
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from dssp_core.errors import ConfigError, DSSPError
from dssp_core.files import atomic_write_text

DASHBOARDS = ("tensorboard", "wandb", "none")
"""The values of ``--log``; each but ``none`` is also the package it imports."""
INSTALL_HINT = 'pip install -e ".[viz]"'
TENSORBOARD_DIR = "tensorboard"
WANDB_DIR = "wandb"
WANDB_ID_FILE = "run_id"  # in RUN_DIR/wandb/
WANDB_PROJECT = "dssp"


class Dashboard(Protocol):
    """Where a run's scalars and figures go besides ``log.jsonl``."""

    def log_scalars(self, step: int, values: Mapping[str, Any]) -> None:
        """The numbers of ``values`` (a ``log.jsonl`` row; other entries are left out) at ``step``."""

    def log_figure(self, step: int, name: str, fig: Any) -> None:
        """The matplotlib figure ``fig`` as an image called ``name`` at ``step`` (the caller keeps the figure)."""

    def close(self, failed: bool = False) -> None:
        """Write out what is pending and let go of the files; ``failed``: the run stopped on an error."""


def check_dashboard(name: str, flag: str = "--log") -> None:
    """Refuse an unknown dashboard ``name`` or one whose package is not installed (:class:`ConfigError`, one line
    naming ``flag``). Imports the package, so that a broken install fails here rather than during training."""
    if name not in DASHBOARDS:
        raise ConfigError(f"{flag} {name}: choose one of {', '.join(DASHBOARDS)}")
    if name == "none":
        return
    try:
        importlib.import_module(name)
    except ImportError:
        raise ConfigError(f"{flag} {name} needs the {name} package: {INSTALL_HINT}") from None


def open_dashboard(name: str, run_dir: Path, config: Mapping[str, Any], resume_step: int | None = None) -> Dashboard:
    """The dashboard ``name`` (one of :data:`DASHBOARDS`) of the run in ``run_dir``.

    ``config``: the run's config as a dict (W&B records it). ``resume_step``: the checkpoint's step when the
    run is continued (None for a new run).
    """
    check_dashboard(name)
    if name == "tensorboard":
        return TensorBoardDashboard(Path(run_dir) / TENSORBOARD_DIR, resume_step)
    if name == "wandb":
        return WandbDashboard(Path(run_dir), config, resumed=resume_step is not None)
    return NoDashboard()


def scalars_of(values: Mapping[str, Any]) -> dict[str, float]:
    """The finite real numbers of a ``log.jsonl`` row, by name, without ``step`` (bools and the rest left out)."""
    return {
        key: float(value)
        for key, value in values.items()
        if key != "step" and isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    }


def figure_image(fig: Any) -> np.ndarray:
    """The matplotlib figure ``fig`` rendered as an RGB image, (height, width, 3) uint8."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # deferred: loads matplotlib

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.ascontiguousarray(np.asarray(canvas.buffer_rgba())[..., :3])


class NoDashboard:
    """``--log none``: nothing beyond ``log.jsonl``."""

    def log_scalars(self, step: int, values: Mapping[str, Any]) -> None:
        pass

    def log_figure(self, step: int, name: str, fig: Any) -> None:
        pass

    def close(self, failed: bool = False) -> None:
        pass


class TensorBoardDashboard:
    """Event files in ``log_dir``; ``resume_step``: events after it, from an interrupted process, are purged."""

    def __init__(self, log_dir: Path, resume_step: int | None = None):
        from torch.utils.tensorboard import SummaryWriter  # deferred: loads tensorboard, termios, torch, …

        self.log_dir = Path(log_dir)
        self.writer = SummaryWriter(str(self.log_dir), purge_step=None if resume_step is None else resume_step + 1)

    def log_scalars(self, step: int, values: Mapping[str, Any]) -> None:
        for key, value in scalars_of(values).items():
            self.writer.add_scalar(key, value, step)
        self.writer.flush()

    def log_figure(self, step: int, name: str, fig: Any) -> None:
        self.writer.add_image(name, figure_image(fig), step, dataformats="HWC")
        self.writer.flush()

    def close(self, failed: bool = False) -> None:
        self.writer.close()


class WandbDashboard:
    """A W&B run in ``run_dir/wandb`` (offline unless ``WANDB_MODE`` is set), the same id on every resume.

    ``config``: the run's config. ``resumed``: the run is continued; its saved id is reused (a run whose id
    was not saved, e.g. one that logged to W&B for the first time at this resume, gets a new one).
    """

    def __init__(self, run_dir: Path, config: Mapping[str, Any], resumed: bool = False):
        import wandb  # deferred: loads termios, wandb

        self.wandb = wandb
        run_dir = Path(run_dir)
        folder = run_dir / WANDB_DIR
        folder.mkdir(parents=True, exist_ok=True)
        id_file = folder / WANDB_ID_FILE
        run_id = id_file.read_text().strip() if resumed and id_file.is_file() else None
        mode = os.environ.get("WANDB_MODE") or "offline"
        try:
            self.run = wandb.init(
                mode=mode,
                dir=str(run_dir),
                project=WANDB_PROJECT,
                name=run_dir.resolve().name,
                config=dict(config),
                id=run_id,
                resume="allow" if run_id else None,
                settings=wandb.Settings(console="off"),
            )
        except Exception as exc:  # noqa: BLE001 - wandb's errors (no login online, a bad WANDB_MODE) share no base
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise DSSPError(
                f"--log wandb: W&B could not start the run in {mode} mode ({reason}); "
                "unset WANDB_MODE to log offline, or run wandb login"
            ) from None

        atomic_write_text(id_file, self.run.id + "\n")
        self.run.define_metric("step")
        self.run.define_metric("*", step_metric="step")

    def log_scalars(self, step: int, values: Mapping[str, Any]) -> None:
        self.run.log({**scalars_of(values), "step": step})

    def log_figure(self, step: int, name: str, fig: Any) -> None:
        self.run.log({name: self.wandb.Image(figure_image(fig)), "step": step})

    def close(self, failed: bool = False) -> None:
        self.run.finish(exit_code=1 if failed else 0)
