"""The plug-in whitenings a thread computed last, by the values of the state they came from.

A solve whitens the same state more than once (the escape test, the nuisance stage and the
covariance all start from the polished fit; a restart often regrows states it had before),
and each whitening costs an eigendecomposition (about a fifth of a K = 1 solve). The
whitening is a function of the state's values alone (positions, heights, weights, gains,
scale, noise) and of the kernels in use, so a whitening found under the same values is the
one that would be computed: the answers do not change. Per thread (a solver serves many),
bounded in count and kept only for rooms of a few dozen LEDs. Private.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable

from ..._kernels import kernel_mode
from .state import FitState
from .whitening import Whitening

__all__ = ["MAX_KEPT_VALUES", "WhiteningMemo", "state_key"]

# Whitenings kept per thread; a solve needs a few dozen at most (K = 8 with restarts).
_CAPACITY = 64
# Only whitenings of at most this many values are kept (a 16-LED correlation has 136; a
# 1024-LED one would hold an 8 MB rotation and 4 MB of weights each: computed, not kept).
MAX_KEPT_VALUES = 4096
# The key's two scalars (noise, scale), as float64 bytes.
_SCALARS = struct.Struct("dd")


def state_key(state: FitState) -> bytes:
    """The state's values (positions, heights, weights, gains, scale, noise) as one key:
    what a whitening, and anything else computed from the state alone, depends on (the
    float64 arrays' bytes in order, then the noise and the scale; a solve asks for it a
    few times per state, so it joins bytes rather than arrays)."""
    return b"".join(
        (
            state.positions.tobytes(),
            state.heights.tobytes(),
            state.weights.tobytes(),
            state.log_gains.tobytes(),
            _SCALARS.pack(state.noise, state.log_scale),
        )
    )


class WhiteningMemo:
    """``get(state, compute)``: ``compute(state)`` once per thread and set of state values."""

    def __init__(self) -> None:
        self._local = threading.local()

    def get(self, state: FitState, compute: Callable[[FitState], Whitening]) -> Whitening:
        """The whitening of ``state``, computed by ``compute`` unless already known."""
        key = (kernel_mode(), state_key(state))
        known: dict[tuple[str, bytes], Whitening] | None = getattr(self._local, "known", None)
        if known is None:
            known = self._local.known = {}
        found = known.get(key)
        if found is None:
            found = compute(state)
            if found.weights.shape[0] <= MAX_KEPT_VALUES:
                if len(known) >= _CAPACITY:
                    known.clear()
                known[key] = found
        return found

    def __reduce__(self) -> tuple[type[WhiteningMemo], tuple[()]]:
        """A copy starts empty (thread-local storage is not copied)."""
        return (WhiteningMemo, ())
