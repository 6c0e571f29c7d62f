"""The machine-readable training log (``log.jsonl``: one JSON object per line), its plot (``loss.png``), and
the figure of a validation chunk the dashboards show (:func:`chunk_figure`).

Each line has ``"kind": "train"`` (step, loss, diffusion, dynamics, lr, steps_per_s, windows_per_s; with the
dynamics loss also dyn_cos, dyn_cos_mean, dyn_cos_prev: the predictor's and two trivial predictors' cosines;
a distilled student logs loss, distill and teacher_mse instead of the diffusion and dynamics losses) or ``"kind":
"val"`` (step, val_diffusion, val_action_mse). Lines are flushed as written, so a
crashed run keeps its log up to the crash.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.files import atomic_write_text


class RunLog:
    """``log.jsonl`` writer. ``resume_step``: continue an existing log from that step.

    On resume the lines of steps after ``resume_step`` (written after the checkpoint the run continues
    from, then lost with the interrupted process) and a torn last line are dropped first (the file is
    rewritten atomically), so the log never repeats a step.
    """

    def __init__(self, path: Path, append: bool = False, resume_step: int | None = None):
        self.path = Path(path)
        if resume_step is not None and self.path.exists():
            kept = [
                line for line, row in _parsed_lines(self.path) if row is not None and row.get("step", 0) <= resume_step
            ]
            atomic_write_text(self.path, "".join(line + "\n" for line in kept))
            append = True
        self._file = open(self.path, "a" if append else "w")

    def write(self, kind: str, **values: Any) -> None:
        self._file.write(json.dumps({"kind": kind, **values}) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _parsed_lines(path: Path) -> list[tuple[str, dict[str, Any] | None]]:
    out = []
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            row = None  # a line torn by a crash mid-write
        out.append((line, row if isinstance(row, dict) else None))
    return out


def read_log(path: Path) -> list[dict[str, Any]]:
    """The log's rows; a line torn by a crash is skipped."""
    return [row for _, row in _parsed_lines(path) if row is not None]


def plot_log(log_path: Path, png_path: Path) -> None:
    """Loss curves: training diffusion and dynamics losses, validation losses, on a log scale."""
    import matplotlib  # deferred: loads matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: loads matplotlib

    rows = read_log(log_path)
    train = [r for r in rows if r["kind"] == "train"]
    val = [r for r in rows if r["kind"] == "val"]
    diagnostics = [r for r in train if "dyn_cos" in r]
    fig, axes = plt.subplots(1, 3 if diagnostics else 2, figsize=(16.5 if diagnostics else 11, 4))
    if train:
        steps = [r["step"] for r in train]
        if "distill" in train[0]:  # a distilled student (dssp-distill)
            axes[0].plot(steps, [r["distill"] for r in train], label="distillation (train)")
            axes[0].plot(steps, [r["teacher_mse"] for r in train], label="K-step chunk vs teacher (train)")
        else:
            axes[0].plot(steps, [r["diffusion"] for r in train], label="diffusion (train)")
            if any(r["dynamics"] for r in train):
                axes[0].plot(steps, [r["dynamics"] for r in train], label="dynamics 1-cos (train)")
    if diagnostics:  # the dynamics predictor against trivial guesses of z_{t+1}: a collapsed z shows here
        steps = [r["step"] for r in diagnostics]
        for key, label in (
            ("dyn_cos", "g_phi(c_t, a_t)"),
            ("dyn_cos_prev", "z_t (persistence)"),
            ("dyn_cos_mean", "episode mean z"),
        ):
            axes[2].plot(steps, [r[key] for r in diagnostics], label=label)
        axes[2].set(xlabel="step", ylabel="cosine to z_{t+1}", title="Dynamics predictor vs trivial predictors")
        axes[2].legend()
    if val:
        steps = [r["step"] for r in val]
        axes[0].plot(steps, [r["val_diffusion"] for r in val], "o-", label="diffusion (val, EMA)")
        axes[1].plot(steps, [r["val_action_mse"] for r in val], "o-", color="C3")
    axes[0].set(xlabel="step", ylabel="loss", yscale="log", title="Training losses")
    axes[0].legend()
    axes[1].set(
        xlabel="step", ylabel="MSE (normalised units)", yscale="log", title="Validation: sampled action chunk error"
    )
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)


@dataclass
class ValChunk:
    """One validation window's chunk: ``steps`` (H,) the episode steps of its actions, ``sampled`` and ``expert``
    (H, A) the EMA model's sampled chunk and the expert's actions in raw units, ``executed`` the [start, stop)
    indices of the actions the robot runs; ``episode`` and ``start`` say which window, ``held_out`` whether the
    episode is a validation one (else a training one, as with ``--no-holdout``)."""

    episode: int
    start: int
    steps: np.ndarray
    sampled: np.ndarray
    expert: np.ndarray
    executed: tuple[int, int]
    held_out: bool


def chunk_figure(chunk: ValChunk, max_dims: int = 14):
    """A matplotlib figure of ``chunk``: one panel per action dimension (the first ``max_dims``), the sampled
    chunk against the expert's actions, the executed actions shaded. Built without pyplot (nothing to close)."""
    from matplotlib.figure import Figure  # deferred: loads matplotlib

    dims = min(chunk.expert.shape[1], max_dims)
    cols = min(dims, 7)
    rows = -(-dims // cols)
    fig = Figure(figsize=(max(2.2 * cols, 5.0), 1.9 * rows + 0.7), dpi=80)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    lo, hi = chunk.steps[chunk.executed[0]], chunk.steps[chunk.executed[1] - 1]
    for d, ax in enumerate(axes):
        if d >= dims:
            ax.set_axis_off()
            continue
        ax.axvspan(lo - 0.5, hi + 0.5, color="0.9")
        ax.plot(chunk.steps, chunk.expert[:, d], "o-", ms=3, color="C0", label="expert")
        ax.plot(chunk.steps, chunk.sampled[:, d], "s--", ms=3, color="C3", label="sampled")
        ax.set_title(f"action[{d}]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7)
    where = "held-out" if chunk.held_out else "training"
    fig.suptitle(
        f"validation chunk: {where} episode {chunk.episode}, window at step {chunk.start}\n"
        "sampled (EMA) vs expert, raw units; executed actions shaded",
        fontsize=9,
    )
    fig.tight_layout()
    return fig
