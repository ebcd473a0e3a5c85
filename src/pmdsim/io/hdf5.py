"""HDF5 outputs: per-camera mappings, evaluations and reconstructions (layouts in
docs/conventions.md, "HDF5 outputs").

Every file is self-describing (issue 23): each dataset carries ``units`` (a UDUNITS string from
:data:`UNITS`), ``long_name`` and, where it has one, its ``frame``; per-pixel maps are attached
to HDF5 dimension scales ``v`` and ``u`` (pixel row and column indices) and, for vectors,
``component`` (x, y, z) or ``component_xy`` (x, y), so that
``xarray.open_datatree(path, engine="h5netcdf")`` opens every file with named dimensions.
Parameters (Δh, scenario, screen model, …) are group attributes, never part of a group name.
Filters chosen by measurement (docs/benchmarks.md, "HDF5 writing"): float maps of mapping and
evaluation files uncompressed, of ``heights.h5`` gzip + shuffle, booleans and integers gzip +
shuffle — standard filters any HDF5 reader decodes without plugins.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

__all__ = ["write_mapping_h5", "reconstructions_h5", "write_reconstructions_h5", "write_evaluation_h5",
           "EvaluationFile", "append_stereo_h5", "write_consistency_h5", "UNITS", "FLOAT_FILTERS", "ARCHIVE_FILTERS",
           "INT_FILTERS", "case_groups"]

#: The units strings pmdsim writes (UDUNITS-2 spellings; ``1``: dimensionless, counts, codes,
#: booleans, indices). Documented in docs/conventions.md; the tests check every dataset against it.
UNITS = ("mm", "um", "urad", "1")

#: HDF5 filters for the float maps of ``mapping.h5`` and ``evaluation.h5``, chosen by measurement
#: (docs/benchmarks.md, "HDF5 writing"): none. Decoded float maps carry noise in their low
#: mantissa bits, so gzip + shuffle saves only 47 % of their size at 8–27× the write time
#: (11 s of a full-resolution evaluate at load 4, against 0.8–1.3 s uncompressed).
FLOAT_FILTERS: dict = {}

#: HDF5 filters for the float maps of ``heights.h5`` (experiment archives of many cases, where
#: the size matters more than a second per case): byte shuffle + gzip level 1.
ARCHIVE_FILTERS: dict = dict(compression="gzip", compression_opts=1, shuffle=True)

#: HDF5 filters for boolean and integer maps (masks, flags, codes: long runs of equal values, a
#: few per cent of their size after gzip level 1 + shuffle, at little cost).
INT_FILTERS: dict = dict(compression="gzip", compression_opts=1, shuffle=True)

#: Rows per chunk of a per-pixel map (a chunk spans whole rows and all components).
CHUNK_ROWS = 64

_STR = h5py.string_dtype()
_SCALES = {"v": "pixel row index v (0 = centre of the top row, docs/conventions.md)",
           "u": "pixel column index u (0 = centre of the left column, docs/conventions.md)"}
_COMPONENTS = {3: ("component", ("x", "y", "z")), 2: ("component_xy", ("x", "y"))}


def _units_of(name: str) -> str:
    """Units from a dataset name's suffix (``_mm``, ``_um``, ``_urad``), else ``1``."""
    for u in ("mm", "um", "urad"):
        if name.endswith(f"_{u}"):
            return u
    return "1"


def _scale(g: h5py.Group, name: str, values, units: str, long_name: str) -> h5py.Dataset:
    """The dimension scale ``name`` of group ``g`` (created on first use)."""
    if name in g:
        return g[name]
    d = g.create_dataset(name, data=values)
    d.make_scale(name)
    d.attrs["units"] = units
    d.attrs["long_name"] = long_name
    return d


def _pixel_scales(g: h5py.Group, shape: tuple) -> list[h5py.Dataset]:
    """Dimension scales for an (H, W[, k]) per-pixel map: ``v``, ``u`` and the component axis."""
    scales = [_scale(g, "v", np.arange(shape[0], dtype=np.int32), "1", _SCALES["v"]),
              _scale(g, "u", np.arange(shape[1], dtype=np.int32), "1", _SCALES["u"])]
    if len(shape) == 3:
        if shape[2] not in _COMPONENTS:
            raise ValueError(f"per-pixel map with {shape[2]} components per pixel; expected 2 or 3")
        name, labels = _COMPONENTS[shape[2]]
        scales.append(_scale(g, name, np.array(labels, dtype=object).astype(_STR), "1",
                             f"vector component ({', '.join(labels)}) in the dataset's frame"))
    return scales


