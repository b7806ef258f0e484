"""Model-selection candidates and cross-validation folds fitted on all cores give the same
results as fitted one after the other in this process (``calib.parallel``)."""

from __future__ import annotations

import numpy as np
import pytest

from calib import parallel as parallel_module
from calib.parallel import InlineExecutor, fit_pool
from tests.support.projected import calibrate


def _fingerprint(res) -> dict[str, np.ndarray]:
    """Everything the selection decided and measured: per candidate its fit and its held-out
    errors, then the returned result."""
    sel = res.trust.model_selection
    out = {"chosen": np.array([c.name == sel.chosen.name for c in sel.candidates])}
    for c in sel.candidates:
        out[c.name + " held-out px"] = c.cv.station_errors()
        out[c.name + " folds X"] = np.array([e.hand_eye for e in c.cv.estimates])
        out[c.name + " X"] = c.fit.cell.hand_eye
        out[c.name + " kappa, nu"] = np.array([c.fit.cell.kappa, c.fit.cell.nu])
    out["X"], out["Y"] = res.hand_eye, res.target_pose
    out["sigmas"] = np.concatenate([np.ravel(v) for v in res.trust.uncertainty.sigmas.values()])
    return out


@pytest.mark.parametrize("true_kappa", [1.0, 1.004])
def test_candidates_and_folds_on_two_processes_match_the_serial_path(monkeypatch, true_kappa):
    monkeypatch.setattr(parallel_module, "cores", lambda: 1)
    serial = _fingerprint(calibrate(true_kappa))
    monkeypatch.setattr(parallel_module, "cores", lambda: 2)
    with fit_pool() as pool:
        assert not isinstance(pool, InlineExecutor)  # really the process pool
    parallel = _fingerprint(calibrate(true_kappa))
    assert serial.keys() == parallel.keys()
    for name, value in serial.items():
        np.testing.assert_allclose(parallel[name], value, rtol=1e-9, atol=1e-12, err_msg=name)


def test_a_failing_fit_in_a_worker_reaches_the_caller():
    with fit_pool(2) as pool, pytest.raises(ValueError, match="no fit for 3"):
        pool.submit(_fail, 3).result()


def _fail(x):
    raise ValueError(f"no fit for {x}")
