"""Compiled Levenberg-Marquardt: :func:`.gridless.lm.levenberg_marquardt` (its NumPy code is
the reference and documents the loop) for any model registered here, and the Cholesky solves
it and the covariances use. Private: callers validate.

A model is a ``NamedTuple`` class of its arguments and two compiled functions of it,
``evaluate(model, theta) -> (cost, point)`` and ``normal_equations(model, theta, point) ->
(J^T J, J^T r)``, with the Cholesky solve of its damped normal equations
(:func:`register_model`). :func:`lm_kernel` finds them by the class of the model it is given,
when it is compiled: numba compiles the loop once per model, with the model's functions called
directly, as if written in the loop. (Passing the functions themselves would do the same, but
a compiled caller that passes one cannot be cached on disk.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numba.extending import overload

from ...._kernels import compiled, compiled_inline
from ....typing import FloatArray
from ..lm import (
    DAMPING_DOWN,
    DAMPING_SINGULAR,
    DAMPING_UP,
    DIAGONAL_FLOOR,
    MIN_DAMPING,
    LMSettings,
)

__all__ = [
    "cholesky_solve",
    "cholesky_substitution",
    "lapack_cholesky_solve",
    "lm_kernel",
    "register_model",
]

Solve = Callable[[FloatArray, FloatArray], tuple[FloatArray, bool]]
# Each model class's (evaluate, normal_equations, solve).
_MODELS: dict[
    type,
    tuple[Callable[..., tuple[float, Any]], Callable[..., tuple[FloatArray, FloatArray]], Solve],
] = {}


def register_model(
    model: type,
    evaluate: Callable[..., tuple[float, Any]],
    normal_equations: Callable[..., tuple[FloatArray, FloatArray]],
    solve: Solve | None = None,
) -> None:
    """Let :func:`lm_kernel` fit instances of ``model`` (a ``NamedTuple`` class) with the
    compiled ``evaluate`` and ``normal_equations``, its damped normal equations solved by
    ``solve`` (:func:`cholesky_solve` when None)."""
    _MODELS[model] = (evaluate, normal_equations, cholesky_solve if solve is None else solve)


def _evaluate(model: Any, theta: FloatArray) -> tuple[float, Any]:
    """The model's ``evaluate`` (compiled code only)."""
    raise NotImplementedError


def _normal_equations(model: Any, theta: FloatArray, point: Any) -> tuple[FloatArray, FloatArray]:
    """The model's ``normal_equations`` (compiled code only)."""
    raise NotImplementedError


def _solve(model: Any, matrix: FloatArray, rhs: FloatArray) -> tuple[FloatArray, bool]:
    """The model's ``solve`` (compiled code only)."""
    raise NotImplementedError


# Typing functions: numba types in, the implementation out (its parameters, annotations
# included, must be the typing function's). Inlined into the loop, with each model's
# evaluate and normal equations (compiled_inline): as separate calls they cost the power
# model's K = 8 fits about 1 us of 19 an iteration (measured; the arithmetic is the same).
@overload(_evaluate, inline="always")
def _evaluate_of(model: Any, _theta: Any) -> Callable[..., tuple[float, Any]]:
    evaluate = _MODELS[model.instance_class][0]

    def implementation(model: Any, _theta: Any) -> tuple[float, Any]:
        return evaluate(model, _theta)

    return implementation


@overload(_normal_equations, inline="always")
def _normal_equations_of(
    model: Any, _theta: Any, _point: Any
) -> Callable[..., tuple[FloatArray, FloatArray]]:
    normal_equations = _MODELS[model.instance_class][1]

    def implementation(model: Any, _theta: Any, _point: Any) -> tuple[FloatArray, FloatArray]:
        return normal_equations(model, _theta, _point)

    return implementation


@overload(_solve, inline="always")
def _solve_of(_model: Any, _matrix: Any, _rhs: Any) -> Callable[..., tuple[FloatArray, bool]]:
    solve = _MODELS[_model.instance_class][2]

    def implementation(_model: Any, _matrix: Any, _rhs: Any) -> tuple[FloatArray, bool]:
        return solve(_matrix, _rhs)

    return implementation