def _all_zero_bits(data: np.ndarray) -> bool:
    """Every element of a bool, integer or float array all zero bits (0, +0.0, False: HDF5's
    default fill value, what an unwritten chunk reads as; −0.0 is not)."""
    if data.dtype.kind not in "biuf" or not data.size:
        return False
    words = data.view(f"u{data.dtype.itemsize}")  # the same strides: no copy
    return not words.flat[0] and not words.any()


def _put(g: h5py.Group, name: str, data, *, units: str, long_name: str, frame: str | None = None,
         dims: list | None = None, compress: bool = True, archive: bool = False, **attrs) -> h5py.Dataset:
    """Write ``g[name]`` with its units, long name, frame and dimension scales (per-pixel
    (H, W[, k]) maps by default, in chunks of :data:`CHUNK_ROWS` whole rows; ``dims``: other
    scales, one per axis). Filters: :data:`INT_FILTERS` for booleans and integers, else
    :data:`ARCHIVE_FILTERS` if ``archive`` else :data:`FLOAT_FILTERS`. A chunked map whose
    elements are all zero bits (e.g. the calibration σ maps when the setup carries no calibration
    covariance) is created without writing its chunks: HDF5 reads unwritten chunks as the
    default fill value 0, so the dataset reads back identical (issue 25: 110 MB less to write
    for a two-camera 1920×1200 evaluation)."""
    if units not in UNITS:
        raise ValueError(f"units {units!r} of {name!r} not in {UNITS}")
    data = np.asarray(data)
    kw: dict = {}
    if dims is None:
        dims = _pixel_scales(g, data.shape)
        if compress and data.size:
            filters = INT_FILTERS if data.dtype.kind != "f" else ARCHIVE_FILTERS if archive else FLOAT_FILTERS
            kw = dict(filters, chunks=(min(CHUNK_ROWS, data.shape[0]), *data.shape[1:]))
    if kw and _all_zero_bits(data):  # every chunk equals the fill value: none written (read back as 0)
        d = g.create_dataset(name, shape=data.shape, dtype=data.dtype, **kw)
    else:
        d = g.create_dataset(name, data=data, **kw)
    d.attrs["units"] = units
    d.attrs["long_name"] = long_name
    if frame is not None:
        d.attrs["frame"] = frame
    for k, v in attrs.items():
        d.attrs[k] = v
    for axis, s in enumerate(dims):
        d.dims[axis].attach_scale(s)
    return d


def _file_attrs(f: h5py.File, attrs: dict[str, Any]) -> None:
    for k, v in attrs.items():
        f.attrs[k] = v if v is not None else ""


def write_mapping_h5(path: str | Path, mappings: dict[str, Any], attrs: dict[str, Any]) -> None:
    """Write per-camera pixel → screen mappings (one group per camera).

    Each group holds ``screen_xy_mm`` (float64, (H, W, 2), screen frame, NaN where invalid),
    ``valid`` (bool, (H, W)) and ``status`` (uint8, (H, W),
    :class:`pmdsim.simulation.trace.Status` codes), on the dimension scales ``v``, ``u``,
    ``component_xy``.
    """
    from ..simulation.trace import Status

    codes = json.dumps({s.name: int(s) for s in Status})
    with h5py.File(path, "w", track_order=True) as f:
        _file_attrs(f, attrs)
        f.attrs["status_codes"] = codes
        for name, m in mappings.items():
            g = f.create_group(name)
            _put(g, "screen_xy_mm", m.screen_xy_mm, units="mm", frame="screen",
                 long_name="pattern-screen coordinates (x_q, y_q) seen by the pixel; NaN where invalid")
            _put(g, "valid", m.valid, units="1", long_name="pixel sees the screen via the sample (bool)")
            _put(g, "status", m.status, units="1", long_name="ray-trace status code (attribute codes)",
                 codes=codes)
            for sname, count in m.status_counts().items():
                g.attrs[f"count_{sname}"] = count


def _write_case(g: h5py.Group, c) -> None:
    """One reconstructed case (an Experiment 1 ``Case``) into group ``g``."""
    _put(g, "height_mm", c.height_mm, units="mm", frame="sample",
         long_name="reconstructed height along sample +z; NaN outside the field of view", archive=True)
    _put(g, "height_error_um", (c.height_error_mm * 1e3).astype(np.float32), units="um", frame="sample",
         long_name="reconstructed minus true height", archive=True)
    _put(g, "points_mm", c.p_sample_mm, units="mm", frame="sample", long_name="reconstructed surface points",
         archive=True)
    _put(g, "valid", c.reconstructed, units="1", long_name="pixel reconstructed (bool)")
    for k, v in c.as_record().items():
        g.attrs[k] = json.dumps(v) if isinstance(v, (list, dict)) else v


