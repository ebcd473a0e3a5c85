"""Reading OpenCV camera files (``cv::FileStorage`` YAML, XML, JSON) with pmdsim's own parser.

A setup file may take a camera's intrinsics from such a file (``[cameras.left] opencv =
"left.yml"``), so reading lives here in the setup layer; :mod:`pmdsim.io.opencv` re-exports it
beside the writers. The public entry points are documented there.

OpenCV's calibration samples (``samples/cpp/calibration.cpp``, the ``camera_calibration``
tutorial) store a camera as the top-level nodes ``camera_matrix`` (3 × 3 ``opencv-matrix``),
``distortion_coefficients`` (N × 1 or 1 × N, N ∈ {4, 5, 8, 12, 14}), ``image_width`` and
``image_height``; other nodes are ignored. Also read: ``cameraMatrix``/``K``,
``distCoeffs``/``D``, an ``image_size``/``imageSize`` pair, and ROS ``camera_info`` YAML (plain
``rows``/``cols``/``data`` mappings). Fisheye models are refused. The parsers cover what
``cv::FileStorage`` writes (the YAML subset: block mappings and sequences, flow sequences and
mappings, ``!!opencv-matrix``; XML with ``type_id`` and ``<_>`` items; JSON) — not general YAML.
Conventions: docs/conventions.md ("OpenCV cameras").
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SetupError
from ..geometry.camera import Camera

__all__ = ["read_filestorage", "read_opencv_camera", "camera_from_filestorage", "FILESTORAGE_FORMATS"]

_CAMERA_KEYS = ("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix", "intrinsics")
_DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion")
_SIZE_KEYS = ("image_size", "imageSize", "img_size")
_FISHEYE_MODELS = ("equidistant", "fisheye", "kannala_brandt", "kb4")
_PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "radial-tangential", "pinhole", "")
FILESTORAGE_FORMATS = {".yml": "yaml", ".yaml": "yaml", ".xml": "xml", ".json": "json"}


def _format_of(path: Path) -> str:
    fmt = FILESTORAGE_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise SetupError(f"{path}: not an OpenCV FileStorage file name (expected .yml, .yaml, .xml or .json, "
                         f"got {path.suffix or 'no suffix'!r})")
    return fmt


# ============================================================================ values
def _scalar(text: str) -> Any:
    """A FileStorage scalar: int, float (OpenCV writes ``1.``, ``.Inf``, ``.Nan``) or string."""
    t = text.strip()
    if len(t) >= 2 and t[0] == t[-1] and t[0] in "\"'":
        return t[1:-1]
    if re.fullmatch(r"[-+]?\d+", t):
        return int(t)
    special = {".inf": math.inf, "+.inf": math.inf, "-.inf": -math.inf, ".nan": math.nan}
    if t.lower() in special:
        return special[t.lower()]
    if re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", t):
        return float(t)
    return t


def _matrix(node: dict, where: str) -> np.ndarray:
    """An ``opencv-matrix`` node (rows, cols, dt, data) as an ndarray (rows, cols[, channels])."""
    try:
        rows, cols, data = int(node["rows"]), int(node["cols"]), node["data"]
    except (KeyError, TypeError, ValueError):
        raise SetupError(f"{where}: an opencv-matrix needs integer rows and cols and a data list") from None
    dt = str(node.get("dt", "d"))
    m = re.fullmatch(r"(\d*)([ucwsifdh])", dt)
    if m is None:
        raise SetupError(f"{where}: unknown opencv-matrix element type dt = {dt!r}")
    channels = int(m.group(1) or 1)
    if not isinstance(data, list):
        data = [data]
    try:
        arr = np.array([float(v) for v in data], dtype=float)
    except (TypeError, ValueError):
        raise SetupError(f"{where}: opencv-matrix data must be numbers") from None
    if arr.size != rows * cols * channels:
        raise SetupError(f"{where}: opencv-matrix of {rows} × {cols} × {channels} needs "
                         f"{rows * cols * channels} numbers, has {arr.size}")
    shape = (rows, cols) if channels == 1 else (rows, cols, channels)
    return arr.reshape(shape)


def _nd_matrix(node: dict, where: str) -> np.ndarray:
    """An ``opencv-nd-matrix`` node (sizes, dt, data), as OpenCV writes 1-D and n-D arrays."""
    sizes = node.get("sizes")
    sizes = [sizes] if isinstance(sizes, int) else sizes
    if not isinstance(sizes, list) or not all(isinstance(v, int) and v >= 0 for v in sizes):
        raise SetupError(f"{where}: an opencv-nd-matrix needs a list of integer sizes, got {sizes!r}")
    n = int(np.prod(sizes)) if sizes else 0
    flat = _matrix({"rows": 1, "cols": n, "dt": node.get("dt", "d"), "data": node.get("data", [])}, where)
    return flat.reshape(tuple(sizes) + flat.shape[2:])


def _finish(node: Any, where: str) -> Any:
    """Turn matrix-like mappings (``type_id``/tag ``opencv-matrix`` or ``opencv-nd-matrix``, or
    ROS's rows/cols/data) into arrays."""
    if isinstance(node, dict):
        if node.get("type_id") == "opencv-nd-matrix":
            return _nd_matrix(node, where)
        if node.get("type_id") == "opencv-matrix" or {"rows", "cols", "data"} <= set(node):
            return _matrix(node, where)
        return {k: _finish(v, f"{where}.{k}") for k, v in node.items()}
    if isinstance(node, list):
        return [_finish(v, f"{where}[{i}]") for i, v in enumerate(node)]
    return node


# ============================================================================ YAML
def _strip_comment(line: str) -> str:
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i]
    return line


