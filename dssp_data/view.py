"""Pictures of one episode of a dataset (matplotlib, headless), for ``dssp-data view``.

    paths = render_episode("demo.zarr", 3, Path("views"))            # two PNGs
    paths = render_episode("demo.zarr", 3, Path("views"), video=True)  # and an animated GIF

- ``<name>_ep<K>_clouds.png``: the point cloud (P, 3 or 6), metres, at a few steps across the episode
  (columns) from three viewpoints (rows: oblique, top, side), on common axes; coloured by height, or by
  the stored RGB; steps with recorded problems have a red title.
- ``<name>_ep<K>_trajectories.png``: every state channel (solid) and action channel (dashed) over time
  (seconds from the recorded timestamps, else step / control rate); steps with recorded problems are
  shaded red; for a recorded dataset also the age of each stream at each step (ms).
- ``<name>_ep<K>.gif`` (``video``): the oblique view over the whole episode.

``rerun_episode`` shows the same episode in Rerun (``dssp-data view --rerun`` / ``--rerun-save PATH.rrd``), with the
entities of the robot's live views (:mod:`dssp_data.rerun_views`), one tick per step: the cloud, the depth image and
camera pose when the dataset recorded them, the state, the recorded action as the command, the actions of the next
``horizon`` steps as the gripper's ghost path, and the recorded problems as events.

The episode is read through the dataset reader's checked path: a chunk of it that is missing or corrupt
raises DatasetError naming the key and the chunk, and nothing is drawn from zeros that were never recorded.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dssp_core.files import make_dirs
from dssp_core.output_guard import check_not_inside, check_output_files, write_output_file
from dssp_data import attributes
from dssp_data.recording import FLAGS_KEY, can_log_dir, problem_names
from dssp_data.replay_buffer import ReplayBufferReader
from dssp_data.rerun_views import open_views

VIEWS = (("oblique", 25.0, -60.0), ("top", 90.0, -90.0), ("side", 0.0, -90.0))
"""(name, elevation, azimuth) in degrees of each row of the cloud figure."""
MAX_VIDEO_FRAMES = 150


def _pyplot():
    import matplotlib  # deferred: loads matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: loads matplotlib

    return plt


def _channel_names(n: int) -> list[str]:
    if n % 7 == 0 and n // 7 in (1, 2):
        arms = ["left ", "right "] if n == 14 else [""]
        return [f"{arm}{'J' + str(j + 1) if j < 6 else 'gripper'}" for arm in arms for j in range(7)]
    return [f"dim {d}" for d in range(n)]


def _times(ep, rate: float | None) -> tuple[np.ndarray, str]:
    if "timestamp" in ep.extras:
        return np.asarray(ep.extras["timestamp"], dtype=np.float64), "time (s)"
    if rate:
        return np.arange(ep.n_steps) / rate, "time (s)"
    return np.arange(ep.n_steps, dtype=np.float64), "step"


def _colors(cloud: np.ndarray, zlim: tuple[float, float]):
    if cloud.shape[1] >= 6:
        rgb = cloud[:, 3:6]
        if rgb.max() > 1.0:  # MetaWorld stores 0..255
            rgb = rgb / 255.0
        return np.clip(rgb, 0.0, 1.0)
    import matplotlib  # deferred: loads matplotlib

    z = (cloud[:, 2] - zlim[0]) / max(zlim[1] - zlim[0], 1e-9)
    return matplotlib.colormaps["viridis"](np.clip(z, 0, 1))


def _limits(clouds: np.ndarray) -> list[tuple[float, float]]:
    xyz = clouds[..., :3].reshape(-1, 3)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if xyz.size == 0:
        return [(-1.0, 1.0)] * 3
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3) * 1.05
    return [(float(c - half), float(c + half)) for c in centre]


def _draw_cloud(ax, cloud: np.ndarray, limits, elev: float, azim: float) -> None:
    ax.scatter(cloud[:, 0], cloud[:, 1], cloud[:, 2], s=2, c=_colors(cloud, limits[2]), depthshade=False, linewidths=0)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_zlim(*limits[2])
    ax.view_init(elev=elev, azim=azim)
    ax.set_box_aspect((1, 1, 1))
    ax.tick_params(labelsize=5, pad=0)
    facing = {90.0: "z", 0.0: "y"}.get(elev) if azim == -90.0 else None  # the axis pointing at the viewer
    if facing is not None:
        ax.set_proj_type("ortho")
    for axis, setter in (("x", ax.set_xlabel), ("y", ax.set_ylabel), ("z", ax.set_zlabel)):
        if axis == facing:
            getattr(ax, f"set_{axis}ticks")([])
        else:
            setter(f"{axis} (m)", fontsize=6, labelpad=-8)


def _problem_spans(flags: np.ndarray | None, t: np.ndarray) -> list[tuple[float, float]]:
    if flags is None or not np.any(flags):
        return []
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    spans, start = [], None
    for i, bad in enumerate(np.asarray(flags) != 0):
        if bad and start is None:
            start = i
        if not bad and start is not None:
            spans.append((t[start] - dt / 2, t[i - 1] + dt / 2))
            start = None
    if start is not None:
        spans.append((t[start] - dt / 2, t[-1] + dt / 2))
    return spans


def picture_paths(path: str | os.PathLike, episode: int, out_dir: str | os.PathLike, video: bool = False) -> list[Path]:
    """The files :func:`render_episode` writes: ``<name>_ep<K>_clouds.png``, ``_trajectories.png`` (and ``.gif``)."""
    stem = f"{Path(path).name.removesuffix('.zarr') or 'dataset'}_ep{episode}"
    out_dir = Path(out_dir)
    names = [f"{stem}_clouds.png", f"{stem}_trajectories.png"] + ([f"{stem}.gif"] if video else [])
    return [out_dir / n for n in names]


def render_episode(
    path: str | os.PathLike,
    episode: int,
    out_dir: str | os.PathLike,
    *,
    columns: int = 5,
    video: bool = False,
    force: bool = False,
) -> list[Path]:
    """Write the pictures of episode ``episode`` of dataset ``path`` into ``out_dir``; returns their paths.

    Only the files of :func:`picture_paths` are written (atomically); one that exists is replaced only
    with ``force`` — checked for all of them before anything is read or drawn. ``out_dir`` may not be the
    dataset, lie inside it or in its CAN-log folder, or lie under a file.
    """
    check_not_inside(out_dir, [path, can_log_dir(path)], flag="--out", contains=False)
    check_output_files(picture_paths(path, episode, out_dir, video), force=force, flag="--out")
    plt = _pyplot()
    path, out_dir = Path(path), Path(out_dir)
    reader = ReplayBufferReader(path, allow_incomplete_tail=True)
    ep = reader.episode(episode, extras=[k for k in reader.extra_keys if k != "depth"], check_finite=False)
    t, t_label = _times(ep, reader.control_rate_hz)
    flags = ep.extras.get(FLAGS_KEY)
    name = path.name.removesuffix(".zarr") or "dataset"
    stem = f"{name}_ep{episode}"
    make_dirs(out_dir, flag="--out")
    written = []

    # ---- clouds: columns = steps across the episode, rows = viewpoints
    n_cols = max(1, min(columns, ep.n_steps))
    steps = np.unique(np.linspace(0, ep.n_steps - 1, n_cols).round().astype(int))
    limits = _limits(ep.point_cloud[steps])
    fig = plt.figure(figsize=(2.6 * len(steps), 2.6 * len(VIEWS) + 0.4))
    for col, s in enumerate(steps):
        problems = problem_names(flags[s]) if flags is not None else []
        for row, (view, elev, azim) in enumerate(VIEWS):
            ax = fig.add_subplot(len(VIEWS), len(steps), row * len(steps) + col + 1, projection="3d")
            _draw_cloud(ax, ep.point_cloud[s], limits, elev, azim)
            if row == 0:
                title = f"step {s}  t = {t[s]:.2f} s" if t_label.startswith("time") else f"step {s}"
                if problems:
                    title += "\n" + ", ".join(problems)
                ax.set_title(title, fontsize=8, color="red" if problems else "black")
            if col == 0:
                ax.text2D(-0.12, 0.5, view, transform=ax.transAxes, rotation=90, va="center", fontsize=9)
    fig.suptitle(
        f"{path.name}  episode {episode}: point clouds ({ep.point_cloud.shape[1]} points, metres)", fontsize=10
    )
    fig.subplots_adjust(left=0.03, right=0.99, bottom=0.01, top=0.9, wspace=0.05, hspace=0.08)
    clouds_png = out_dir / f"{stem}_clouds.png"
    write_output_file(clouds_png, lambda tmp: fig.savefig(tmp, format="png", dpi=110), force=force, flag="--out")
    plt.close(fig)
    written.append(clouds_png)

    # ---- trajectories: one panel per channel, state solid and action dashed; stream ages below
    dims = max(ep.state.shape[1], ep.action.shape[1])
    names = _channel_names(dims)
    has_ages = all(k in ep.extras for k in ("timestamp", "camera_timestamp", "state_timestamp", "action_timestamp"))
    n_cols = 2 if dims > 7 else 1
    n_rows = int(np.ceil(dims / n_cols)) + (1 if has_ages else 0)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(7 * n_cols, 1.6 * n_rows + 0.6), sharex=True, squeeze=False)
    spans = _problem_spans(flags, t)
    for d in range(dims):
        ax = axes[d % int(np.ceil(dims / n_cols)), d // int(np.ceil(dims / n_cols))]
        if d < ep.state.shape[1]:
            ax.plot(t, ep.state[:, d], lw=1.2, label="state")
        if d < ep.action.shape[1]:
            ax.plot(t, ep.action[:, d], lw=1.0, ls="--", label="action")
        for a, b in spans:
            ax.axvspan(a, b, color="red", alpha=0.15, lw=0)
        ax.set_ylabel(names[d], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    for d in range(dims, (n_rows - (1 if has_ages else 0)) * n_cols):
        axes[d % int(np.ceil(dims / n_cols)), d // int(np.ceil(dims / n_cols))].set_visible(False)
    if has_ages:
        for col in range(n_cols):
            ax = axes[-1, col]
            if col > 0:
                ax.set_visible(False)
                continue
            now = ep.extras["timestamp"]
            for key, label in (
                ("camera_timestamp", "camera"),
                ("state_timestamp", "follower state"),
                ("action_timestamp", "leader command"),
            ):
                ax.plot(t, (now - ep.extras[key]) * 1e3, lw=1.0, label=label)
            for a, b in spans:
                ax.axvspan(a, b, color="red", alpha=0.15, lw=0)
            ax.set_ylabel("stream age (ms)", fontsize=8)
            ax.legend(fontsize=7, loc="upper right")
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    for col in range(n_cols):
        axes[-1, col].set_xlabel(t_label, fontsize=8)
    legend = (
        ""
        if not spans
        else "\nred: steps with " + ", ".join(sorted({n for f in np.unique(flags) for n in problem_names(f)}))
    )
    fig.suptitle(f"{path.name}  episode {episode}: state (solid) and action (dashed){legend}", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.95 if spans else 0.97))
    traj_png = out_dir / f"{stem}_trajectories.png"
    write_output_file(traj_png, lambda tmp: fig.savefig(tmp, format="png", dpi=110), force=force, flag="--out")
    plt.close(fig)
    written.append(traj_png)

    if video:
        written.append(_write_gif(plt, ep, t, flags, out_dir / f"{stem}.gif", f"{path.name} episode {episode}", force))
    return written


def _write_gif(plt, ep, t: np.ndarray, flags, target: Path, title: str, force: bool) -> Path:
    from matplotlib.animation import FuncAnimation, PillowWriter  # deferred: loads matplotlib

    steps = np.unique(np.linspace(0, ep.n_steps - 1, min(ep.n_steps, MAX_VIDEO_FRAMES)).round().astype(int))
    limits = _limits(ep.point_cloud)
    fig = plt.figure(figsize=(4.5, 4.5))
    ax = fig.add_subplot(projection="3d")

    def draw(k):
        s = steps[k]
        ax.cla()
        _draw_cloud(ax, ep.point_cloud[s], limits, VIEWS[0][1], VIEWS[0][2])
        problems = problem_names(flags[s]) if flags is not None else []
        ax.set_title(
            f"{title}\nstep {s}  t = {t[s]:.2f}" + (f"  {', '.join(problems)}" if problems else ""),
            fontsize=8,
            color="red" if problems else "black",
        )
        return ()

    period = float(np.median(np.diff(t[steps]))) if len(steps) > 1 else 0.1
    animation = FuncAnimation(fig, draw, frames=len(steps), blit=False)
    writer = PillowWriter(fps=max(1.0, min(30.0, 1.0 / max(period, 1e-3))))
    write_output_file(
        target, lambda tmp: animation.save(tmp, writer=writer), force=force, flag="--out", suffix=".tmp.gif"
    )
    plt.close(fig)
    return target


def rerun_episode(
    path: str | os.PathLike, episode: int, connect: str | None, save: Path | None, horizon: int = 16
) -> str:
    """Log episode ``episode`` of dataset ``path`` to Rerun (``connect``: "spawn" or a viewer's URL; ``save``: a new
    .rrd file); returns the views' closing line — every step is logged (the queue waits, nothing is dropped)."""

    path = Path(path)
    reader = ReplayBufferReader(path, allow_incomplete_tail=True)
    ep = reader.episode(episode, check_finite=False)
    intrinsics, to_base = (
        attributes.camera_intrinsics(reader.attrs, path),
        attributes.camera_to_base(reader.attrs, path),
    )
    unit = attributes.depth_unit(reader.attrs, path)
    depth, flags = ep.extras.get("depth"), ep.extras.get(FLAGS_KEY)
    views = open_views("dssp-data view", connect, save)
    with views:
        if intrinsics is not None and to_base is not None:
            views.camera(intrinsics, np.asarray(to_base, np.float64))
        views.text(0, "episode", f"{path.name} episode {episode}: {ep.n_steps} steps")
        for t in range(ep.n_steps):
            views.tick(
                t,
                wait=True,
                cloud=ep.point_cloud[t],
                state=ep.state[t],
                command=ep.action[t],
                chunk=ep.action[t : t + horizon],
                depth=depth[t] if depth is not None else None,
                depth_unit=unit,
                events=problem_names(flags[t]) if flags is not None else (),
            )
    return views.close_line("steps")  # closed already: the counts