@contextlib.contextmanager
def reconstructions_h5(path: str | Path, attrs: dict[str, Any]):
    """Open a reconstructions file for writing case by case (so that a long experiment need not
    hold every height map in memory); yields ``add(c, params=None, *, group=None)``.

    ``add`` writes the case ``c`` into ``case_{k:03d}/{camera}``, where ``case_{k:03d}`` is the
    group of the parameter set ``params`` (default ``{"bulge_mm": c.bulge_mm}``), numbered in
    order of first appearance; the parameters are that group's attributes (never part of its
    name). ``group``: an explicit group name instead (e.g. the camera, for a one-case file).
    Layout: see :func:`write_reconstructions_h5`; reading: :func:`case_groups`.
    """
    with h5py.File(path, "w", track_order=True) as f:
        _file_attrs(f, attrs)
        cases: dict = {}

        def add(c, params: dict | None = None, *, group: str | None = None) -> None:
            if group is None:
                params = {"bulge_mm": float(c.bulge_mm)} if params is None else dict(params)
                key = json.dumps(params, sort_keys=True)
                if key not in cases:
                    cases[key] = f.create_group(f"case_{len(cases):03d}")
                    for k, v in params.items():
                        cases[key].attrs[k] = v
                g = cases[key].create_group(c.camera)
            else:
                g = f.create_group(group)
            _write_case(g, c)

        yield add


def case_groups(f: h5py.File):
    """Iterate over a reconstructions file's cases: yields ``(params, camera, group)`` with the
    case group's attributes as ``params`` (e.g. ``{"bulge_mm": 3.0}``)."""
    for name, case in f.items():
        if isinstance(case, h5py.Group) and name.startswith("case_"):
            params = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in case.attrs.items()}
            for cam, g in case.items():
                if isinstance(g, h5py.Group):
                    yield params, cam, g


def write_reconstructions_h5(path: str | Path, cases, attrs: dict[str, Any]) -> None:
    """Write reconstructions: group ``case_{k:03d}`` per Δh (attribute ``bulge_mm``), in it
    one group per camera.

    Each camera group holds ``height_mm`` (float64 (H, W), reconstructed height in the sample
    frame, NaN outside the FOV), ``height_error_um`` (float32, reconstructed − true),
    ``points_mm`` ((H, W, 3), sample frame) and ``valid`` (bool), with the metrics as
    attributes.
    """
    with reconstructions_h5(path, attrs) as add:
        for c in cases:
            add(c)


#: Evaluation datasets: name → (units, long_name, frame).
_EVALUATION = {
    "screen_xy_mm": ("mm", "decoded pattern-screen coordinates (x_q, y_q); NaN where not decoded", "screen"),
    "std_xy_mm": ("mm", "predicted standard deviation of screen_xy_mm", "screen"),
    "decoded": ("1", "pixel decoded (bool)", None),
    "phase_flags": ("1", "decoding flags (PhaseFlag bits, file attribute phase_flags)", None),
    "reversed_contrast": ("1", "fringe contrast reversed by the lens and corrected by π, per direction (x, y) (bool)",
                          None),
    "registration_status": ("1", "registration status code (file attribute registration_status)", None),
    "normals": ("1", "unit surface normals", "sample"),
    "points_mm": ("mm", "reconstructed surface points", "sample"),
    "height_mm": ("mm", "height along sample +z (docs/conventions.md); NaN where not reconstructed", "sample"),
    "reconstructed": ("1", "pixel reconstructed (bool)", None),
    "slopes": ("1", "surface slopes (dz/dx, dz/dy)", "sample"),
    "residual_slopes": ("1", "slopes minus the fitted paraboloid's slopes", "sample"),
    "height_detrended_mm": ("mm", "height minus the fitted paraboloid", "sample"),
    "slope_std_urad": ("urad", "combined standard uncertainty (k = 1) of slopes (dz/dx, dz/dy)", "sample"),
    "height_std_um": ("um", "combined standard uncertainty (k = 1) of height_mm, relative to the anchor", "sample"),
    "height_std_noise_um": ("um", "height standard uncertainty from the images' noise (k = 1)", "sample"),
    "height_std_calibration_um": ("um", "height standard uncertainty from the calibration covariance (k = 1)",
                                  "sample"),
    "slope_std_noise_urad": ("urad", "slope standard uncertainty from the images' noise (k = 1)", "sample"),
    "slope_std_calibration_urad": ("urad", "slope standard uncertainty from the calibration covariance (k = 1)",
                                   "sample"),
}


