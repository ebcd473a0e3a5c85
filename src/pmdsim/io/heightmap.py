"""Height-map files of curved samples: HDF5, NPY and CSV (issue 14).

A setup's ``[sample] height_map = "file"`` names one of

* **HDF5** (``.h5``, ``.hdf5``): a 2-D dataset of heights ``z[j, i]`` (``height_map_dataset``;
  default: the file's only 2-D dataset) and its grid as 1-D datasets ``x_mm`` and ``y_mm``
  (``height_map_x_dataset``, ``height_map_y_dataset``), or the grid given in the setup;
* **NPY** (``.npy``): a 2-D array ``z[j, i]``; the grid in the setup (``height_map_x_mm``,
  ``height_map_y_mm``: one value per column / row, or [first, last] for even spacing);
* **CSV** (``.csv``): either columns with a header naming ``x``, ``y`` and ``z`` (one row per
  grid point; the points must form a complete rectilinear grid), or a plain matrix ``z[j, i]``
  (no header) with the grid in the setup.

Heights are in ``height_map_units`` (mm, um or m), grid coordinates in the file in
``height_map_grid_units`` (the setup's ``height_map_x_mm`` are mm). Rows are y, columns x;
heights along the sample's +z (away from the cameras; docs/conventions.md). Every problem
raises :class:`~pmdsim.errors.SetupError` naming the file.

:func:`load_setup` is :func:`pmdsim.setup.load_setup` with this reader plugged in.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import SetupError
from ..setup.sample_shape import HEIGHT_MAP_UNITS, HeightMapData, HeightMapSource
from ..setup.toml import load_setup as _load_setup
from ..setup.toml import parse_setup as _parse_setup

__all__ = ["read_height_map", "write_height_map", "load_setup", "parse_setup"]

_HDF5 = (".h5", ".hdf5")


def load_setup(path):
    """Read a setup TOML file, reading any ``[sample] height_map`` file relative to it."""
    return _load_setup(path, read_height_map=read_height_map)


def parse_setup(doc, *, source: str = "setup", base_dir=None):
    """:func:`pmdsim.setup.parse_setup` with this module's height-map reader."""
    return _parse_setup(doc, source=source, read_height_map=read_height_map, base_dir=base_dir)


def _setup_grid(src: HeightMapSource, name: str, n: int, path: Path) -> np.ndarray:
    g = src.x_mm if name == "x" else src.y_mm
    if g is None:
        raise SetupError(f"height map {str(path)!r} has no {name} grid: give sample.height_map_{name}_mm in the setup "
                         f"({n} values, or [first, last])")
    g = np.asarray(g, dtype=float)
    if g.size == 2 and n != 2:
        return np.linspace(g[0], g[1], n)
    if g.size != n:
        raise SetupError(f"sample.height_map_{name}_mm has {g.size} values, but {str(path)!r} has {n} "
                         f"{'columns' if name == 'x' else 'rows'}; expected {n} values or [first, last]")
    return g


def _read_hdf5(path: Path, src: HeightMapSource):
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise SetupError(f"cannot read height map {str(path)!r} as HDF5: {e}") from None
    with f:
        if src.dataset is None:
            two_d = []
            f.visititems(lambda n, o: two_d.append(n) if isinstance(o, h5py.Dataset) and o.ndim == 2 else None)
            if len(two_d) != 1:
                raise SetupError(f"height map {str(path)!r} has {len(two_d)} 2-D datasets ({two_d}); name the heights "
                                 f"with sample.height_map_dataset")
            name = two_d[0]
        else:
            name = src.dataset
        if name not in f or not isinstance(f[name], h5py.Dataset) or f[name].ndim != 2:
            raise SetupError(f"height map {str(path)!r} has no 2-D dataset {name!r} (sample.height_map_dataset)")
        z = np.asarray(f[name][()], dtype=float)
        scale = HEIGHT_MAP_UNITS[src.grid_units]
        grids = []
        for axis, key, n in (("x", src.x_key, z.shape[1]), ("y", src.y_key, z.shape[0])):
            if key in f:
                g = np.asarray(f[key][()], dtype=float).ravel() * scale
                if g.size != n:
                    raise SetupError(f"height map {str(path)!r}: dataset {key!r} has {g.size} values, the heights "
                                     f"{name!r} have {n} {'columns' if axis == 'x' else 'rows'}")
            else:
                g = _setup_grid(src, axis, n, path)
            grids.append(g)
    return grids[0], grids[1], z


