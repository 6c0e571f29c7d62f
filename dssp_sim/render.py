"""Renders of a MuJoCo camera from any thread: :class:`CameraRenders` starts, on first use, one
:class:`RenderThread` per kind of image (depth, colour), each owning its renderer and GL context, and stops them on
``close()`` or when the object that owns it is collected. The sim's envs and the calibration twin render through it.

    renders = CameraRenders(env, model, (H, W), camera_id)
    metres = renders.render(data)               # (H, W) float32 depth along the optical axis
    rgb = renders.render(data, depth=False)      # (H, W, 3) uint8
    renders.close()                              # rendering again starts new threads
"""

from __future__ import annotations

import os
import queue
import threading
import weakref

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402


class CameraRenders:
    """The renders of camera ``camera_id`` of ``model`` at ``size`` (H, W) pixels: a :class:`RenderThread` per kind,
    started by the first render of that kind, stopped by :meth:`close` or when ``owner`` (the env holding this) is
    collected. The caller keeps ``data`` still while a render reads it (the envs hold their lock)."""

    def __init__(self, owner: object, model: mujoco.MjModel, size: tuple[int, int], camera_id: int) -> None:
        self._model, self._size, self._camera_id = model, (int(size[0]), int(size[1])), int(camera_id)
        self._threads: dict[bool, RenderThread] = {}
        self._lock = threading.Lock()
        weakref.finalize(owner, _stop, self._threads, self._lock)

    def render(self, data: mujoco.MjData, depth: bool = True) -> np.ndarray:
        """(H, W) float32 metres along the optical axis (0 where nothing is hit), or with ``depth=False`` (H, W, 3)
        uint8 RGB."""
        with self._lock:
            thread = self._threads.get(depth)
            if thread is None:
                thread = self._threads[depth] = RenderThread(self._model, self._size, self._camera_id, depth)
        return thread.render(data)

    def close(self) -> None:
        """Stop the render threads and free their GL contexts (rendering again starts new ones)."""
        _stop(self._threads, self._lock)


def _stop(threads: dict[bool, RenderThread], lock: threading.Lock) -> None:
    with lock:
        stopping = list(threads.values())
        threads.clear()
    for thread in stopping:
        thread.close()


class RenderThread:
    """One thread that owns a MuJoCo depth renderer and its GL context (a GL context is bound to the
    thread that made it current), so a render works from any thread: a capture thread, a test,
    the main loop. ``render(data)`` -> (H, W) float32 metric depth (metres along the optical axis); with
    ``depth=False`` the colour image instead, (H, W, 3) uint8 RGB."""

    def __init__(self, model: mujoco.MjModel, size: tuple[int, int], camera_id: int, depth: bool = True) -> None:
        self._model, self._size, self._camera_id, self._depth = model, size, camera_id, depth
        self._requests: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="dssp-sim-render", daemon=True)
        self._thread.start()

    def render(self, data: mujoco.MjData) -> np.ndarray:
        reply: queue.Queue = queue.Queue(maxsize=1)
        self._requests.put((data, reply))
        ok, value = reply.get()
        if not ok:
            raise value
        return value

    def close(self) -> None:
        if self._thread.is_alive():
            self._requests.put(None)
            if threading.current_thread() is not self._thread:
                self._thread.join()

    def _run(self) -> None:
        renderer = None
        try:
            while True:
                item = self._requests.get()
                if item is None:
                    return
                data, reply = item
                try:
                    if renderer is None:
                        renderer = mujoco.Renderer(self._model, *self._size)
                        if self._depth:
                            renderer.enable_depth_rendering()
                    renderer.update_scene(data, camera=self._camera_id)
                    reply.put((True, renderer.render()))
                except Exception as e:  # handed to the caller
                    reply.put((False, e))
        finally:
            if renderer is not None:
                renderer.close()
