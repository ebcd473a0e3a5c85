"""pmdsim's HDF5 outputs as xarray objects (optional extra ``pmdsim[xarray]``: xarray, h5netcdf).

The files are self-describing (:mod:`pmdsim.io.hdf5`), so xarray reads them directly —
``xarray.open_datatree(path, engine="h5netcdf")`` for any of them; :func:`open_evaluation` is
the one-call form for an ``evaluation.h5``.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import require_extra

__all__ = ["open_evaluation", "require_xarray"]


def require_xarray():
    """Import xarray (and check h5netcdf), or raise
    :class:`~pmdsim.errors.OptionalDependencyError` naming the extra that installs them."""
    require_extra("xarray", "xarray", "h5netcdf", feature="reading pmdsim's HDF5 files as xarray objects")
    import xarray

    return xarray


def open_evaluation(path, camera: str | None = None):
    """Open an ``evaluation.h5`` (``pmdsim evaluate``) as an :class:`xarray.Dataset`.

    Parameters
    ----------
    path : str or Path
        The file.
    camera : str, optional
        One camera's group: its maps on the dimensions ``v``, ``u`` (pixel indices) and
        ``component`` / ``component_xy``, the group's attributes as the Dataset's attributes.
        Default: every camera, stacked along a dimension ``camera`` (the cameras must have the
        same image size; for different sizes open them one by one, or use
        ``xarray.open_datatree(path, engine="h5netcdf")``); a stereo file's per-camera anchors
        are padded with NaN to the longest list.

    Returns
    -------
    xarray.Dataset
        Variables with their ``units``, ``long_name`` and ``frame`` attributes
        (docs/conventions.md, "HDF5 outputs"); the file's attributes (provenance, code tables)
        in ``attrs``, and with ``camera=None`` each camera's group attributes as the JSON
        attribute ``camera_attrs``. Loaded into memory (the file is closed on return).
    """
    xr = require_xarray()
    import h5py

    from ..errors import ImageSetError

    p = Path(path)
    try:
        with h5py.File(p, "r") as f:
            root = {k: _plain(v) for k, v in f.attrs.items()}
            cameras = [k for k, g in f.items() if isinstance(g, h5py.Group)]
    except OSError as exc:
        raise ImageSetError(f"{str(p)!r}: not a readable HDF5 file ({exc})") from None
    if not cameras or "phase_flags" not in root:
        raise ImageSetError(f"{str(p)!r}: not an evaluation.h5 written by pmdsim evaluate (no camera groups "
                            "or no phase_flags attribute)")
    if camera is not None and camera not in cameras:
        raise ImageSetError(f"{str(p)!r}: no camera {camera!r} (cameras: {', '.join(cameras)})")

    def load(cam):
        with xr.open_dataset(p, group=cam, engine="h5netcdf") as ds:
            return ds.load()

    if camera is not None:
        ds = load(camera)
        ds.attrs = {**root, **ds.attrs, "camera": camera}
        return ds
    parts = [load(c) for c in cameras]
    shapes = {(d.sizes["v"], d.sizes["u"]) for d in parts}
    if len(shapes) > 1:
        raise ImageSetError(f"{str(p)!r}: the cameras have different image sizes {sorted(shapes)}; open one with "
                            "open_evaluation(path, camera=NAME)")
    group_attrs = {c: {k: _plain(v) for k, v in d.attrs.items()} for c, d in zip(cameras, parts)}
    for d in parts:
        d.attrs = {}
    ds = xr.concat(parts, dim=xr.DataArray(cameras, dims="camera", name="camera"), data_vars="all",
                   coords="minimal", compat="override", join="outer", combine_attrs="override")
    ds["camera"].attrs.update(units="1", long_name="camera name in the setup")
    ds.attrs = {**root, "camera_attrs": json.dumps(group_attrs, default=str)}
    return ds


def _plain(v):
    """An attribute value as a plain Python value."""
    return v.tolist() if hasattr(v, "tolist") else v
