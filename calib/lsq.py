"""The shape shared by the bundle adjustments: residuals and a sparse Jacobian from one pass.

``scipy.optimize.least_squares`` asks for the residuals and then the Jacobian at the same
point; computing both in one pass and keeping the last one halves the work.
"""

from __future__ import annotations

import numpy as np


class CachedProblem:
    """Base of a least-squares problem whose ``_compute(x)`` returns residuals and blocks.

    ``evaluate`` returns ``(residuals, blocks)`` of the last ``x`` without recomputing them;
    ``residuals`` is the callable to hand to ``least_squares``. The blocks go to
    ``calib.schur.solve_blocks`` (``calib.intrinsics``, ``calib.joint``); ``calib.joint`` also
    builds its sparse Jacobian from them.
    """

    _cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _compute(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals and Jacobian blocks at ``x`` (cached for the last ``x``)."""
        if self._cache is not None and np.array_equal(self._cache[0], x):
            return self._cache[1], self._cache[2]
        r, blocks = self._compute(x)
        self._cache = (x.copy(), r, blocks)
        return r, blocks

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x)[0]
