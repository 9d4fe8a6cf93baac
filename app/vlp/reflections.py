"""First-bounce diffuse reflections off the room's walls, floor and ceiling.

Each surface element ``dA`` at ``q`` (inward normal ``n_q``, reflectance ``rho``) is lit by
LED ``i`` and re-emits as a Lambertian source (Barry et al. 1993; Komine and Nakagawa 2004):

.. math::

    dh = \\frac{m+1}{2 \\pi d_1^2} \\cos^m\\alpha_1 \\cos\\beta_1\\, dA\\;
         \\rho\\, \\frac{1}{\\pi d_2^2} \\cos\\beta_2\\, A\\, G_f\\, G_c \\cos\\phi_2,

zero outside the receiver's field of view or behind a surface. The integral over each
rectangle is a tensor Gauss-Legendre rule on a graded mesh: cells no larger than
``element_size_m`` and, near the receiver's (or an LED's) foot point on that plane, no larger
than :data:`GRADING` times the distance to that point, down to a floor. The receiver-side
kernel varies on the scale of the receiver's distance ``a`` to the plane (it integrates to a
configuration factor concentrated within a few ``a`` of the foot point), so a uniform mesh is
not converged near a wall while the graded one is; ``docs/explanation/reflections.md`` says why
the defaults are what they are and ``docs/results/reflections.md`` shows the measured
convergence.
"""

from __future__ import annotations

from ._diffuse import diffuse_gains, surface_flux_fractions, view_factors
from ._diffuse_quadrature import (
    DEFAULT_ELEMENT_SIZE_M,
    GRADING,
    SURFACES,
    Surface,
    room_surfaces,
)
from ._reflection_table import ReflectionTable

__all__ = [
    "DEFAULT_ELEMENT_SIZE_M",
    "GRADING",
    "SURFACES",
    "ReflectionTable",
    "Surface",
    "diffuse_gains",
    "room_surfaces",
    "surface_flux_fractions",
    "view_factors",
]
