"""The stage runner every study uses: stages are calls of the packages' Python entry points, run side by side
in their own processes with one thread each, resumed after an interruption.

    stages = [Stage("collect_tap", sim_cli.main, ("collect", "--task", "tap", ...)),
              Stage("train_tap_dssp_s0", train.main, (...), after=("collect_tap",),
                    resume=("--data", ..., "--resume"), started="runs/tap_dssp_s0/checkpoint")]
    seconds = Runner(work, workers=2).run(stages)

- A stage is done when its marker ``work/done/NAME.json`` exists; the marker is written (atomically, with the
  stage's seconds and its call) only after the entry point returned 0, so a stage stopped halfway runs
  again. A stage whose ``started`` path exists but is not done runs its ``resume`` call instead (training:
  ``--resume`` from the last checkpoint).
- Up to ``workers`` stages run at once, each a fresh process (multiprocessing's spawn) with ``OMP_NUM_THREADS`` and
  friends at ``threads`` (default 1) before anything imports torch or ONNX Runtime (it is given the entry point by name,
  ``"package.module:function"``, and imports it then), its output in ``work/logs/NAME.log``, run in the work folder
  (relative paths in a call are the work folder's). A stage starts when every stage it comes ``after`` is done;
  ``clean`` paths are removed before it starts (a collection stopped halfway is collected again, not appended to).
- With ``echo``, each running stage's output is shown as it comes, line by line behind ``[NAME]`` (a progress
  bar, a line ended by a carriage return, at most every :data:`PROGRESS_EVERY_S`).
- The first stage that fails stops the others and raises :class:`StageFailed`, one line: its name, its exit code,
  its log's last line and the log's path. Ctrl-C, or SIGTERM (also where a background launch ignores SIGINT), stops every
  running stage too; what finished is kept.
- ``on_done`` (optional) is called with each stage as soon as its marker is written, while the others run: a study
  keeps what the stage made there and then, so a run that is ended outright (the machine gone) loses only the
  stages still running.
"""

from __future__ import annotations

import importlib
import json
import multiprocessing
import os
import re
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
POLL_S = 0.2
PROGRESS_EVERY_S = 15.0


@dataclass(frozen=True)
class Stage:
    """One call of an entry point: a function of ``argv`` returning an exit code, kept as ``"module:function"``."""

    name: str
    entry: str | Callable[[list[str]], int | None]
    argv: tuple[str, ...]
    after: tuple[str, ...] = ()
    resume: tuple[str, ...] | None = None  # the call when ``started`` exists and the stage is not done
    started: str | None = None  # a path (relative to the work folder, or absolute) left by an attempt stopped halfway
    outputs: tuple[str, ...] = field(default=())  # what the stage writes (for the record's copies)
    clean: tuple[
        str, ...
    ] = ()  # paths (in the work folder) an attempt stopped halfway leaves, removed before it runs again

    def __post_init__(self):
        if not self.name or any(c in self.name for c in "/\\ ") or self.name.startswith("."):
            raise ValueError(f"a stage name must be a plain file name, got {self.name!r}")
        if callable(self.entry):
            object.__setattr__(self, "entry", f"{self.entry.__module__}:{self.entry.__name__}")
        if ":" not in self.entry:
            raise ValueError(f"a stage's entry must be 'module:function', got {self.entry!r}")


def _call(entry: str, argv: list[str], log: str, threads: int, cwd: str) -> None:
    """In the child: threads first, output to the log, then the entry point in the work folder; its return value is the
    exit code."""
    os.chdir(cwd)
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    os.environ["PYTHONUNBUFFERED"] = "1"
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    sys.stdout = open(1, "w", buffering=1, closefd=False)
    sys.stderr = open(2, "w", buffering=1, closefd=False)
    module, function = entry.split(":")
    code = getattr(importlib.import_module(module), function)(list(argv))
    sys.stdout.flush()
    sys.stderr.flush()
    sys.exit(int(code or 0))