@compiled
def lm_kernel(
    model: tuple[Any, ...],
    theta0: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float, int, Any]:
    """:func:`levenberg_marquardt` of a registered ``model``: theta, cost and point at the
    last accepted point, and the iterations begun."""
    theta = theta0.copy()
    cost, point = _evaluate(model, theta)
    n = theta.shape[0]
    n_positions = settings.n_positions
    damping = settings.damping
    used = 0
    converged = False
    # The damped normal matrix and the diagonal scaling, refilled by every trial and
    # iteration (not allocated anew).
    damped = np.empty((n, n))
    scaling = np.empty(n)
    while used < settings.max_iter and not converged:
        used += 1
        normal, gradient = _normal_equations(model, theta, point)
        for i in range(n):
            scaling[i] = max(normal[i, i], DIAGONAL_FLOOR)
        found = False
        for _ in range(settings.max_rejections):
            damped[:, :] = normal
            for i in range(n):
                damped[i, i] += damping * scaling[i]
            step, ok = _solve(model, damped, gradient)
            if not ok:
                damping *= DAMPING_SINGULAR
                continue
            largest = 0.0
            for i in range(n_positions):
                largest = max(largest, abs(step[i]))
            small = largest < settings.step_tol
            if settings.before_trial:
                predicted = 0.0
                for i in range(n):
                    curvature = 0.0
                    for j in range(n):
                        curvature += normal[i, j] * step[j]
                    predicted += step[i] * (2.0 * gradient[i] - curvature)
                converged = small or predicted < settings.cost_tol * cost
            trial = _clipped_sum(theta, step, lower, upper)
            trial_cost, trial_point = _evaluate(model, trial)
            if trial_cost < cost:
                converged = converged or small or (cost - trial_cost) < settings.cost_tol * cost
                theta, cost, point = trial, trial_cost, trial_point
                damping = max(damping / DAMPING_DOWN, MIN_DAMPING)
                found = True
                break
            if converged:
                found = True
                break
            damping *= DAMPING_UP
        if not found:
            converged = True  # no decrease found along any damping: a local minimum
    return theta, cost, used, point


@compiled_inline
def _clipped_sum(
    theta: FloatArray, step: FloatArray, lower: FloatArray, upper: FloatArray
) -> FloatArray:
    """``np.minimum(np.maximum(theta + step, lower), upper)`` in one pass, without its two
    temporary arrays (a trial's clip, two or three a Levenberg-Marquardt iteration): the
    same numbers, a NaN kept as those ufuncs keep it."""
    trial = np.empty(theta.shape[0])
    for i in range(theta.shape[0]):
        value = theta[i] + step[i]
        if value < lower[i]:
            value = lower[i]
        if value > upper[i]:
            value = upper[i]
        trial[i] = value
    return trial


@compiled
def cholesky_solve(matrix: FloatArray, rhs: FloatArray) -> tuple[FloatArray, bool]:
    """Solve ``matrix x = rhs`` for a symmetric positive definite matrix (LAPACK's posv
    fails, and so does this, when a pivot is not positive)."""
    n = rhs.shape[0]
    # Only the lower triangle is written and read (the substitution reads no other).
    factor = np.empty((n, n))
    for j in range(n):
        total = matrix[j, j]
        for p in range(j):
            total -= factor[j, p] * factor[j, p]
        if not total > 0.0:
            return rhs.copy(), False
        pivot = math.sqrt(total)
        factor[j, j] = pivot
        for i in range(j + 1, n):
            total = matrix[i, j]
            for p in range(j):
                total -= factor[i, p] * factor[j, p]
            factor[i, j] = total / pivot
    return cholesky_substitution(factor, rhs), True


@compiled
def lapack_cholesky_solve(matrix: FloatArray, rhs: FloatArray) -> tuple[FloatArray, bool]:
    """:func:`cholesky_solve` with LAPACK's factorisation (its blocked code: faster on the
    joint fit's larger systems, round-off in another order)."""
    try:
        factor = np.linalg.cholesky(matrix)
    except Exception:  # not positive definite
        return rhs.copy(), False
    return cholesky_substitution(factor, rhs), True


@compiled
def cholesky_substitution(factor: FloatArray, rhs: FloatArray) -> FloatArray:
    """``x`` with ``L L^T x = rhs`` for the lower Cholesky factor ``L`` (forward, then back
    substitution)."""
    n = rhs.shape[0]
    x = rhs.copy()
    for i in range(n):
        total = x[i]
        for p in range(i):
            total -= factor[i, p] * x[p]
        x[i] = total / factor[i, i]
    for i in range(n - 1, -1, -1):
        total = x[i]
        for p in range(i + 1, n):
            total -= factor[p, i] * x[p]
        x[i] = total / factor[i, i]
    return x
