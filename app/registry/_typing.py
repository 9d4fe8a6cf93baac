"""Type aliases of the registry."""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["StoredMatrix"]

StoredMatrix: TypeAlias = NDArray[np.float64] | sp.csr_array