def write_evaluation_h5(path: str | Path, results: dict, attrs: dict[str, Any], extras: dict | None = None) -> None:
    """Write an evaluation: one group per camera with the decoded coordinates, masks, normals
    and the height map.

    Datasets per camera: ``screen_xy_mm`` ((H, W, 2), screen frame, NaN where not decoded),
    ``std_xy_mm`` (predicted σ), ``decoded`` (bool), ``phase_flags`` (uint8,
    :class:`pmdsim.evaluation.phase.PhaseFlag`), ``reversed_contrast`` ((H, W, 2) bool: a period's
    contrast reversed by the lens and corrected by π, per direction), ``registration_status`` (uint8,
    :class:`pmdsim.evaluation.registration.RegistrationStatus`), ``normals`` ((H, W, 3), unit,
    sample frame), ``points_mm`` ((H, W, 3), sample frame), ``height_mm`` ((H, W), sample frame,
    NaN where not reconstructed) and ``reconstructed`` (bool); ``extras[camera]`` adds further
    (H, W[, k]) float datasets of that camera by name (e.g. ``slopes``, ``height_detrended_mm``;
    units from the name's suffix). Units, long names, frames and dimension scales: see the
    module docstring. The same file, written camera by camera: :class:`EvaluationFile`.
    """
    with EvaluationFile(path) as f:
        for cam, (decoded, reg, rec) in results.items():
            f.add_camera(cam, decoded, reg, rec)
        for cam in results:
            f.add_extras(cam, (extras or {}).get(cam) or {})
        f.finish(attrs)


class EvaluationFile:
    """``evaluation.h5`` written in steps (:func:`write_evaluation_h5`'s layout and order), so
    that each camera's maps can be written as soon as the camera is evaluated while the others
    and the joint surface fit are still computing (issue 25, item 1).

    Call :meth:`add_camera` per camera (in camera order), then :meth:`add_extras` per camera,
    then :meth:`finish` with the file attributes (known only at the end: warnings, anchors);
    use as a context manager (the file is closed also on an exception). The file tracks creation
    order, links and attributes separately, so the file attributes written last list in the same
    order as when they were written first (the camera groups list by name)."""

    def __init__(self, path: str | Path):
        self._f = h5py.File(path, "w", track_order=True)

    def __enter__(self) -> "EvaluationFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._f.id.valid:
            self._f.close()

    def add_camera(self, cam: str, decoded, reg, rec) -> None:
        """The camera's group: the decoding's, registration's and reconstruction's maps and the
        reconstruction's attributes (:func:`write_evaluation_h5`)."""
        g = self._f.create_group(cam)
        data = {"screen_xy_mm": decoded.screen_xy_mm, "std_xy_mm": decoded.std_xy_mm, "decoded": decoded.valid,
                "phase_flags": decoded.flags, "reversed_contrast": getattr(decoded, "reversed", None),
                "registration_status": reg.status, "normals": rec.n_sample,
                "points_mm": rec.p_sample_mm, "height_mm": rec.height_mm, "reconstructed": rec.reconstructed}
        if data["reversed_contrast"] is None:  # a decoded-like object without it
            del data["reversed_contrast"]
        self.add_extras(cam, data)
        g.attrs["method"] = rec.method
        g.attrs["seed_pixel"] = list(rec.seed_pixel)
        g.attrs["converged"] = bool(rec.converged)
        g.attrs["iterations"] = int(rec.iterations)

    def add_extras(self, cam: str, extras: dict) -> None:
        """Further (H, W[, k]) maps of camera ``cam`` by name (units from the name's suffix)."""
        g = self._f[cam]
        for name, arr in extras.items():
            units, long_name, frame = _EVALUATION.get(name, (_units_of(name), name.replace("_", " "), "sample"))
            _put(g, name, arr, units=units, long_name=long_name, frame=frame)

    def finish(self, attrs: dict[str, Any]) -> None:
        """The file attributes (``attrs``, then the flag and status codes); closes the file."""
        from ..evaluation.phase import PhaseFlag
        from ..evaluation.registration import RegistrationStatus

        _file_attrs(self._f, attrs)
        self._f.attrs["phase_flags"] = json.dumps({fl.name: int(fl) for fl in PhaseFlag})
        self._f.attrs["registration_status"] = json.dumps({s.name: int(s) for s in RegistrationStatus})
        self.close()


