"""Result documents (``cellcal/result@1``) of the default mock cell: full, pose-only,
intrinsics-only."""

from __future__ import annotations

from typing import Any

from calib.geometry import ur_pose_from_matrix
from calib.handeye import HandEyeResult
from mocks.scene import default_scene
from service.results.document import hand_eye_result

SCENE = default_scene()


def full_result(setup="eye_in_hand", hand_eye=None, dist=None):
    X = SCENE.hand_eye_matrix if hand_eye is None else hand_eye
    Y = SCENE.target_pose_matrix
    return {
        "format": "cellcal/result@1",
        "setup": setup,
        "camera": {"image_size": [1280, 1024], "K": SCENE.camera.K,
                   "dist": SCENE.camera.dist if dist is None else dist, "rms_px": 0.05},
        "target": {"kappa": 1.005, "nu": 0.9975},
        "hand_eye": {"matrix": X.tolist(), "pose": ur_pose_from_matrix(X).tolist()},
        "target_pose": {"matrix": Y.tolist(), "pose": ur_pose_from_matrix(Y).tolist()},
    }


def pose_only_result():
    fit = HandEyeResult(setup="eye_in_hand", method="sm", hand_eye=SCENE.hand_eye_matrix,
                        target_pose=SCENE.target_pose_matrix)
    return hand_eye_result(fit, [], options={}).document()


def intrinsics_only_result() -> dict[str, Any]:
    """A camera model without robot poses (``calib.pipeline``: hand_eye None)."""
    return full_result() | {"hand_eye": None, "target_pose": None}