def _split_flow(text: str, where: str) -> list[str]:
    """Split the inside of a flow collection at top-level commas."""
    parts, depth, quote, cur = [], 0, None, []
    for ch in text:
        if quote:
            cur.append(ch)
            if ch == quote:
                quote = None
            continue
        if ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    if depth != 0 or quote:
        raise SetupError(f"{where}: unbalanced brackets or quotes")
    tail = "".join(cur)
    if tail.strip():
        parts.append(tail)
    return [p.strip() for p in parts]


def _flow(text: str, where: str) -> Any:
    t = text.strip()
    if t.startswith("!!"):  # a tag on a flow value, e.g. !!opencv-matrix { … }
        tag, _, t = t.partition(" ")
        value = _flow(t, where)
        if tag in ("!!opencv-matrix", "!!opencv-nd-matrix") and isinstance(value, dict):
            value["type_id"] = tag[2:]
        return value
    if t.startswith("["):
        if not t.endswith("]"):
            raise SetupError(f"{where}: unterminated flow sequence")
        return [_flow(p, where) for p in _split_flow(t[1:-1], where)]
    if t.startswith("{"):
        if not t.endswith("}"):
            raise SetupError(f"{where}: unterminated flow mapping")
        out = {}
        for p in _split_flow(t[1:-1], where):
            k, sep, v = p.partition(":")
            if not sep:
                raise SetupError(f"{where}: flow mapping entry {p!r} has no ':'")
            out[_scalar(k)] = _flow(v, where)
        return out
    return _scalar(t)


def _balanced(text: str) -> bool:
    depth, quote = 0, None
    for ch in text:
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
    return depth <= 0


def _yaml_lines(text: str) -> list[tuple[int, str, int]]:
    out = []
    for no, raw in enumerate(text.splitlines(), start=1):
        line = _strip_comment(raw).rstrip()
        if not line.strip() or line.startswith("%") or line.strip() in ("---", "..."):
            continue
        if "\t" in line[: len(line) - len(line.lstrip())]:
            raise SetupError(f"line {no}: tabs in indentation are not valid YAML")
        out.append((len(line) - len(line.lstrip(" ")), line.strip(), no))
    return out


def _key_value(content: str, where: str) -> tuple[str, str]:
    if content[:1] in "\"'":
        end = content.find(content[0], 1)
        key, rest = content[1:end], content[end + 1:]
        if not rest.startswith(":"):
            raise SetupError(f"{where}: expected 'key: value', got {content!r}")
        return key, rest[1:].strip()
    m = re.match(r"([^:]+?)\s*:(\s+|$)(.*)$", content)
    if m is None:
        raise SetupError(f"{where}: expected 'key: value', got {content!r}")
    return m.group(1), m.group(3).strip()


