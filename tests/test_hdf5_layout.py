"""Self-describing HDF5 outputs (issue 23 item 1): every file pmdsim writes opens in xarray
(h5netcdf, an independent reader of HDF5 dimension scales) with named dimensions and no warning;
every dataset has ``units`` from the list documented in docs/conventions.md, a ``long_name``;
parameters are attributes, not group names."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

xr = pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")

import pmdsim  # noqa: E402
from pmdsim.io import hdf5  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def documented_units() -> set[str]:
    """The units list as docs/conventions.md states it (not the code's own constant)."""
    text = (ROOT / "docs" / "conventions.md").read_text(encoding="utf-8")
    line = re.search(r"UDUNITS-2 string from this list:\s*\n?\s*(.+?)\(", text, re.S).group(1)
    return set(re.findall(r"`([^`]+)`", line))


def open_tree(path):
    """xarray's datatree of ``path``, failing on any warning (phony dims, undecodable types)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_datatree(path, engine="h5netcdf")


def check_file(path, units=None) -> dict:
    """Every variable of every group: named dims, units from the documented list, a long_name.
    Returns {group path: Dataset}."""
    units = documented_units() if units is None else units
    assert documented_units() == set(hdf5.UNITS)
    tree = open_tree(path)
    groups = {}
    with h5py.File(path) as f:
        n_datasets = []
        f.visititems(lambda n, o: n_datasets.append(n) if isinstance(o, h5py.Dataset) else None)
    seen = 0
    for node in tree.subtree:
        ds = node.to_dataset()
        groups[node.path] = ds
        for name, v in ds.variables.items():
            seen += name in node.variables and not name.startswith("_")
            assert not any(str(d).startswith("phony") for d in v.dims), (node.path, name, v.dims)
            assert v.attrs.get("units") in units, (node.path, name, v.attrs.get("units"))
            assert v.attrs.get("long_name"), (node.path, name)
    assert seen >= len(n_datasets) // 2  # xarray saw the file's datasets (coords are counted once)
    return groups


@pytest.fixture(scope="module")
def sim_eval(small_bulge3_evaluated):
    """The small setup simulated with Δh = 3 mm and evaluated (tests/conftest.py: shared with
    tests/test_evaluate.py)."""
    return small_bulge3_evaluated


def test_mapping_h5_opens_with_named_dims(sim_eval):
    sim, _ = sim_eval
    g = check_file(sim / "mapping.h5")["/left"]
    assert g["screen_xy_mm"].dims == ("v", "u", "component_xy")
    assert list(g["component_xy"].values) == ["x", "y"]
    assert g["screen_xy_mm"].attrs["frame"] == "screen" and g["screen_xy_mm"].attrs["units"] == "mm"
    assert g["valid"].dims == ("v", "u") and g.sizes["v"] == 60 and g.sizes["u"] == 96
    # the coordinates are the pixel indices of docs/conventions.md
    assert np.array_equal(g["u"].values, np.arange(96)) and np.array_equal(g["v"].values, np.arange(60))
    with h5py.File(sim / "mapping.h5") as f:  # same numbers as h5py reads
        np.testing.assert_array_equal(g["screen_xy_mm"].values, f["left/screen_xy_mm"][()])


def test_evaluation_h5_opens_with_named_dims_and_open_evaluation(sim_eval):
    _, ev = sim_eval
    groups = check_file(ev / "evaluation.h5")
    left = groups["/left"]
    assert left["normals"].dims == ("v", "u", "component")
    assert left["height_mm"].attrs["frame"] == "sample" and left["height_mm"].attrs["units"] == "mm"
    assert left["fit_residual_ratio"].attrs["units"] == "1"
    # issue 20: the decoder's contrast-reversal map, per direction (none in ideal images).
    assert left["reversed_contrast"].dims == ("v", "u", "component_xy")
    assert left["reversed_contrast"].dtype == bool and not left["reversed_contrast"].values.any()
    ds = pmdsim.open_evaluation(ev / "evaluation.h5")
    assert isinstance(ds, xr.Dataset)
    assert ds["height_mm"].dims == ("camera", "v", "u") and list(ds["camera"].values) == ["left", "right"]
    with h5py.File(ev / "evaluation.h5") as f:
        np.testing.assert_array_equal(ds["height_mm"].sel(camera="right").values, f["right/height_mm"][()])
        assert ds.attrs["pmdsim_version"] == f.attrs["pmdsim_version"]
    with h5py.File(ev / "evaluation.h5") as f:  # the storage docs/benchmarks.md chose: standard filters only
        assert f["left/height_mm"].compression is None and f["left/height_mm"].chunks[1:] == (96,)
        assert f["left/decoded"].compression == "gzip" and f["left/decoded"].shuffle
    one = pmdsim.open_evaluation(ev / "evaluation.h5", camera="right")
    assert one["screen_xy_mm"].dims == ("v", "u", "component_xy") and one.attrs["camera"] == "right"
    with pytest.raises(pmdsim.PmdsimError, match="no camera 'middle'"):
        pmdsim.open_evaluation(ev / "evaluation.h5", camera="middle")
    with pytest.raises(pmdsim.PmdsimError, match="not an evaluation.h5"):
        pmdsim.open_evaluation(_sim_mapping(ev))


def _sim_mapping(ev):
    return ev.parent / "sim" / "mapping.h5"


def test_stereo_append_opens_with_named_dims(tmp_path):
    H, W, n = 6, 8, 4
    rng = np.random.default_rng(0)
    res = {c: (SimpleNamespace(screen_xy_mm=rng.random((H, W, 2)), std_xy_mm=rng.random((H, W, 2)),
                               valid=np.ones((H, W), bool), flags=np.zeros((H, W), np.uint8)),
               SimpleNamespace(status=np.zeros((H, W), np.uint8)),
               SimpleNamespace(n_sample=rng.random((H, W, 3)), p_sample_mm=rng.random((H, W, 3)),
                               height_mm=rng.random((H, W)), reconstructed=np.ones((H, W), bool), method="stereo",
                               seed_pixel=(1, 2), converged=True, iterations=3)) for c in ("left", "right")}
    path = tmp_path / "evaluation.h5"
    hdf5.write_evaluation_h5(path, res, {"pmdsim_version": "x"})
    cams = {c: SimpleNamespace(overlap=np.ones((H, W), bool), normal_disagreement_urad=rng.random((H, W)),
                               height_discrepancy_um=rng.random((H, W)),
                               anchor_pixels=rng.integers(0, 6, (k, 2)), anchor_height_mm=rng.random(k),
                               anchor_residual_urad=rng.random(k), anchor_fit_um=rng.random(k))
            for c, k in zip(res, (n, n + 2))}
    hdf5.append_stereo_h5(path, SimpleNamespace(cameras=cams), {"stride_px": 4})
    g = check_file(path)["/left"]
    assert g["anchor_pixels"].dims == ("anchor", "pixel_axis") and list(g["pixel_axis"].values) == ["v", "u"]
    assert g["normal_disagreement_urad"].attrs["units"] == "urad" and g["anchor_fit_um"].attrs["units"] == "um"
    ds = pmdsim.open_evaluation(path)  # anchors of different counts per camera: padded, not refused
    assert ds.sizes["anchor"] == n + 2 and np.isnan(ds["anchor_fit_um"].sel(camera="left").values[n:]).all()
    np.testing.assert_array_equal(ds["anchor_fit_um"].sel(camera="right").values, cams["right"].anchor_fit_um)


def _case(camera, bulge, rng, H=5, W=7):
    rec = {"bulge_mm": bulge, "camera": camera, "max_height_diff_um": 1.0}
    return SimpleNamespace(camera=camera, bulge_mm=bulge, height_mm=rng.random((H, W)),
                           height_error_mm=rng.random((H, W)), p_sample_mm=rng.random((H, W, 3)),
                           reconstructed=np.ones((H, W), bool), as_record=lambda: rec)


def test_heights_h5_parameters_are_attributes(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "heights.h5"
    with hdf5.reconstructions_h5(path, {"pmdsim_version": "x"}) as add:
        for scenario, model in (("bulge", "planar"), ("bulge", "3x3"), ("offcentre", "3x3")):
            for cam in ("left", "right"):
                add(_case(cam, 3.0, rng), {"scenario": scenario, "bulge_mm": 3.0, "screen_model": model})
    groups = check_file(path)
    assert set(groups) == {"/", "/case_000", "/case_001", "/case_002"} | {
        f"/case_00{k}/{c}" for k in range(3) for c in ("left", "right")}
    assert groups["/case_002/left"]["height_error_um"].attrs["units"] == "um"
    assert groups["/case_002/left"]["points_mm"].dims == ("v", "u", "component")
    with h5py.File(path) as f:
        found = {(p["scenario"], p["screen_model"], cam) for p, cam, _ in hdf5.case_groups(f)}
    assert found == {(s, m, c) for s, m in (("bulge", "planar"), ("bulge", "3x3"), ("offcentre", "3x3"))
                     for c in ("left", "right")}


def test_experiment1_heights_h5(tmp_path):
    """The default grouping (one case per Δh, attribute bulge_mm) and the explicit-group form the
    studies use (one group per camera)."""
    rng = np.random.default_rng(2)
    hdf5.write_reconstructions_h5(tmp_path / "heights.h5", [_case(c, b, rng) for b in (0.0, 3.0)
                                                            for c in ("left", "right")], {"a": 1})
    groups = check_file(tmp_path / "heights.h5")
    assert groups["/case_001"].attrs["bulge_mm"] == 3.0
    with h5py.File(tmp_path / "heights.h5") as f:  # archives: float maps gzip + shuffle
        d = f["case_001/left/height_error_um"]
        assert d.compression == "gzip" and d.shuffle
    with hdf5.reconstructions_h5(tmp_path / "case.h5", {}) as add:
        add(_case("left", 1.0, rng), group="left")
    assert set(check_file(tmp_path / "case.h5")) == {"/", "/left"}


def test_height_map_writer_opens_with_named_dims(tmp_path):
    from pmdsim.io.heightmap import write_height_map

    x, y = np.linspace(-10, 10, 7), np.linspace(-5, 5, 4)
    z = np.add.outer(y, x) * 1e-3
    p = write_height_map(tmp_path / "h.h5", x, y, z, units="um")
    g = check_file(p, units=documented_units() | {"um"})["/"]
    assert g["height"].dims == ("y_mm", "x_mm") and g["height"].attrs["units"] == "um"
    np.testing.assert_allclose(g["height"].values, z * 1e3)  # µm as declared
    np.testing.assert_array_equal(g["x_mm"].values, x)


def test_all_zero_maps_read_back_identical_without_written_chunks(tmp_path):
    """Maps of all-zero bits (0.0, False, 0) are stored without written chunks (HDF5's fill value
    0) and read back equal, with the same chunking and filters as written maps and +0.0 signs;
    −0.0, NaN and True are written as usual. xarray (h5netcdf) reads the same numbers."""
    rng = np.random.default_rng(3)
    maps = {"zero_um": np.zeros((70, 9)), "zero_xy_mm": np.zeros((70, 9, 2)), "off": np.zeros((70, 9), bool),
            "code": np.zeros((70, 9), np.uint8), "negzero_um": np.full((70, 9), -0.0),
            "nan_um": np.full((70, 9), np.nan), "on": np.ones((70, 9), bool), "noise_um": rng.normal(size=(70, 9)),
            "late_um": np.zeros((70, 9))}
    maps["late_um"][69, 8] = 1e-300  # zero up to the last element
    path = tmp_path / "z.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("cam")
        for name, a in maps.items():
            hdf5._put(g, name, a, units=hdf5._units_of(name), long_name=name)
    unwritten = {"zero_um", "zero_xy_mm", "off", "code"}
    with h5py.File(path) as f:
        for name, a in maps.items():
            d = f["cam"][name]
            got = d[()]
            assert got.dtype == a.dtype and got.shape == a.shape
            assert np.array_equal(got, a, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(a)), name
            assert (d.id.get_storage_size() == 0) == (name in unwritten), name
            assert d.chunks == (64,) + a.shape[1:], name
            assert d.compression == ("gzip" if a.dtype.kind in "biu" else None), name
    ds = check_file(path)["/cam"]
    np.testing.assert_array_equal(ds["zero_xy_mm"].values, maps["zero_xy_mm"])
    np.testing.assert_array_equal(ds["off"].values, maps["off"])