class StageFailed(DSSPError):
    """A stage's entry point ended with a non-zero exit code (or was killed: ``code`` None)."""

    def __init__(self, stage: str, entry: str, code: int | None, log: Path, last: str):
        self.stage, self.code, self.log, self.last = stage, code, log, last
        super().__init__(
            f"stage {stage} ({entry}) failed with exit code {code}: {last} (log: {log}); run the study again to resume"
        )


class _Echo:
    """Shows what a stage appends to its log, line by line behind ``[NAME] ``; a progress bar (a line ended by
    ``\\r``) at most every PROGRESS_EVERY_S, and its last state when the stage ends."""

    def __init__(self, name: str, log: Path, say: Callable[[str], None], clock: Callable[[], float] = time.monotonic):
        self.name, self.log, self.say, self.clock = name, log, say, clock
        self.offset, self.buffer, self.bar, self.shown = 0, b"", None, -PROGRESS_EVERY_S

    def _show(self, line: str) -> None:
        self.say(f"[{self.name}] {line}")

    def poll(self) -> None:
        try:
            with open(self.log, "rb") as f:
                f.seek(self.offset)
                chunk = f.read()
        except OSError:
            return
        self.offset += len(chunk)
        self.buffer += chunk
        held = b"\r" if self.buffer.endswith(b"\r") else b""  # perhaps the first half of \r\n
        *parts, rest = re.split(rb"(\r\n|\n|\r)", self.buffer[: len(self.buffer) - len(held)])
        self.buffer = rest + held
        for text, end in zip(parts[::2], parts[1::2]):
            line = text.decode("utf-8", "replace").rstrip()
            if end == b"\r":
                self.bar = line
                if line and self.clock() - self.shown >= PROGRESS_EVERY_S:
                    self._show(line)
                    self.bar, self.shown = None, self.clock()
            else:  # a complete line also ends a bar (tqdm closes with its final state)
                self.bar = None
                if line:
                    self._show(line)

    def close(self) -> None:
        self.poll()
        for line in (self.bar, self.buffer.decode("utf-8", "replace").rstrip()):  # a bar's last state, an unended line
            if line:
                self._show(line)
        self.bar, self.buffer = None, b""


class Stopped(KeyboardInterrupt):
    """SIGTERM while stages run: handled as Ctrl-C (every running stage is stopped, the command exits 130)."""


def _raise_stopped(signum, frame):
    raise Stopped(f"signal {signum}")