class _YamlParser:
    def __init__(self, lines: list[tuple[int, str, int]], source: str):
        self.lines = lines
        self.source = source

    def where(self, i: int) -> str:
        return f"{self.source}, line {self.lines[min(i, len(self.lines) - 1)][2]}"

    def value(self, rest: str, i: int, indent: int) -> tuple[Any, int]:
        """The value after 'key:' (``rest``) at line i; returns (value, next line)."""
        tag = ""
        if rest.startswith("!"):
            tag, _, rest = rest.partition(" ")
            rest = rest.strip()
        if rest:
            while not _balanced(rest):  # a flow collection continued on the next lines
                i += 1
                if i >= len(self.lines):
                    raise SetupError(f"{self.where(i - 1)}: unterminated flow collection")
                rest += " " + self.lines[i][1]
            value = _flow(rest, self.where(i))
            i += 1
        elif i + 1 < len(self.lines) and (self.lines[i + 1][0] > indent or
                                          (self.lines[i + 1][0] == indent and self.lines[i + 1][1].startswith("- "))):
            value, i = self.block(i + 1, self.lines[i + 1][0])
        else:
            value, i = None, i + 1
        if tag in ("!!opencv-matrix", "!!opencv-nd-matrix") and isinstance(value, dict):
            value["type_id"] = tag[2:]
        return value, i

    def block(self, i: int, indent: int) -> tuple[Any, int]:
        if self.lines[i][1] == "-" or self.lines[i][1].startswith("- "):
            return self.sequence(i, indent)
        return self.mapping(i, indent)

    def mapping(self, i: int, indent: int, first: str | None = None) -> tuple[dict, int]:
        out: dict[str, Any] = {}
        while i < len(self.lines):
            ind, content, _ = self.lines[i]
            if first is not None:
                content, first = first, None
            elif ind < indent:
                break
            elif ind > indent:
                raise SetupError(f"{self.where(i)}: unexpected indentation")
            elif content.startswith("- "):
                break
            key, rest = _key_value(content, self.where(i))
            out[key], i = self.value(rest, i, indent)
        return out, i

    def sequence(self, i: int, indent: int) -> tuple[list, int]:
        out = []
        while i < len(self.lines):
            ind, content, _ = self.lines[i]
            if ind != indent or not (content == "-" or content.startswith("- ")):
                if ind > indent:
                    raise SetupError(f"{self.where(i)}: unexpected indentation")
                break
            item = content[1:].strip()
            if not item:
                if i + 1 < len(self.lines) and self.lines[i + 1][0] > indent:
                    value, i = self.block(i + 1, self.lines[i + 1][0])
                else:
                    value, i = None, i + 1
            elif item[0] not in "[{\"'" and re.match(r"[^:]+?\s*:(\s|$)", item):
                value, i = self.mapping(i, indent + 2, first=item)  # "- key: v" then keys at indent + 2
            else:
                value, i = self.value(item, i, indent)
            out.append(value)
        return out, i


def _parse_yaml(text: str, source: str) -> dict:
    lines = _yaml_lines(text)
    if not lines:
        return {}
    value, i = _YamlParser(lines, source).block(0, lines[0][0])
    if i < len(lines):
        raise SetupError(f"{source}, line {lines[i][2]}: unexpected content {lines[i][1]!r}")
    if not isinstance(value, dict):
        raise SetupError(f"{source}: the top level of a FileStorage file must be a mapping")
    return value


# ============================================================================ XML, JSON
def _xml_node(el: ET.Element, where: str) -> Any:
    children = list(el)
    is_matrix = el.get("type_id") in ("opencv-matrix", "opencv-nd-matrix")
    if is_matrix or (children and all(c.tag != "_" for c in children)):
        node = {c.tag: _xml_node(c, f"{where}.{c.tag}") for c in children}
        if el.get("type_id"):
            node["type_id"] = el.get("type_id")
        return node
    if children:  # a sequence of <_> items
        return [_xml_node(c, f"{where}[{i}]") for i, c in enumerate(children)]
    text = (el.text or "").strip()
    if text.startswith('"') and text.endswith('"') and len(text) >= 2:
        return text[1:-1]
    tokens = re.findall(r'"[^"]*"|\S+', text)  # a sequence of scalars is written as one text
    if len(tokens) > 1:
        return [_scalar(t) for t in tokens]
    return _scalar(text) if tokens else None


def _parse_xml(text: str, source: str) -> dict:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise SetupError(f"{source}: not valid XML: {e}") from None
    if root.tag != "opencv_storage":
        raise SetupError(f"{source}: not an OpenCV FileStorage XML file (root element <{root.tag}>, "
                         f"expected <opencv_storage>)")
    return {c.tag: _xml_node(c, f"{source}: {c.tag}") for c in root}


