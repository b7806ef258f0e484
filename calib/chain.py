"""The robot cell as one kinematic loop: setups, the robot chain, and the motions it implies.

Frames and unknowns follow ``docs/conventions.md``. Both setups close the same loop per station
``i``, written once here::

    P_i X C_i = Y          P_i = robot chain pose, C_i = T_cam_target

============  ===============  =====================  =====================
setup         ``P_i``          ``X`` (``hand_eye``)   ``Y`` (``target_pose``)
============  ===============  =====================  =====================
eye-in-hand   T_base_tcp       T_tcp_cam              T_base_target
eye-to-hand   inv(T_base_tcp)  T_base_cam             T_tcp_target
============  ===============  =====================  =====================

Every other form is this loop solved for one of its members: the camera seen from a robot pose
``C = inv(X) inv(P) Y``, the robot pose for a view, the target (board-in-base eye-in-hand) or the
hand-eye closed through one station. Pairs of stations give the motions ``A X = X B`` that the
hand-eye solvers use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib import so3
from calib.geometry import invert, rotation_angle

SETUPS = ("eye_in_hand", "eye_to_hand")
#: Motions rotating less than this have no well-defined screw axis and are skipped.
MIN_MOTION_ROTATION_DEG = 2.0
#: All rotation axes within this angle of each other cannot fix the solution.
MIN_AXIS_SPREAD_DEG = 2.0
#: Largest number of motion pairs formed: all pairs of up to 200 stations, a spread subset
#: beyond (memory and time stay bounded for any station count).
MAX_MOTION_PAIRS = 19_900
#: Reading noise of a UR-class robot: σ of the error's rotation angle (rad) and length (m).
DEFAULT_ROBOT_NOISE_ROT_RAD = float(np.deg2rad(0.05))
DEFAULT_ROBOT_NOISE_TRANS_M = 0.25e-3


@dataclass(frozen=True)
class RobotNoise:
    """Noise of the robot's pose readings, as in Strobl & Hirzinger section IV-A.

    ``rot_rad`` is the σ of the error's rotation *angle* about a random axis and ``trans_m``
    the σ of its translation *length* along a random direction (``calib.geometry.perturb``
    draws it), so each component of the rotation vector (translation) has σ / √3.
    """

    rot_rad: float = DEFAULT_ROBOT_NOISE_ROT_RAD
    trans_m: float = DEFAULT_ROBOT_NOISE_TRANS_M

    def __post_init__(self) -> None:
        if not (self.rot_rad > 0 and self.trans_m > 0):
            raise ValueError("robot noise levels (rotation rad, translation m) must be positive")


def check_setup(setup: str) -> str:
    """Return ``setup`` if it names a setup; raise ``ValueError`` saying the choices if not."""
    if setup not in SETUPS:
        raise ValueError(f"unknown setup '{setup}': choose eye_in_hand or eye_to_hand")
    return setup


def robot_chain(T_base_tcp: np.ndarray, setup: str) -> np.ndarray:
    """The poses that play ``P`` in ``P_i X C_i = Y``: T_base_tcp, or its inverse eye-to-hand.

    The map is its own inverse: ``robot_chain(robot_chain(T, s), s) == T``.
    """
    T_base_tcp = np.asarray(T_base_tcp, dtype=float)
    return T_base_tcp if check_setup(setup) == "eye_in_hand" else invert(T_base_tcp)


def camera_from_chain(P: np.ndarray, hand_eye: np.ndarray, target_pose: np.ndarray
                      ) -> np.ndarray:
    """T_cam_target ``inv(X) inv(P) Y`` from robot chain pose(s) P, (..., 4, 4) -> (..., 4, 4)."""
    return invert(hand_eye) @ invert(P) @ target_pose


def chain_from_camera(T_cam_target: np.ndarray, hand_eye: np.ndarray, target_pose: np.ndarray
                      ) -> np.ndarray:
    """Robot chain pose(s) ``P = Y inv(C) inv(X)`` giving camera pose(s) C, (..., 4, 4)."""
    return target_pose @ invert(T_cam_target) @ invert(hand_eye)


def corrected_readings(T_base_tcp: np.ndarray, robot_map: np.ndarray | None) -> np.ndarray:
    """Robot readings (..., 4, 4) with their translations mapped ``t + S t`` (S = ``robot_map``
    (3, 3), base frame; None: unchanged).

    An industrial arm's positions are often off by a linear map of a fraction of a percent
    (link lengths, joint offsets and base tilt to first order: scale and skew of the workspace)
    while the orientations are right; ``S`` is that map (``calib.joint``, ``robot_map``).
    """
    T_base_tcp = np.asarray(T_base_tcp, dtype=float)
    if robot_map is None:
        return T_base_tcp
    out = T_base_tcp.copy()
    out[..., :3, 3] += T_base_tcp[..., :3, 3] @ np.asarray(robot_map, dtype=float).T
    return out


def camera_from_robot(T_base_tcp: np.ndarray, hand_eye: np.ndarray, target_pose: np.ndarray,
                      setup: str, robot_map: np.ndarray | None = None) -> np.ndarray:
    """T_cam_target seen from robot pose(s) T_base_tcp, shapes (..., 4, 4) -> (..., 4, 4).

    Eye-in-hand ``inv(X) inv(T_base_tcp) Y``, eye-to-hand ``inv(X) T_base_tcp Y``; the
    readings' translations first mapped by ``robot_map`` (:func:`corrected_readings`).
    """
    return camera_from_chain(robot_chain(corrected_readings(T_base_tcp, robot_map), setup),
                             hand_eye, target_pose)


def robot_from_camera(T_cam_target: np.ndarray, hand_eye: np.ndarray, target_pose: np.ndarray,
                      setup: str) -> np.ndarray:
    """T_base_tcp giving view(s) T_cam_target, (..., 4, 4); inverse of :func:`camera_from_robot`."""
    return robot_chain(chain_from_camera(T_cam_target, hand_eye, target_pose), setup)


def target_from_station(T_base_tcp: np.ndarray, hand_eye: np.ndarray, T_cam_target: np.ndarray,
                        setup: str) -> np.ndarray:
    """The target pose ``Y = P X C`` closed through station(s), (..., 4, 4).

    T_base_target (the board in the base frame) eye-in-hand, T_tcp_target eye-to-hand.
    """
    return robot_chain(T_base_tcp, setup) @ hand_eye @ T_cam_target


def hand_eye_from_station(T_base_tcp: np.ndarray, target_pose: np.ndarray,
                          T_cam_target: np.ndarray, setup: str) -> np.ndarray:
    """The hand-eye ``X = inv(P) Y inv(C)`` closed through station(s), (..., 4, 4).

    T_tcp_cam eye-in-hand, T_base_cam eye-to-hand.
    """
    return invert(robot_chain(T_base_tcp, setup)) @ target_pose @ invert(T_cam_target)


@dataclass(frozen=True)
class MotionPairs:
    """Motion pairs between stations ``i < j``: ``A X = X B`` (see docs/conventions.md)."""

    A: np.ndarray  # shape (m, 4, 4), robot chain motions inv(P_i) P_j
    B: np.ndarray  # shape (m, 4, 4), camera motions C_i inv(C_j)
    pairs: np.ndarray  # shape (m, 2), station indices
    skipped: int


def spread_pairs(n: int, max_pairs: int = MAX_MOTION_PAIRS) -> tuple[np.ndarray, np.ndarray]:
    """Station index pairs ``(i, j)``, ``i < j``: all of them, or a spread set of ``max_pairs``.

    Beyond ``max_pairs`` every station (evenly spaced ones if there are more stations than
    pairs) is paired ``max_pairs // n`` times with a partner drawn uniformly from the others,
    with a fixed seed so a result is reproducible. Every station enters, partners are near and
    far alike (capture order often follows a path, so neighbours differ little), and memory and
    time stay bounded for any ``n``.

    Returns
    -------
    i, j : shape (m,), int, ``m <= max_pairs``.
    """
    if n * (n - 1) // 2 <= max_pairs:
        return np.triu_indices(n, 1)
    first = np.tile(np.arange(n), max(1, max_pairs // n))
    if len(first) > max_pairs:
        first = np.linspace(0, n - 1, max_pairs).astype(int)
    other = (first + np.random.default_rng(0).integers(1, n, len(first))) % n
    pair = np.unique(np.minimum(first, other) * n + np.maximum(first, other))
    return pair // n, pair % n


def station_motions(P: np.ndarray, C: np.ndarray, *,
                    min_rotation_deg: float = MIN_MOTION_ROTATION_DEG,
                    max_pairs: int = MAX_MOTION_PAIRS) -> MotionPairs:
    """Station pairs (``spread_pairs``: all up to 200 stations) whose rotation defines a screw axis.

    A pair is used when both its robot and camera rotation angles lie in ``(m, 180 deg - m)``
    with ``m = max(min_rotation_deg, 5 x the angle noise)``; the angle noise is estimated from
    the disagreement of the two angles, which are equal for exact data. Near 0 the screw axis
    is undefined; near 180 deg noise can flip the axis of one of the two rotations.
    """
    i, j = spread_pairs(P.shape[0], max_pairs)
    A = invert(P[i]) @ P[j]
    B = C[i] @ invert(C[j])
    ang_a, ang_b = rotation_angle(A[:, :3, :3]), rotation_angle(B[:, :3, :3])
    noise = 1.4826 * float(np.median(np.abs(ang_a - ang_b))) / np.sqrt(2.0)
    margin = max(np.deg2rad(min_rotation_deg), 5.0 * noise)
    lo, hi = margin, np.pi - margin
    ok = (ang_a > lo) & (ang_a < hi) & (ang_b > lo) & (ang_b < hi)
    return MotionPairs(A=A[ok], B=B[ok], pairs=np.stack([i[ok], j[ok]], axis=1),
                   skipped=int((~ok).sum()))


def tool_side_motions(T_base_tcp: np.ndarray, C: np.ndarray, setup: str) -> MotionPairs:
    """Motion pairs whose robot side is a tcp-frame motion ``inv(P_i) P_j`` (P = T_base_tcp).

    Eye-in-hand their unknown is the hand-eye; eye-to-hand (camera pose replaced by its inverse)
    it is the target pose T_tcp_target: ``inv(P_i) P_j Y = Y inv(C_i) C_j``. Either way the
    robot's reading noise enters in the tcp frame, close to the unknown, instead of being
    carried through the long lever of the base frame.
    """
    return station_motions(T_base_tcp, C if check_setup(setup) == "eye_in_hand" else invert(C))


def check_motion_diversity(motions: MotionPairs, *,
                           min_spread_deg: float = MIN_AXIS_SPREAD_DEG) -> None:
    """Raise ``ValueError`` if the motions cannot determine X (Chen: two non-parallel axes)."""
    if len(motions.A) < 2:
        raise ValueError(
            f"fewer than 2 station pairs rotate by more than {MIN_MOTION_ROTATION_DEG:g} deg: "
            "add stations with the tool tilted (10-35 deg) about different axes")
    axes = so3.log(motions.A[:, :3, :3])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    # the axis lines' largest angle from their principal direction
    principal = np.linalg.svd(axes, full_matrices=False)[2][0]
    spread = np.degrees(np.arccos(np.clip(np.abs(axes @ principal), 0.0, 1.0)).max())
    if spread < min_spread_deg:
        raise ValueError(
            f"rotation axes of all motions are parallel within {min_spread_deg:g} deg: "
            "add stations tilted about another axis")
