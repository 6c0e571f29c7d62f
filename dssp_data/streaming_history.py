"""The streaming history of a DSSP policy: one state machine for PyTorch, ONNX Runtime and TorchScript.

Every backend that runs a policy one control tick at a time keeps the same three things between ticks,
by the same rules:

- the recurrent history state: the zero state at the start of an episode, then what the last step returned;
- ``c_t``, the history context the last step returned (None without a history encoder);
- the last N observation tokens ``z``, oldest first; at the start of an episode the first ``z`` stands in
  for the N - 1 that do not exist yet (as in training, where indices before 0 repeat the first observation).

:class:`StreamingHistory` holds them and knows nothing of the model or of the array library: the backend
passes its history step, its zero state and how to stack tokens (``np.stack(tokens, axis=1)``,
``torch.stack(tokens, dim=1)``)::

    history = StreamingHistory(n_recent=3, step=step, zero_state=zeros, stack=lambda ts: np.stack(ts, axis=1))
    z_t = history.observe(point_cloud, agent_pos)   # step(point_cloud, agent_pos, state) → z_t, c_t, new state
    history.context                                 # c_t (B, d), or None
    history.recent                                  # (B, N, d): z_{t-N+1} .. z_t
    history.reset()                                 # a new episode

A step that raises (a refused observation, a graph error) changes nothing. An observation holding NaN or
infinity must be refused before the step (:func:`check_finite`): the recurrent state would carry it for
the rest of the episode.

Shapes (B batch, P points, C point channels, S state, d width, N = ``n_recent``): observation arrays
(B, ...), e.g. point_cloud (B, P, C) and agent_pos (B, S); z_t, c_t (B, d); recent (B, N, d); the state
is whatever ``step`` and ``zero_state`` use (per history layer conv (B, E, W) and ssm (B, E, n)).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

import numpy as np

from dssp_core.errors import NonFiniteObservation

Array = TypeVar("Array")  # numpy.ndarray or torch.Tensor: the backend's array type
State = Any  # the backend's recurrent state: a dict or list of arrays, a list of (conv, ssm) pairs, or None
Step = Callable[..., tuple]  # (*observation, state) → (z_t (B, d), c_t (B, d) or None, new state)

MAX_LISTED = 4  # non-finite entries named in a refusal


class StreamingHistory(Generic[Array]):
    """The history state, ``c_t`` and the last ``n_recent`` tokens of one episode, updated one tick at a time.

    Args:
        n_recent: N, the number of recent tokens kept (``n_obs_steps``).
        step: ``step(*observation, state) → (z_t (B, d), c_t (B, d) or None, new state)``; ``state`` is
            ``zero_state(B)`` on the first tick of an episode.
        stack: a list of N tokens (B, d) → one array (B, N, d).
        zero_state: the state at the start of an episode for batch B; None passes None to ``step``
            (a step that starts from zeros by itself, as ``HistoryEncoder.step`` does).
    """

    def __init__(
        self,
        n_recent: int,
        step: Step,
        stack: Callable[[Sequence[Array]], Array],
        zero_state: Callable[[int], State] | None = None,
    ):
        if n_recent < 1:
            raise ValueError(f"n_recent must be >= 1, got {n_recent}")
        self.n_recent = n_recent
        self._step = step
        self._stack = stack
        self._zero_state = zero_state
        self.reset()

    def reset(self) -> None:
        """Start a new episode: no state, no context, no tokens; the next tick starts from the zero state."""
        self.state: State = None
        self.context: Array | None = None  # c_t (B, d)
        self.tokens: list[Array] = []  # N tokens (B, d), oldest first; empty before the first tick
        self.batch: int | None = None
        self.steps = 0
        self._recent: Array | None = None

    @property
    def started(self) -> bool:
        """True once a tick of this episode has been observed."""
        return self.steps > 0

    @property
    def recent(self) -> Array | None:
        """The last N tokens stacked, (B, N, d), oldest first; None before the first tick."""
        if self._recent is None and self.tokens:
            self._recent = self._stack(self.tokens)
        return self._recent

    def observe(self, *observation: Array) -> Array:
        """One tick: run the step on ``observation`` (arrays (B, ...)) and the state; returns z_t (B, d).

        Raises ValueError when B differs from the episode's (call :meth:`reset` first); whatever ``step``
        raises propagates. Either way nothing changes.
        """
        batch = int(observation[0].shape[0])
        if self.batch is not None and batch != self.batch:
            raise ValueError(f"batch size {batch} within an episode of batch size {self.batch}; call reset() first")
        state = self.state
        if not self.started and self._zero_state is not None:
            state = self._zero_state(batch)
        z_t, context, new_state = self._step(*observation, state)
        self.state, self.context, self.batch = new_state, context, batch
        self.tokens = [z_t] * self.n_recent if not self.tokens else [*self.tokens[1:], z_t]
        self._recent = None
        self.steps += 1
        return z_t


def check_finite(name: str, values) -> None:
    """Raise :class:`NonFiniteObservation` naming the input ``values`` (any shape) and its first non-finite entries."""
    values = np.asarray(values)
    bad = ~np.isfinite(values)
    if not bad.any():
        return
    where = np.argwhere(bad)
    listed = ", ".join(f"{tuple(int(i) for i in idx)}={values[tuple(idx)]}" for idx in where[:MAX_LISTED])
    more = f" and {len(where) - MAX_LISTED} more" if len(where) > MAX_LISTED else ""
    raise NonFiniteObservation(
        f"{name} {list(values.shape)} has {len(where)} non-finite value(s) at {listed}{more}; "
        "the observation was not used (the history is unchanged)"
    )
