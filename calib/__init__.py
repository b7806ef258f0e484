"""cellcal's calibration mathematics: pure functions on arrays, no I/O and no devices.

This is the public surface that ``service``, ``drivers``, ``mocks`` and ``benchmarks`` import;
``calibrate(stations, options)`` (``calib.calibration``) is the one way into the solver.
Modules inside ``calib`` import each other directly; the layout is in ``docs/architecture.md``:

* ``so3``, ``geometry`` — rotations and rigid transforms, UR pose vectors, validation;
* ``chain`` — the cell as one loop ``P X C = Y``: setups, camera-from-robot, motions;
* ``camera`` — the pinhole model with distortion, PnP;
* ``boards`` — the board interface (checkerboard, ChArUco), detection, the target type;
* ``screw``, ``peers``, ``refine``, ``handeye`` — pose-level hand-eye (SM, OpenCV, ``refine``);
* ``intrinsics``, ``joint``, ``nu``, ``bounds`` — corner-level estimation: Method #1, the joint
  maximum likelihood, Method #2, the Cramér-Rao bound;
* ``validation``, ``planning`` — trust metrics, station planning;
* ``options``, ``calibration``, ``pipeline`` — how to calibrate, the one entry, the image flow.
* ``result`` — the result ``cellcal/result@1`` as pydantic models (``Result`` and its blocks).

The names below are loaded on first use (PEP 562): ``import calib.boards`` loads the boards
and OpenCV without scipy or the solvers, so ``cellcal calibrate`` reads and detects its images
while those load (``service.cli.calibrate``).
"""

from __future__ import annotations

import importlib
from typing import Any

#: The public names by the submodule that defines them; ``"ALIAS:NAME"`` exports ``NAME``
#: under another name.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "boards": (
        "MIN_CONTRAST", "Board", "BoardTarget", "Charuco", "CharucoTarget", "Checkerboard",
        "CheckerboardTarget", "ChecksConfiguration", "Detection", "Target", "TargetAdapter",
        "board_from_target", "board_points", "detect_checkerboard", "opencv_out_of_memory",
        "target_from_board",
    ),
    "bounds": ("cramer_rao_bound",),
    "calibration": ("Calibration", "PoseOnlyResult", "calibrate"),
    "camera": ("Pinhole", "image_corner_error", "solve_pnp"),
    "chain": (
        "SETUPS", "MotionPairs", "RobotNoise", "camera_from_robot", "check_setup",
        "hand_eye_from_station", "robot_chain", "robot_from_camera", "station_motions",
        "target_from_station",
    ),
    "coldstart": ("Bootstrap", "Guess", "View", "bootstrap", "camera_position"),
    "crossval": ("CrossValidation", "PoseStations"),
    "evidence": ("Trust",),
    "fields": ("FiniteFloat",),
    "explorer": ("ColdStart", "Proposal"),
    "geometry": (
        "PoseError", "check_joint_positions", "check_transforms", "check_ur_pose",
        "check_ur_poses", "check_ur_vector", "invert", "make_transform", "matrix_from_ur_pose",
        "perturb", "pose_error", "rotation_angle", "ur_pose_from_matrix",
    ),
    "handeye": ("HandEyeResult", "calibrate_hand_eye"),
    "intrinsics": ("IntrinsicsOptions", "IntrinsicsResult", "calibrate_intrinsics"),
    "joint": (
        "CAMERA_PARAMS", "CellParameters", "CornerStations", "JointOptions", "JointResult",
        "solve_joint",
    ),
    "nu": ("NuSearch", "nu_from_extrinsics"),
    "options": ("KAPPA_MODES", "METHODS", "POSE_METHODS", "SolverOptions"),
    "peers": ("OPENCV_HAND_EYE_METHODS", "OPENCV_ROBOT_WORLD_METHODS"),
    "pipeline": ("CalibrationResult",),
    "planning": (
        "CellGuess", "Plan", "PlanOptions", "cuts_board_at_corner", "look_at_view",
        "plan_stations", "rough_target_from_image",
    ),
    "quality": ("COVERAGE_GRID", "image_coverage", "outlier_limit"),
    "recheck": ("CheckVerdict", "Expected", "StationCheck", "StoredCell", "check_verdict"),
    "refine": ("RefineOptions",),
    "result": (
        "RESULT_FORMAT", "BoardScale", "CameraModel", "Candidate", "CrossValidationBlock",
        "Finding", "HeldOutStation", "ModelSelection", "Motions", "QualityBlock",
        "Rejected", "Result", "Software", "StationFit", "Transform", "Uncertainty", "parse_result",
    ),
    "screw": ("solve_sm",),
    "selection": ("ModelCandidate", "Selection", "SELECTION_RULE:RULE"),
    "stations": ("MIN_IMAGES", "Station", "StationInputs", "Stations"),
    "uncertainty": ("COVERAGE_90", "hand_eye_rss"),
    "validation": ("dot_hit", "leave_one_out", "motion_residuals", "reprojection_rms"),
    "viewselect": ("ColdStartScene:Scene", "hand_eye_sigma"),
}
#: Public name -> (module, name there).
_WHERE = {alias: (f"calib.{module}", name or alias)
          for module, names in _EXPORTS.items()
          for alias, _, name in (entry.partition(":") for entry in names)}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """A public name, imported from its submodule on first use and kept."""
    if name not in _WHERE:
        raise AttributeError(f"module 'calib' has no attribute {name!r}")
    module, attr = _WHERE[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