def _stop_on_sigterm():
    """Make SIGTERM stop the study like Ctrl-C while it runs (by default it would end this process and leave its stages
    running); returns the handler to restore, or None off the main thread (where no handler can be set)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_stopped)


def _restore_sigterm(previous) -> None:
    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


class Runner:
    """Runs a study's stages in ``work`` (``done/``, ``logs/``): see the module docstring."""

    def __init__(
        self, work: Path, workers: int = 1, threads: int = 1, say: Callable[[str], None] = print, echo: bool = False
    ):
        if workers < 1 or threads < 1:
            raise DSSPError(f"workers and threads must be at least 1, got {workers} and {threads}")
        self.work, self.workers, self.threads, self.say, self.echo = Path(work), workers, threads, say, echo
        self.context = multiprocessing.get_context("spawn")

    def marker(self, name: str) -> Path:
        return self.work / "done" / f"{name}.json"

    def done(self, name: str) -> bool:
        return self.marker(name).is_file()

    def seconds(self) -> dict[str, float]:
        """Every done stage's seconds (the compute a study took, resumed and parallel runs included)."""
        folder = self.work / "done"
        return (
            {p.stem: json.loads(p.read_text())["seconds"] for p in sorted(folder.glob("*.json"))}
            if folder.is_dir()
            else {}
        )

    def _path(self, path: str) -> Path:
        return Path(path) if os.path.isabs(path) else self.work / path

    def run(self, stages: Sequence[Stage], on_done: Callable[[Stage], None] | None = None) -> dict[str, float]:
        """Run every stage not done yet, in dependency order (``on_done``: called with each one as it finishes);
        returns {name: seconds} of the stages run now."""
        names = [s.name for s in stages]
        if len(set(names)) != len(names):
            raise DSSPError(f"stage names repeat: {sorted({n for n in names if names.count(n) > 1})}")
        known = set(names)
        for s in stages:
            missing = [a for a in s.after if a not in known and not self.done(a)]
            if missing:
                raise DSSPError(f"stage {s.name} comes after {missing}, which no stage makes")
        (self.work / "logs").mkdir(parents=True, exist_ok=True)
        (self.work / "done").mkdir(parents=True, exist_ok=True)
        pending = [s for s in stages if not self.done(s.name)]
        for s in stages:
            if self.done(s.name):
                self.say(f"  {s.name}: done before")
        running: dict[str, tuple[Stage, multiprocessing.Process, float, list[str]]] = {}
        echoes: dict[str, _Echo] = {}
        ran: dict[str, float] = {}
        previous = _stop_on_sigterm()
        try:
            while pending or running:
                for s in list(pending):
                    if len(running) >= self.workers:
                        break
                    if all(self.done(a) for a in s.after):
                        pending.remove(s)
                        for path in s.clean:
                            self._remove(path)
                        argv = (
                            list(s.resume)
                            if s.resume is not None and s.started and self._path(s.started).exists()
                            else list(s.argv)
                        )
                        log = self.work / "logs" / f"{s.name}.log"
                        proc = self.context.Process(
                            target=_call,
                            args=(s.entry, argv, str(log.resolve()), self.threads, str(self.work.resolve())),
                            name=s.name,
                        )
                        proc.start()
                        running[s.name] = (s, proc, time.perf_counter(), argv)
                        if self.echo:
                            echoes[s.name] = _Echo(s.name, log, self.say)
                        self.say(f"  {s.name}: started{' (resumed)' if argv != list(s.argv) else ''}")
                if not running and pending:
                    blocked = {s.name: [a for a in s.after if not self.done(a)] for s in pending}
                    raise DSSPError(f"stages wait on stages that cannot finish: {blocked}")
                for name, (s, proc, t0, argv) in list(running.items()):
                    if proc.is_alive():
                        if name in echoes:
                            echoes[name].poll()
                        continue
                    proc.join()
                    del running[name]
                    if name in echoes:
                        echoes.pop(name).close()
                    if proc.exitcode != 0:
                        raise self._failure(s, proc.exitcode)
                    seconds = time.perf_counter() - t0
                    atomic_write_text(
                        self.marker(name),
                        json.dumps({"seconds": round(seconds, 1), "entry": s.entry, "argv": argv}, indent=1) + "\n",
                    )
                    ran[name] = seconds
                    self.say(f"  {name}: done in {seconds:.0f} s")
                    if on_done is not None:
                        on_done(s)
                time.sleep(POLL_S)
        finally:
            _restore_sigterm(previous)
            for _, proc, _, _ in running.values():
                if proc.is_alive():
                    proc.terminate()
                    proc.join(timeout=10)
                    if proc.is_alive():
                        proc.kill()
                        proc.join()
        return ran

    def _remove(self, path: str) -> None:
        """Remove what an attempt stopped halfway left at ``path``, which must lie inside the work folder (a link is
        removed, never followed)."""
        target = self.work / path
        if os.path.isabs(path) or ".." in Path(path).parts:
            raise DSSPError(f"a stage may only clean paths inside its work folder, got {path!r}")
        if target.is_symlink() or target.is_file():
            target.unlink()
        elif target.is_dir():
            shutil.rmtree(target)

    def _failure(self, s: Stage, code: int | None) -> StageFailed:
        log = self.work / "logs" / f"{s.name}.log"
        lines = log.read_text(encoding="utf-8", errors="replace").strip().splitlines() if log.is_file() else []
        return StageFailed(s.name, s.entry, code, log, lines[-1] if lines else "(no output)")
