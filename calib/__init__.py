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
"""

from calib.boards import (
    MIN_CONTRAST,
    Board,
    BoardTarget,
    Charuco,
    CharucoTarget,
    Checkerboard,
    CheckerboardTarget,
    ChecksConfiguration,
    Detection,
    Target,
    TargetAdapter,
    board_from_target,
    board_points,
    detect_checkerboard,
    target_from_board,
)
from calib.bounds import cramer_rao_bound
from calib.calibration import Calibration, PoseOnlyResult, calibrate
from calib.camera import Pinhole, image_corner_error, solve_pnp
from calib.chain import (
    SETUPS,
    MotionPairs,
    RobotNoise,
    camera_from_robot,
    check_setup,
    hand_eye_from_station,
    robot_chain,
    robot_from_camera,
    station_motions,
    target_from_station,
)
from calib.coldstart import Bootstrap, Guess, View, bootstrap, camera_position
from calib.crossval import CrossValidation, PoseStations
from calib.evidence import Trust
from calib.explorer import ColdStart, Proposal
from calib.geometry import (
    PoseError,
    check_joint_positions,
    check_transforms,
    check_ur_pose,
    check_ur_poses,
    check_ur_vector,
    invert,
    make_transform,
    matrix_from_ur_pose,
    perturb,
    pose_error,
    rotation_angle,
    ur_pose_from_matrix,
)
from calib.handeye import POSE_METHODS, HandEyeResult, calibrate_hand_eye
from calib.intrinsics import (
    MIN_IMAGES,
    IntrinsicsOptions,
    IntrinsicsResult,
    calibrate_intrinsics,
)
from calib.joint import (
    CAMERA_PARAMS,
    CellParameters,
    CornerStations,
    JointOptions,
    JointResult,
    solve_joint,
)
from calib.nu import NuSearch, nu_from_extrinsics
from calib.options import METHODS, SolverOptions
from calib.peers import OPENCV_HAND_EYE_METHODS, OPENCV_ROBOT_WORLD_METHODS
from calib.pipeline import CalibrationResult
from calib.planning import (
    CellGuess,
    Plan,
    PlanOptions,
    cuts_board_at_corner,
    look_at_view,
    plan_stations,
    rough_target_from_image,
)
from calib.quality import COVERAGE_GRID, OUTLIER_FACTOR, image_coverage
from calib.recheck import CheckVerdict, Expected, StationCheck, StoredCell, check_verdict
from calib.refine import RefineOptions
from calib.result import (
    RESULT_FORMAT,
    BoardScale,
    CameraModel,
    Candidate,
    CrossValidationBlock,
    Finding,
    FiniteFloat,
    HeldOutStation,
    ModelSelection,
    Motions,
    QualityBlock,
    Rejected,
    Result,
    Software,
    StationFit,
    Transform,
    Uncertainty,
    parse_result,
)
from calib.screw import solve_sm
from calib.selection import KAPPA_MODES, ModelCandidate, Selection
from calib.selection import RULE as SELECTION_RULE
from calib.stations import Station, StationInputs, Stations
from calib.uncertainty import COVERAGE_90
from calib.validation import dot_hit, leave_one_out, motion_residuals, reprojection_rms
from calib.viewselect import Scene as ColdStartScene
from calib.viewselect import hand_eye_sigma

__all__ = [
    "CAMERA_PARAMS",
    "COVERAGE_90",
    "COVERAGE_GRID",
    "KAPPA_MODES",
    "METHODS",
    "MIN_CONTRAST",
    "MIN_IMAGES",
    "OPENCV_HAND_EYE_METHODS",
    "OPENCV_ROBOT_WORLD_METHODS",
    "OUTLIER_FACTOR",
    "POSE_METHODS",
    "RESULT_FORMAT",
    "SELECTION_RULE",
    "SETUPS",
    "Board",
    "BoardScale",
    "BoardTarget",
    "Bootstrap",
    "Calibration",
    "CalibrationResult",
    "CameraModel",
    "Candidate",
    "CellGuess",
    "CellParameters",
    "Charuco",
    "CharucoTarget",
    "CheckVerdict",
    "Checkerboard",
    "CheckerboardTarget",
    "ChecksConfiguration",
    "ColdStart",
    "ColdStartScene",
    "CornerStations",
    "CrossValidation",
    "CrossValidationBlock",
    "Detection",
    "Expected",
    "Finding",
    "FiniteFloat",
    "Guess",
    "HandEyeResult",
    "HeldOutStation",
    "IntrinsicsOptions",
    "IntrinsicsResult",
    "JointOptions",
    "JointResult",
    "ModelCandidate",
    "ModelSelection",
    "MotionPairs",
    "Motions",
    "NuSearch",
    "Pinhole",
    "Plan",
    "PlanOptions",
    "PoseError",
    "PoseOnlyResult",
    "PoseStations",
    "Proposal",
    "QualityBlock",
    "RefineOptions",
    "Rejected",
    "Result",
    "RobotNoise",
    "Selection",
    "Software",
    "SolverOptions",
    "Station",
    "StationCheck",
    "StationFit",
    "StationInputs",
    "Stations",
    "StoredCell",
    "Target",
    "TargetAdapter",
    "Transform",
    "Trust",
    "Uncertainty",
    "View",
    "board_from_target",
    "board_points",
    "bootstrap",
    "calibrate",
    "calibrate_hand_eye",
    "calibrate_intrinsics",
    "camera_from_robot",
    "camera_position",
    "check_joint_positions",
    "check_setup",
    "check_transforms",
    "check_ur_pose",
    "check_ur_poses",
    "check_ur_vector",
    "check_verdict",
    "cramer_rao_bound",
    "cuts_board_at_corner",
    "detect_checkerboard",
    "dot_hit",
    "hand_eye_from_station",
    "hand_eye_sigma",
    "image_corner_error",
    "image_coverage",
    "invert",
    "leave_one_out",
    "look_at_view",
    "make_transform",
    "matrix_from_ur_pose",
    "motion_residuals",
    "nu_from_extrinsics",
    "parse_result",
    "perturb",
    "plan_stations",
    "pose_error",
    "reprojection_rms",
    "robot_chain",
    "robot_from_camera",
    "rotation_angle",
    "rough_target_from_image",
    "solve_joint",
    "solve_pnp",
    "solve_sm",
    "station_motions",
    "target_from_board",
    "target_from_station",
    "ur_pose_from_matrix",
]
