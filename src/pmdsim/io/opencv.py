"""OpenCV camera files: ``cv::FileStorage`` YAML, XML and JSON, read and written by pmdsim's own code.

OpenCV's calibration samples (``samples/cpp/calibration.cpp``, the ``camera_calibration``
tutorial) store a camera as the top-level nodes

* ``camera_matrix`` — an ``opencv-matrix`` 3 × 3 (K, pixels),
* ``distortion_coefficients`` — an ``opencv-matrix`` N × 1 or 1 × N, N ∈ {4, 5, 8, 12, 14}
  in OpenCV's order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]]),
* ``image_width``, ``image_height`` — integers (px),

beside other nodes (``avg_reprojection_error``, ``extrinsic_parameters`` …) that pmdsim ignores.
:func:`read_opencv_camera` also takes the common alternative names (``cameraMatrix``/``K``,
``distCoeffs``/``D``, an ``image_size``/``imageSize`` pair) and ROS ``camera_info`` YAML
(matrices as plain ``rows``/``cols``/``data`` mappings). It refuses fisheye models
(``fisheye_model: 1``, ``distortion_model: equidistant``): their four coefficients are not
OpenCV's pinhole k1, k2, p1, p2. :func:`write_opencv_camera` writes what the calibration
samples write, readable by ``cv2.FileStorage``.

The readers live in :mod:`pmdsim.setup.opencv_file` (a setup file may reference an OpenCV file)
and are re-exported here. Conventions: docs/conventions.md ("OpenCV cameras").
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SetupError
from ..geometry.camera import Camera
from ..setup.opencv_file import _format_of, camera_from_filestorage, read_filestorage, read_opencv_camera
from .outputs import atomic_file

__all__ = ["read_filestorage", "write_filestorage", "read_opencv_camera", "write_opencv_camera",
           "camera_from_filestorage", "camera_to_filestorage"]


# ============================================================================ writing
def _num(v: float) -> str:
    """A float as the shortest text that reads back to the same double (strtod, Python, OpenCV)."""
    if not math.isfinite(v):
        raise SetupError(f"cannot write the non-finite value {v!r} to an OpenCV camera file")
    return repr(float(v))


def _yaml_entry(key: str, v: Any) -> str:
    if isinstance(v, np.ndarray):
        m = np.atleast_2d(v.astype(float))
        data = ", ".join(_num(x) for x in m.ravel())
        return (f"{key}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n"
                f"   data: [ {data} ]\n")
    if isinstance(v, bool):
        return f"{key}: {int(v)}\n"
    if isinstance(v, (int, np.integer)):
        return f"{key}: {int(v)}\n"
    if isinstance(v, (float, np.floating)):
        return f"{key}: {_num(v)}\n"
    if isinstance(v, str):
        return f"{key}: {json.dumps(v, ensure_ascii=False)}\n"
    if isinstance(v, (list, tuple)):
        return f"{key}: [ {', '.join(str(int(x)) if isinstance(x, (int, np.integer)) else _num(x) for x in v)} ]\n"
    raise TypeError(f"cannot write {type(v).__name__} to a FileStorage file (key {key!r})")


def _xml_entry(key: str, v: Any) -> str:
    if isinstance(v, np.ndarray):
        m = np.atleast_2d(v.astype(float))
        data = " ".join(_num(x) for x in m.ravel())
        return (f'<{key} type_id="opencv-matrix">\n  <rows>{m.shape[0]}</rows>\n  <cols>{m.shape[1]}</cols>\n'
                f"  <dt>d</dt>\n  <data>\n    {data}</data></{key}>\n")
    if isinstance(v, (bool, int, np.integer)):
        return f"<{key}>{int(v)}</{key}>\n"
    if isinstance(v, (float, np.floating)):
        return f"<{key}>{_num(v)}</{key}>\n"
    if isinstance(v, str):
        esc = v.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
        return f'<{key}>"{esc}"</{key}>\n'
    if isinstance(v, (list, tuple)):
        return f"<{key}>{' '.join(str(int(x)) if isinstance(x, (int, np.integer)) else _num(x) for x in v)}</{key}>\n"
    raise TypeError(f"cannot write {type(v).__name__} to a FileStorage file (key {key!r})")


def _json_value(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        m = np.atleast_2d(v.astype(float))
        return {"type_id": "opencv-matrix", "rows": m.shape[0], "cols": m.shape[1], "dt": "d",
                "data": [float(_num(x)) for x in m.ravel()]}
    if isinstance(v, (bool, int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(_num(v))
    if isinstance(v, str):
        return v
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    raise TypeError(f"cannot write {type(v).__name__} to a FileStorage file")


def write_filestorage(path: str | Path, nodes: dict[str, Any], *, force: bool = False) -> None:
    """Write top-level nodes (int, float, str, numeric lists, 2-D float arrays as
    ``opencv-matrix``) as a ``cv::FileStorage`` file (YAML, XML or JSON, by suffix), atomically.

    Floats are written with the shortest text that reads back to the same double.
    """
    p = Path(path)
    fmt = _format_of(p)
    for k in nodes:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k):
            raise SetupError(f"FileStorage node names must be identifiers, got {k!r}")
    if fmt == "yaml":
        text = "%YAML:1.0\n---\n" + "".join(_yaml_entry(k, v) for k, v in nodes.items())
    elif fmt == "xml":
        text = ('<?xml version="1.0"?>\n<opencv_storage>\n' + "".join(_xml_entry(k, v) for k, v in nodes.items())
                + "</opencv_storage>\n")
    else:
        text = json.dumps({k: _json_value(v) for k, v in nodes.items()}, indent=4) + "\n"
    with atomic_file(p, force=force) as f:
        f.write(text.encode("utf-8"))


def camera_to_filestorage(camera: Camera, *, n_coefficients: int | None = None) -> dict[str, Any]:
    """The nodes OpenCV's calibration samples write for a camera: ``image_width``,
    ``image_height``, ``camera_matrix`` (3 × 3), ``distortion_coefficients`` (N × 1; N as
    :meth:`Camera.as_opencv`)."""
    k, d = camera.as_opencv(n_coefficients)
    return {"image_width": camera.width_px, "image_height": camera.height_px,
            "camera_matrix": k, "distortion_coefficients": d.reshape(-1, 1)}


def write_opencv_camera(path: str | Path, camera: Camera, *, n_coefficients: int | None = None,
                        force: bool = False) -> None:
    """Write a camera as an OpenCV ``cv::FileStorage`` file (YAML, XML or JSON, by suffix),
    readable by ``cv2.FileStorage`` and by :func:`read_opencv_camera` (bit-exact round trip)."""
    write_filestorage(path, camera_to_filestorage(camera, n_coefficients=n_coefficients), force=force)
