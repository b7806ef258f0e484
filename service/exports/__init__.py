"""Export a result document (``cellcal/result@1``) in the format a user's stack wants.

``TABLE`` lists every format, one line each: its name, the part of the result it needs, its
writer (an import string ``module:function``, imported when the format is asked for) and what
it is (the REST parameter's description and ``cellcal export --format``'s help are made from
it). A writer takes ``(result, names)`` and returns ``(content, media_type, filename)``; the
writers live in one module per family:

* ``json`` — the result document itself (here);
* camera model (``service.exports.camera``): ``opencv-yaml`` (``cv::FileStorage``) and
  ``ros-camera-info`` (the YAML of ROS ``camera_calibration_parsers``);
* hand-eye transform (``service.exports.transforms``): ``urdf`` (a fixed joint),
  ``ur-pose`` (``p[x, y, z, rx, ry, rz]``) and ``ros2-static-tf`` (a ROS 2 Python launch
  file starting ``tf2_ros static_transform_publisher``).

A format that needs the camera model refuses pose-only results, one that needs the hand-eye
refuses intrinsics-only results; both say which formats the result does have. Frame and link
names are configurable (``ExportNames``) and checked, so they can be written into XML and
Python without quoting. A new format is a module with its writer and one line in ``TABLE``.
"""

from __future__ import annotations

import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from calib import Result, parse_result
from service.exports.common import ExportNames

__all__ = ["CAMERA_FORMATS", "FORMATS", "TABLE", "TRANSFORM_FORMATS", "ExportNames", "export",
           "formats_help"]

@dataclass(frozen=True)
class Format:
    """An export format: the part of the result it ``needs`` (None: the document is enough),
    its ``writer`` (import string of a function ``(result, names) -> (content, media type,
    file name)``) and ``what`` it is in a few words (None: its name says it)."""

    needs: Literal["camera", "hand_eye"] | None
    writer: str
    what: str | None = None

    def write(self, result: Result, names: ExportNames) -> tuple[str, str, str]:
        """``result`` in this format."""
        return pkgutil.resolve_name(self.writer)(result, names)

    def usable(self, result: Result) -> bool:
        """Whether ``result`` has what this format needs."""
        if self.needs is None:
            return True
        return (result.camera if self.needs == "camera" else result.hand_eye) is not None


def document(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """The result document itself, as JSON."""
    return (result.model_dump_json(indent=2, exclude_unset=True) + "\n", "application/json",
            "calibration.json")


#: Every export format, in the order they are listed.
TABLE: dict[str, Format] = {
    "json": Format(None, "service.exports:document", "the result document"),
    "opencv-yaml": Format("camera", "service.exports.camera:opencv_yaml", "cv::FileStorage"),
    "ros-camera-info": Format("camera", "service.exports.camera:ros_camera_info"),
    "urdf": Format("hand_eye", "service.exports.transforms:urdf", "camera joint"),
    "ur-pose": Format("hand_eye", "service.exports.transforms:ur_pose", "hand-eye as p[...]"),
    "ros2-static-tf": Format("hand_eye", "service.exports.transforms:ros2_static_tf",
                             "ROS 2 launch file"),
}
FORMATS = tuple(TABLE)
#: Exports of the camera model, and of the hand-eye transform.
CAMERA_FORMATS = tuple(name for name, f in TABLE.items() if f.needs == "camera")
TRANSFORM_FORMATS = tuple(name for name, f in TABLE.items() if f.needs == "hand_eye")
#: What a result without the part a format needs is, for the error message.
_WITHOUT = {"camera": "a camera model, but this result has none (pose-only hand-eye "
                      "calibration)",
            "hand_eye": "a hand-eye transform, but this result has none (intrinsics-only "
                        "calibration)"}


def formats_help() -> str:
    """The formats with what each is, e.g. ``json (the result document), ...``."""
    return ", ".join(name if f.what is None else f"{name} ({f.what})"
                     for name, f in TABLE.items())


def export(result: Result | Mapping[str, Any], fmt: str,
           names: ExportNames | None = None) -> tuple[str, str, str]:
    """Render a result document as ``fmt``.

    Parameters
    ----------
    result : the result (``calib.Result``), or its JSON document, which is
        validated first (ValueError naming the first problem).
    fmt : one of ``FORMATS``.
    names : camera and frame names (default ``ExportNames()``).

    Returns
    -------
    content, media_type, filename : str
    """
    names = names or ExportNames()
    if fmt not in TABLE:
        raise ValueError(f"unknown export format '{fmt}': choose one of {', '.join(FORMATS)}")
    doc = parse_result(result)
    form = TABLE[fmt]
    if form.needs is not None and not form.usable(doc):
        usable = ", ".join(name for name, f in TABLE.items() if f.usable(doc))
        raise ValueError(f"format '{fmt}' needs {_WITHOUT[form.needs]}: export it as {usable}")
    return form.write(doc, names)