def append_stereo_h5(path: str | Path, stereo, attrs: dict[str, Any]) -> None:
    """Add a stereo evaluation's agreement report to an ``evaluation.h5`` written by
    :func:`write_evaluation_h5` (issue 14). Per camera group: ``overlap`` (bool, pixels a
    partner camera sees), ``normal_disagreement_urad`` ((H, W), angle between the cameras' implied
    normals, NaN outside the overlap), ``height_discrepancy_um`` ((H, W), z_this − z_partner along
    this camera's ray), ``anchor_pixels`` ((n, 2) row, column; dimensions ``anchor``,
    ``pixel_axis``), ``anchor_height_mm``, ``anchor_residual_urad``, ``anchor_fit_um`` and, with σ, ``anchor_height_std_um`` ((n,));
    file attributes ``stereo`` = True and ``attrs``."""
    with h5py.File(path, "a") as f:
        f.attrs["stereo"] = True
        for k, v in attrs.items():
            f.attrs[k] = json.dumps(v) if isinstance(v, (list, dict, tuple)) else v
        for cam, c in stereo.cameras.items():
            g = f.require_group(cam)
            _put(g, "overlap", c.overlap, units="1", long_name="pixel seen by a partner camera (bool)")
            _put(g, "normal_disagreement_urad", c.normal_disagreement_urad.astype(np.float32), units="urad",
                 long_name="angle between this camera's and the partner's implied normals")
            _put(g, "height_discrepancy_um", c.height_discrepancy_um.astype(np.float32), units="um", frame="sample",
                 long_name="z_this - z_partner along this camera's view ray")
            n = len(c.anchor_height_mm)
            anchor = _scale(g, "anchor", np.arange(n, dtype=np.int32), "1", "anchor index")
            axis = _scale(g, "pixel_axis", np.array(["v", "u"], dtype=object).astype(_STR), "1",
                          "pixel coordinate (v: row, u: column)")
            _put(g, "anchor_pixels", c.anchor_pixels.astype(np.int32), units="1", dims=[anchor, axis],
                 long_name="pixel (v, u) of each stereo anchor")
            _put(g, "anchor_height_mm", c.anchor_height_mm, units="mm", frame="sample", dims=[anchor],
                 long_name="absolute height found at the anchor")
            _put(g, "anchor_residual_urad", c.anchor_residual_urad, units="urad", dims=[anchor],
                 long_name="|g_this - g_partner| at the anchor")
            _put(g, "anchor_fit_um", c.anchor_fit_um, units="um", frame="sample", dims=[anchor],
                 long_name="reconstructed minus anchor height")
            if getattr(c, "anchor_height_std_um", None) is not None:
                _put(g, "anchor_height_std_um", c.anchor_height_std_um, units="um", frame="sample", dims=[anchor],
                     long_name="standard uncertainty (k = 1) of the anchor height")


def write_consistency_h5(path: str | Path, checks: dict, image_files: dict[str, list[str]]) -> None:
    """Add the consistency maps of :func:`pmdsim.evaluation.consistency.check_consistency` to an
    evaluation file (per camera group; the existing datasets are unchanged).

    Datasets per camera: ``consistency_flags`` (uint8, the FIT_RESIDUAL / PERIOD_MISMATCH /
    GEOMETRY bits of :class:`pmdsim.evaluation.phase.PhaseFlag`, also OR-ed into ``phase_flags``),
    ``fit_residual_ratio`` and ``period_mismatch_ratio`` (float32, test statistic / threshold:
    > 1 is flagged, NaN where not tested) and ``worst_image`` (int16, index into the group
    attribute ``consistency_images`` — the file name(s) of the image with the largest residual,
    ``a|b|c|d`` when a 4-shift period cannot tell which — or −1).
    """
    with h5py.File(path, "a") as f:
        for cam, c in checks.items():
            g = f[cam]
            _put(g, "consistency_flags", c.flags, units="1", long_name="consistency flags (PhaseFlag bits)")
            _put(g, "fit_residual_ratio", c.fit_residual_ratio, units="1",
                 long_name="fringe-fit residual / threshold (> 1 flagged; NaN where not tested)")
            _put(g, "period_mismatch_ratio", c.period_mismatch_ratio, units="1",
                 long_name="period mismatch / threshold (> 1 flagged; NaN where not tested)")
            _put(g, "worst_image", c.worst_image, units="1",
                 long_name="index into consistency_images of the worst-fitting image, or -1")
            g.attrs["consistency_images"] = json.dumps(image_files[cam])
            g.attrs["consistency_false_alarm"] = c.false_alarm
            g.attrs["consistency_noise_model"] = json.dumps(list(c.noise_model))
            g.attrs["consistency_reasons"] = json.dumps(c.reasons())
