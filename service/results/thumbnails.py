"""Station thumbnails for the report: each used station's image, small, with the detected
corners (green dots) and the corners the calibration reprojects (red crosses) drawn over it,
outlier stations framed in red, so a person signing the report sees every view it rests on.

JPEG at ``WIDTH_PX`` wide keeps 20 stations near half a megabyte, embedded as ``data:`` URIs
(the report needs no other file and no network).
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from calib import Result, StationFit

#: Thumbnail width (px) and JPEG quality: readable corners, a few tens of kB each.
WIDTH_PX = 320
JPEG_QUALITY = 70
_GREEN, _RED = (40, 170, 40), (30, 30, 220)  # BGR


def thumbnail(image_path: Path, fit: StationFit, *, outlier: bool) -> bytes | None:
    """The JPEG thumbnail of one station, None when its image cannot be read."""
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if image is None:
        return None
    scale = WIDTH_PX / image.shape[1]
    small = cv2.resize(image, (WIDTH_PX, max(1, round(image.shape[0] * scale))),
                       interpolation=cv2.INTER_AREA)
    corners = np.asarray(fit.corners_px or [], float).reshape(-1, 2)
    residuals = np.asarray(fit.residuals_px or [], float).reshape(-1, 2)
    if len(residuals) == len(corners):  # crosses first: their arms show around the dots
        for x, y in (corners + residuals) * scale:
            cv2.drawMarker(small, (round(x), round(y)), _RED, cv2.MARKER_CROSS, 9, 1)
    for x, y in corners * scale:
        cv2.circle(small, (round(x), round(y)), 2, _GREEN, -1, cv2.LINE_AA)
    if outlier:
        cv2.rectangle(small, (0, 0), (small.shape[1] - 1, small.shape[0] - 1), _RED, 4)
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return jpeg.tobytes() if ok else None


def thumbnails_section(result: Result, images: Mapping[str, str | Path],
                       outliers: set[str]) -> str:
    """The report's "Station images" section; empty without images."""
    cells = []
    for fit in result.stations or []:
        sid = fit.id
        path = images.get(sid)
        jpeg = None if path is None else thumbnail(Path(path), fit, outlier=sid in outliers)
        if jpeg is None:
            continue
        data = base64.b64encode(jpeg).decode("ascii")
        flag = " · outlier" if sid in outliers else ""
        rms_text = "" if fit.rms_px is None else f" · fit {fit.rms_px:.3f} px"
        cells.append(f"<figure class=\"thumb{' outlier' if flag else ''}\"><img alt=\"station "
                     f"{html.escape(sid)}\" src=\"data:image/jpeg;base64,{data}\"><figcaption>"
                     f"{html.escape(sid)}{rms_text}{flag}</figcaption></figure>")
    if not cells:
        return ""
    return ("<h2>Station images</h2><p class=\"note\">Detected corners green, the corners the "
            "calibration reprojects red; outlier stations framed red.</p>"
            f"<div class=\"thumbs\">{''.join(cells)}</div>")
