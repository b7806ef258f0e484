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

from collections.abc import Mapping
from typing import Any

from service.exports import camera, transforms
from service.exports.common import ExportNames
from service.results.schema import Result, parse_result

__all__ = ["CAMERA_FORMATS", "FORMATS", "TRANSFORM_FORMATS", "ExportNames", "export"]

#: Exports of the camera model, then of the hand-eye transform.
CAMERA_FORMATS = tuple(camera.WRITERS)
TRANSFORM_FORMATS = tuple(transforms.WRITERS)
FORMATS = ("json", *CAMERA_FORMATS, *TRANSFORM_FORMATS)

def export(result: Result | Mapping[str, Any], fmt: str,
           names: ExportNames | None = None) -> tuple[str, str, str]:
    """Render a result document as ``fmt``.

    Parameters
    ----------
    result : the result (``service.results.schema.Result``), or its JSON document, which is
        validated first (ValueError naming the first problem).
    fmt : one of ``FORMATS``.
    names : camera and frame names (default ``ExportNames()``).

    Returns
    -------
    content, media_type, filename : str
    """
    names = names or ExportNames()
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format '{fmt}': choose one of {', '.join(FORMATS)}")
    doc = parse_result(result)
    if fmt == "json":
        return doc.model_dump_json(indent=2, exclude_unset=True) + "\n", "application/json", \
            "calibration.json"
    if fmt in CAMERA_FORMATS:
        if doc.camera is None:
            raise ValueError(f"format '{fmt}' needs a camera model, but this result has none "
                             f"(pose-only hand-eye calibration): export it as "
                             f"{_available(doc)}")
        return camera.WRITERS[fmt](doc, doc.camera, names.camera_name)
    if doc.hand_eye is None:
        raise ValueError(f"format '{fmt}' needs a hand-eye transform, but this result has none "
                         f"(intrinsics-only calibration): export it as {_available(doc)}")
    return transforms.WRITERS[fmt](doc, doc.hand_eye, names)


def _available(result: Result) -> str:
    """The formats a result can be exported as, for error messages."""
    usable = ["json"]
    if result.camera is not None:
        usable += CAMERA_FORMATS
    if result.hand_eye is not None:
        usable += TRANSFORM_FORMATS
    return ", ".join(usable)