def _read_csv(path: Path, src: HeightMapSource):
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as e:
        raise SetupError(f"cannot read height map {str(path)!r}: {e}") from None
    if not rows:
        raise SetupError(f"height map {str(path)!r} is empty")

    def numbers(rs, first_line):
        try:
            return np.array([[float(v) for v in r] for r in rs], dtype=float)
        except ValueError as e:
            raise SetupError(f"height map {str(path)!r}: a non-numeric value after line {first_line} ({e})") from None

    head = [c.strip().lower() for c in rows[0]]
    try:
        [float(c) for c in head]
        header = False
    except ValueError:
        header = True
    if not header:
        z = numbers(rows, 1)
        if z.ndim != 2 or len({len(r) for r in rows}) != 1:
            raise SetupError(f"height map {str(path)!r}: rows of different lengths; expected a matrix z[row = y, "
                             f"column = x] or x, y, z columns with a header")
        return _setup_grid(src, "x", z.shape[1], path), _setup_grid(src, "y", z.shape[0], path), z
    base = [c.split("_")[0].split("[")[0].split("(")[0].strip() for c in head]
    if not all(k in base for k in ("x", "y", "z")):
        raise SetupError(f"height map {str(path)!r}: header {rows[0]} must name columns x, y and z (e.g. "
                         f"'x_mm,y_mm,z'), or the file must be a plain matrix of heights")
    data = numbers(rows[1:], 2)
    if data.ndim != 2 or data.shape[0] == 0:
        raise SetupError(f"height map {str(path)!r} has a header but no data rows")
    cx, cy, cz = data[:, base.index("x")], data[:, base.index("y")], data[:, base.index("z")]
    scale = HEIGHT_MAP_UNITS[src.grid_units]
    xs, ix = np.unique(cx, return_inverse=True)
    ys, iy = np.unique(cy, return_inverse=True)
    z = np.full((ys.size, xs.size), np.nan)
    count = np.zeros(z.shape, dtype=int)
    np.add.at(count, (iy, ix), 1)
    z[iy, ix] = cz
    if np.any(count != 1):
        missing = int(np.sum(count == 0))
        raise SetupError(f"height map {str(path)!r}: the x, y points do not form a complete grid ({xs.size} x values "
                         f"× {ys.size} y values, {missing} points missing, {int(np.sum(count > 1))} repeated); "
                         f"expected one row per grid point")
    return xs * scale, ys * scale, z


def read_height_map(source: HeightMapSource | str | Path, base_dir=None, **keys) -> HeightMapData:
    """Read a height map (HDF5, NPY or CSV) into heights in mm on its grid in mm.

    Parameters
    ----------
    source : HeightMapSource, str or Path
        The file and its description (the setup's ``height_map*`` keys); a path with the
        description's fields as keywords (``dataset``, ``units``, ``grid_units``, ``x_key``,
        ``y_key``, ``x_mm``, ``y_mm``).
    base_dir : path or None
        Directory of relative file names (the setup file's).

    Returns
    -------
    HeightMapData
        Refused (SetupError naming the file) if it holds NaNs or an incomplete grid.
    """
    src = source if isinstance(source, HeightMapSource) else HeightMapSource(str(source), **keys)
    path = Path(src.file)
    if base_dir is not None and not path.is_absolute():
        path = Path(base_dir) / path
    if not path.is_file():
        raise SetupError(f"height map file {str(path)!r} does not exist (sample.height_map = {src.file!r})")
    ext = path.suffix.lower()
    if ext in _HDF5:
        x, y, z = _read_hdf5(path, src)
    elif ext == ".npy":
        try:
            z = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise SetupError(f"cannot read height map {str(path)!r} as NPY: {e}") from None
        if z.ndim != 2:
            raise SetupError(f"height map {str(path)!r} holds an array of shape {z.shape}; expected a 2-D z[y, x]")
        z = np.asarray(z, dtype=float)
        x, y = _setup_grid(src, "x", z.shape[1], path), _setup_grid(src, "y", z.shape[0], path)
    elif ext == ".csv":
        x, y, z = _read_csv(path, src)
    else:
        raise SetupError(f"height map {str(path)!r}: unknown format {ext!r}; expected .h5/.hdf5, .npy or .csv")
    return HeightMapData(x, y, z * HEIGHT_MAP_UNITS[src.units], source=repr(str(path)))


def write_height_map(path, x_mm, y_mm, z_mm, *, units: str = "mm", dataset: str = "height") -> Path:
    """Write heights ``z_mm[j, i]`` at (x_i, y_j) as HDF5 (grid datasets ``x_mm``, ``y_mm``),
    NPY (the matrix only: give the grid in the setup) or CSV (x_mm, y_mm, z columns), with the
    heights in ``units``. Returns the path."""
    p = Path(path)
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    z = np.asarray(z_mm, dtype=float) / HEIGHT_MAP_UNITS[units]
    ext = p.suffix.lower()
    if ext in _HDF5:
        import h5py

        with h5py.File(p, "w") as f:  # self-describing: units, long names, dimension scales (issue 23)
            scales = []
            for name, g, what in (("y_mm", y, "y"), ("x_mm", x, "x")):
                s = f.create_dataset(name, data=g)
                s.make_scale(name)
                s.attrs["units"] = "mm"
                s.attrs["long_name"] = f"{what} of the grid column/row in the sample frame"
                s.attrs["frame"] = "sample"
                scales.append(s)
            d = f.create_dataset(dataset, data=z)
            d.attrs["units"] = units
            d.attrs["long_name"] = "height along sample +z"
            d.attrs["frame"] = "sample"
            for axis, s in enumerate(scales):
                d.dims[axis].attach_scale(s)
    elif ext == ".npy":
        np.save(p, z)
    elif ext == ".csv":
        X, Y = np.meshgrid(x, y)
        with open(p, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["x_mm", "y_mm", f"z_{units}"])
            for a, b, c in zip(X.ravel(), Y.ravel(), z.ravel()):
                w.writerow([repr(float(a)), repr(float(b)), repr(float(c))])
    else:
        raise ValueError(f"unknown height-map format {ext!r}; expected .h5/.hdf5, .npy or .csv")
    return p
