"""calib.levmar: the dense Levenberg-Marquardt against scipy's least_squares (MINPACK), and the
calibrate command's modules without scipy.optimize."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative

from calib.levmar import inverse_scaled, solve_dense, solve_scaled

T = np.linspace(0.0, 4.0, 40)
Y = 2.5 * np.exp(-1.3 * T) + 0.4 * np.cos(3.0 * T) + 0.01 * np.random.default_rng(5).normal(
    size=T.size)


def _model(p: np.ndarray) -> np.ndarray:
    """Residuals of a damped-exponential-plus-cosine fit, scaled unevenly (40,)."""
    return np.concatenate([(p[0] * np.exp(-p[1] * T) + p[2] * np.cos(p[3] * T) - Y)[:20] * 1e3,
                           (p[0] * np.exp(-p[1] * T) + p[2] * np.cos(p[3] * T) - Y)[20:]])


@pytest.mark.parametrize("start", [[2.0, 1.0, 0.3, 2.9], [3.0, 2.0, 0.1, 3.1]])
def test_dense_minimum_is_least_squares_lm(start):
    """The same minimum as least_squares(method='lm', x_scale='jac') from the same start, its
    cost no higher, and the Jacobian there least_squares' own forward differences."""
    x0 = np.array(start)
    ours = solve_dense(_model, x0)
    ref = least_squares(_model, x0, method="lm", x_scale="jac", jac="2-point")
    assert ours.converged
    assert np.allclose(ours.x, ref.x, rtol=1e-7, atol=1e-9)
    assert ours.cost <= float(ref.fun @ ref.fun) * (1.0 + 1e-12)
    assert np.allclose(ours.residuals, _model(ours.x), rtol=0, atol=0)
    assert np.allclose(ours.jacobian, approx_derivative(_model, ours.x, method="2-point"),
                       rtol=1e-12, atol=1e-12)


def test_dense_reaches_a_distant_minimum_through_damping():
    """A start where Gauss-Newton's first step fails: Marquardt's damping takes over."""
    def rosenbrock(p: np.ndarray) -> np.ndarray:
        return np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])

    sol = solve_dense(rosenbrock, np.array([-1.2, 1.0]), max_nfev=200)
    assert sol.converged and np.allclose(sol.x, [1.0, 1.0], atol=1e-8)


def _uninformed(noise: float) -> tuple[np.ndarray, np.ndarray]:
    """A reduced normal matrix (4, 4) of three globals in mixed units and a fourth that the
    stations explain entirely, so that only rounding noise is left of it (the wrong-setup
    real set of test_evidence, where a parameter has no information): its block of the
    three (3, 3), and the matrix."""
    J = np.random.default_rng(2).normal(size=(12, 3)) * np.array([1e3, 1.0, 1e-3])
    A = J.T @ J
    S = np.zeros((4, 4))
    S[:3, :3] = A
    S[3, :3] = S[:3, 3] = noise * np.array([1e3, 1.0, -1e-3])
    S[3, 3] = -noise ** 2
    return A, S


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("noise", [0.0, 1e-12, 1e-9])
def test_a_parameter_without_information_drops_out_of_the_scaled_inverse(noise):
    """The scaled inverse and solve drop the uninformed global and keep the others' own
    inverse: its diagonal at or below zero is no information, not a scale of 1e-150 that
    overflowed and made the pseudo-inverse drop every other direction instead."""
    A, S = _uninformed(noise)
    S_inv = inverse_scaled(S)
    np.testing.assert_allclose(S_inv[:3, :3], np.linalg.inv(A), rtol=1e-9)
    assert not S_inv[3].any() and not S_inv[:, 3].any()
    b = np.array([1.0, -2.0, 3.0, 4.0])
    np.testing.assert_allclose(solve_scaled(S, b), [*np.linalg.solve(A, b[:3]), 0.0],
                               rtol=1e-9)
    with pytest.raises(np.linalg.LinAlgError):
        inverse_scaled(S, strict=True)


def test_calibrate_loads_no_scipy_optimize():
    """``cellcal calibrate``'s modules (solver and result writer) import no scipy.optimize:
    its linear-programming, global and FFT modules cost 0.2-0.3 CPU s before the solve."""
    code = ("import sys, service.cli.calibrate, calib.calibration, calib.pipeline, "
            "service.results.document; print('scipy.optimize' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
