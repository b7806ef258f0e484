"""The error of using a hand-eye fitted at the stations over the whole workspace box.

An arm's kinematic errors (a joint offset, a link a tenth of a millimetre long) move the true
flange away from its reading by an amount that depends on the configuration. Station i's
reading, corrected by the joint estimate (``calib.joint``: ``E_i = exp(δ_i)`` on the right, in
the tcp frame), implies its own hand-eye, the one that station alone would see through the
readings::

    eye-in-hand:  X_i = E_i X                    eye-to-hand:  X_i = inv(P_i E_i inv(P_i)) X

The estimate is about the mean of the ``X_i`` over the stations; what a user of the result
needs is the mean over the poses the arm will take in the box. The two differ by how the
effective hand-eye changes between where the stations are and the box: nothing the images
of these stations show, and no σ built from them alone (the formal one, the jackknife) sees
it. To first order in the tool position ``p`` the effective hand-eye is ``X(p) = a + G (p -
μ_S)`` (per component; ``μ_S`` the stations' mean position), so the mean over the box is off
the mean over the stations by ``G (μ_B - μ_S)``, ``μ_B`` the box's centre (tool positions
spread evenly over it). The gradient's direction is not known (fitting it to 10-40 stations
extrapolates noise), its size is: a gradient with isotropic second moment ``E[g gᵀ] = τ² I``
per component spreads the ``X_i`` over the stations by ``τ² tr Σ_S`` (``Σ_S`` the stations'
position covariance), which is at most their observed variance ``s²`` (noise adds to it).
So ``τ² <= s² / tr Σ_S`` and the mean square of the shift to the box is at most::

    b² = s² |μ_B - μ_S|² / tr Σ_S

per component: the observed spread of the implied hand-eye, times the distance of the box's
centre from the stations' centroid over the stations' own spread. It vanishes when the
stations are centred on the box, and grows as they cluster in a corner of it. It is added to
the reported σ in quadrature (the estimate's mean square error as an estimate of the box's
hand-eye). It takes no coefficient: ``s``, ``Σ_S`` and ``μ_S`` come from the stations, ``μ_B``
from the box the run was given (``SolverOptions.workspace``); without a box nothing is added.
"""

from __future__ import annotations

import numpy as np

from calib import so3
from calib.geometry import invert

#: Fewer stations than this give no spread to speak of (the term is left out).
MIN_STATIONS = 4


def implied_hand_eyes(T_base_tcp: np.ndarray, corrections: np.ndarray, hand_eye: np.ndarray,
                      setup: str) -> np.ndarray:
    """Each station's own hand-eye (n, 4, 4) through its corrected reading (module docstring);
    ``T_base_tcp`` (n, 4, 4) the readings, ``corrections`` (n, 6) the joint estimate's δ."""
    E = np.tile(np.eye(4), (len(corrections), 1, 1))
    E[:, :3, :3] = np.stack([so3.exp(d[:3]) for d in corrections])
    E[:, :3, 3] = corrections[:, 3:]
    if setup == "eye_in_hand":
        return E @ hand_eye
    return np.stack([invert(P @ e @ invert(P)) for P, e in zip(T_base_tcp, E, strict=True)]) \
        @ hand_eye


def box_shift_sigmas(T_base_tcp: np.ndarray, corrections: np.ndarray, hand_eye: np.ndarray,
                     setup: str, box: tuple[np.ndarray, np.ndarray]
                     ) -> dict[str, np.ndarray]:
    """``b`` per axis (module docstring) as ``hand_eye_rot_rad`` and ``hand_eye_trans_m``
    (3,) each, in the layout of the joint σ (small left rotations, translations in the frame of
    the first index); {} below ``MIN_STATIONS`` or for stations all at one position."""
    n = len(T_base_tcp)
    if n < MIN_STATIONS:
        return {}
    X_i = implied_hand_eyes(T_base_tcp, corrections, hand_eye, setup)
    rot = so3.log(X_i[:, :3, :3] @ hand_eye[:3, :3].T)
    trans = X_i[:, :3, 3] - hand_eye[:3, 3]
    p = T_base_tcp[:, :3, 3]
    spread = float(np.trace(np.cov(p.T)))
    if spread <= 0.0:
        return {}
    centre = (np.asarray(box[0], dtype=float) + np.asarray(box[1], dtype=float)) / 2.0
    ratio = float(np.sum((centre - p.mean(axis=0)) ** 2)) / spread
    return {"hand_eye_rot_rad": np.sqrt(ratio * rot.var(axis=0, ddof=1)),
            "hand_eye_trans_m": np.sqrt(ratio * trans.var(axis=0, ddof=1))}