def read_filestorage(path: str | Path) -> dict[str, Any]:
    """Read a ``cv::FileStorage`` file (YAML, XML or JSON, by suffix) into plain values.

    Returns
    -------
    dict
        Top-level node name → int, float, str, list, dict, or ndarray (for ``opencv-matrix``
        nodes, shape (rows, cols) or (rows, cols, channels)).

    Raises
    ------
    SetupError
        The file is missing, unreadable, or not in a form that ``cv::FileStorage`` writes.
    """
    p = Path(path)
    fmt = _format_of(p)
    try:
        text = p.read_text(encoding="utf-8-sig")  # tolerate a byte-order mark
    except FileNotFoundError:
        raise SetupError(f"OpenCV camera file {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SetupError(f"cannot read OpenCV camera file {str(p)!r}: {e}") from None
    if fmt == "yaml":
        doc = _parse_yaml(text, str(p))
    elif fmt == "xml":
        doc = _parse_xml(text, str(p))
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise SetupError(f"{p}: not valid JSON: {e}") from None
        if not isinstance(doc, dict):
            raise SetupError(f"{p}: the top level of a FileStorage JSON file must be an object")
    return {k: _finish(v, f"{p}: {k}") for k, v in doc.items()}


# ============================================================================ cameras
def _first(nodes: dict, keys: tuple[str, ...]) -> tuple[str | None, Any]:
    for k in keys:
        if k in nodes:
            return k, nodes[k]
    return None, None


def camera_from_filestorage(nodes: dict[str, Any], *, source: str = "OpenCV camera") -> Camera:
    """A :class:`Camera` from the nodes of an OpenCV camera file (see :func:`read_filestorage`).

    Raises
    ------
    SetupError
        A node is missing (the message lists the nodes found), the file holds a fisheye model,
        or the values fail :meth:`Camera.from_opencv`'s checks.
    """
    found = ", ".join(sorted(nodes)) or "none"
    fisheye = nodes.get("fisheye_model", 0)
    model = str(nodes.get("distortion_model", "")).strip().lower()
    if (isinstance(fisheye, (int, float)) and fisheye) or model in _FISHEYE_MODELS:
        raise SetupError(f"{source}: a fisheye camera model (fisheye_model / distortion_model = "
                         f"{model or fisheye!r}); pmdsim's camera is OpenCV's pinhole model, whose "
                         f"coefficients mean something else — calibrate with cv2.calibrateCamera")
    if model not in _PINHOLE_MODELS:
        raise SetupError(f"{source}: unknown distortion_model {model!r} (expected one of "
                         f"{', '.join(m for m in _PINHOLE_MODELS if m)})")
    kkey, k = _first(nodes, _CAMERA_KEYS)
    if kkey is None:
        stereo = " (a stereo file? pmdsim reads one camera per file)" if "M1" in nodes else ""
        raise SetupError(f"{source}: no camera matrix (expected a node camera_matrix; nodes found: {found}){stereo}")
    dkey, d = _first(nodes, _DIST_KEYS)
    if dkey is None:
        raise SetupError(f"{source}: no distortion coefficients (expected a node distortion_coefficients; "
                         f"nodes found: {found})")
    k = np.asarray(k, dtype=float)
    d = np.asarray(d if d is not None else [], dtype=float)
    if d.ndim > 1 and min(d.shape) > 1:
        raise SetupError(f"{source}: {dkey} must be a vector (N × 1 or 1 × N), got shape {d.shape}")
    if "image_width" in nodes or "image_height" in nodes:
        if not ("image_width" in nodes and "image_height" in nodes):
            raise SetupError(f"{source}: image_width and image_height must both be given (nodes found: {found})")
        size = (nodes["image_width"], nodes["image_height"])
    else:
        skey, size = _first(nodes, _SIZE_KEYS)
        if skey is None:
            raise SetupError(f"{source}: no image size (expected image_width and image_height, or image_size "
                             f"= [width, height]; nodes found: {found})")
        size = np.asarray(size, dtype=float).ravel()
        if size.size != 2:
            raise SetupError(f"{source}: {skey} must be [width, height], got {size.tolist()}")
    return Camera.from_opencv(k.reshape(k.shape[:2]) if k.ndim == 3 else k, d.ravel(), tuple(size), source=source)


def read_opencv_camera(path: str | Path) -> Camera:
    """Read a camera from an OpenCV ``cv::FileStorage`` file (YAML, XML or JSON).

    Checks the values (:mod:`pmdsim.geometry.camera_checks`): errors for a camera matrix that is
    not normalised, skewed or with a negative focal length, for an implausible image size, for
    non-zero tilted-sensor terms; a warning if the distortion folds over inside the image.
    """
    return camera_from_filestorage(read_filestorage(path), source=str(path))
