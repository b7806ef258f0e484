"""Export a result document (``cellcal/result@1``) in the format a user's stack wants.

Formats (``FORMATS``), one module per family:

* ``json`` — the result document itself;
* camera model (``service.exports.camera``): ``opencv-yaml`` (``cv::FileStorage``) and
  ``ros-camera-info`` (the YAML of ROS ``camera_calibration_parsers``);
* hand-eye transform (``service.exports.transforms``): ``urdf`` (a fixed joint),
  ``ur-pose`` (``p[x, y, z, rx, ry, rz]``) and ``ros2-static-tf`` (a ROS 2 Python launch
  file starting ``tf2_ros static_transform_publisher``).

The camera formats need the camera model and refuse pose-only results; the transform formats
need the hand-eye and refuse intrinsics-only results; both say which formats the result does
have. Frame and link names are configurable (``ExportNames``) and checked, so they can be
written into XML and Python without quoting.
"""

from __future__ import annotations

import json
from typing import Any

from calib import SETUPS
from service.exports import camera, transforms
from service.exports.common import ExportNames

__all__ = ["CAMERA_FORMATS", "FORMATS", "TRANSFORM_FORMATS", "ExportNames", "export"]

#: Exports of the camera model, then of the hand-eye transform.
CAMERA_FORMATS = tuple(camera.WRITERS)
TRANSFORM_FORMATS = tuple(transforms.WRITERS)
FORMATS = ("json", *CAMERA_FORMATS, *TRANSFORM_FORMATS)

def export(result_json: dict[str, Any], fmt: str,
           names: ExportNames | None = None) -> tuple[str, str, str]:
    """Render a result document as ``fmt``.

    Parameters
    ----------
    result_json : the result document (``product.md``, "Result").
    fmt : one of ``FORMATS``.
    names : camera and frame names (default ``ExportNames()``).

    Returns
    -------
    content, media_type, filename : str
    """
    names = names or ExportNames()
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format '{fmt}': choose one of {', '.join(FORMATS)}")
    if fmt == "json":
        return json.dumps(result_json, indent=2) + "\n", "application/json", "calibration.json"
    setup = result_json.get("setup")
    if setup not in SETUPS:
        raise ValueError(f"result has unknown setup {setup!r}: expected eye_in_hand or "
                         "eye_to_hand")
    if fmt in CAMERA_FORMATS:
        if not (result_json.get("camera") or {}).get("K"):
            raise ValueError(f"format '{fmt}' needs a camera model, but this result has none "
                             f"(pose-only hand-eye calibration): export it as "
                             f"{_available(result_json)}")
        return camera.WRITERS[fmt](result_json, setup, names.camera_name)
    if not (result_json.get("hand_eye") or {}).get("matrix"):
        raise ValueError(f"format '{fmt}' needs a hand-eye transform, but this result has none "
                         f"(intrinsics-only calibration): export it as "
                         f"{_available(result_json)}")
    return transforms.WRITERS[fmt](result_json, setup, names)


def _available(result_json: dict[str, Any]) -> str:
    """The formats a result can be exported as, for error messages."""
    usable = ["json"]
    if (result_json.get("camera") or {}).get("K"):
        usable += CAMERA_FORMATS
    if (result_json.get("hand_eye") or {}).get("matrix"):
        usable += TRANSFORM_FORMATS
    return ", ".join(usable)
