"""Image sets of real instruments (issue 12, item 1): a declared intensity response applied
before decoding, 10/12-bit images in 16-bit files with per-pixel saturation, float TIFF,
multi-page TIFF stacks, masks, screen maps and the image-size check — all on real files
written with Pillow/tifffile/h5py, against the analytic pattern coordinates they encode."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from pmdsim.errors import ImageSetError
from pmdsim.evaluation.phase import PhaseFlag
from pmdsim.io.imageset import decode_camera, load_manifest

tifffile = pytest.importorskip("tifffile")

H, W = 24, 40
SCREEN = (100.0, 80.0)
PERIODS = {"x": (120.0, 10.0), "y": (100.0, 8.0)}
N = 4
A, B = 0.5, 0.4


def true_xy() -> np.ndarray:
    """A smooth, invertible pixel → pattern-coordinate field inside the screen (mm)."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x = 10.0 + 2.0 * u + 0.01 * u * v
    y = 8.0 + 2.5 * v + 0.005 * u**2
    return np.stack([x, y], axis=-1)


def display_levels(coord: np.ndarray, period: float, k: int) -> np.ndarray:
    """Commanded display level d = A + B cos(2π c/p − 2πk/N) (docs/conventions.md)."""
    return A + B * np.cos(2 * np.pi * coord / period - 2 * np.pi * k / N)


def write_set(d: Path, camera_level, *, bits: int = 12, fmt: str = "png", extra: dict | None = None,
              dtype=np.uint16, multipage: bool = False) -> dict:
    """Write the fringe images c = camera_level(d) quantised to ``bits`` and a manifest."""
    d.mkdir(parents=True, exist_ok=True)
    xy = true_xy()
    full = 2**bits - 1
    entries, pages = [], []
    for axis, direction in enumerate("xy"):
        for p in PERIODS[direction]:
            for k in range(N):
                c = camera_level(display_levels(xy[..., axis], p, k))
                img = (np.round(c * full).astype(dtype) if dtype != np.float32 else (c * full).astype(np.float32))
                name = f"{direction}_{p:g}_{k}.{fmt}"
                e = {"camera": "cam", "direction": direction, "period_mm": p, "shift_index": k}
                if multipage:
                    e.update(file="stack.tif", page=len(pages))
                    pages.append(img)
                else:
                    e["file"] = name
                    if fmt == "png":
                        Image.fromarray(img).save(d / name)
                    else:
                        tifffile.imwrite(d / name, img)
                entries.append(e)
    if multipage:
        tifffile.imwrite(d / "stack.tif", np.stack(pages))
    doc = {"format": "pmdsim-imageset", "format_version": 1, "screen_size_mm": list(SCREEN), "images": entries}
    if dtype != np.float32 and bits != 16 and bits != 8:
        doc["bit_depth"] = bits
    if dtype == np.float32:
        doc["full_scale"] = float(full)
    doc.update(extra or {})
    (d / "manifest.json").write_text(json.dumps(doc))
    return doc


def gamma_law(g):
    return lambda dl: np.asarray(dl) ** g


def coord_error(dec) -> float:
    ok = dec.valid
    assert ok.sum() > 0.9 * ok.size
    return float(np.abs(dec.screen_xy_mm[ok] - true_xy()[ok]).max())


# Bound on the quantisation error of the finest period (8 mm) at 12 bit: the N-step phase error
# ≤ √(2/N)·σ_I/B per sample-noise σ_I; with σ_I ≤ ½ LSB worst case and the gamma slope ≥ ~0.2 at
# d ≥ 0.1: |Δc| ≤ p/(2π)·(½/4095)/0.4/0.2·√2 ≈ 8/(2π)·2.2e-3 ≈ 2.8 µm; 10 µm is a loose cap that
# the unlinearised decode (mm-scale ripple) misses by far.
CAP_MM = 0.01


def test_gamma_response_linearises_12bit_images(tmp_path):
    d = tmp_path / "set"
    write_set(d, gamma_law(2.2), bits=12, extra={"response": {"gamma": 2.2}})
    m = load_manifest(d)
    assert m.bit_depth == 12 and m.instrument.response_info["kind"] == "gamma"
    err = coord_error(decode_camera(m, "cam"))
    assert err < CAP_MM, err
    # The same images without the declared response: the 4φ ripple of the gamma remains.
    doc = json.loads((d / "manifest.json").read_text())
    del doc["response"]
    (d / "manifest.json").write_text(json.dumps(doc))
    err_raw = coord_error(decode_camera(load_manifest(d), "cam"))
    # The ripple of an unlinearised γ = 2.2 (the 3rd and 5th harmonics alias into 4φ) is about
    # 11 µm at p = 8 mm here; linearised, only the quantisation error is left.
    assert err_raw > 5 * err, (err_raw, err)


def test_measured_series_from_sofast_style_h5_linear(tmp_path):
    """A grey-level series in an HDF5 file (SOFAST's ImageCalibration layout), piecewise-linear
    interpolation: images made with the piecewise-linear forward response decode exactly."""
    dv = np.linspace(0, 255, 27)
    cv = 2.0 + 250.0 * (dv / 255) ** 1.95
    d = tmp_path / "set"
    d.mkdir()
    with h5py.File(d / "cal.h5", "w") as f:
        f["ImageCalibration/display_values"] = dv
        f["ImageCalibration/camera_values"] = cv
    fwd = lambda dl: np.interp(dl, dv / 255, cv / 255)  # noqa: E731
    write_set(d, fwd, bits=16, extra={"response": {"file": "cal.h5", "display_full_scale": 255,
                                                   "camera_full_scale": 255, "interpolation": "linear"}})
    m = load_manifest(d)
    assert m.instrument.response_info["interpolation"] == "linear"
    assert coord_error(decode_camera(m, "cam")) < 1e-3


def test_saturation_flagged_per_pixel_at_declared_12bit_maximum(tmp_path):
    d = tmp_path / "set"
    write_set(d, lambda dl: np.asarray(dl), bits=12)
    img = np.array(Image.open(d / "x_10_0.png"))
    img[3, 5] = 4095           # at the declared maximum: saturated
    img[4, 6] = 4094           # one below: fine
    Image.fromarray(img).save(d / "x_10_0.png")
    dec = decode_camera(load_manifest(d), "cam")
    assert dec.flags[3, 5] & PhaseFlag.SATURATED and not dec.valid[3, 5]
    assert not dec.flags[4, 6] & PhaseFlag.SATURATED
    assert int((dec.flags & PhaseFlag.SATURATED).astype(bool).sum()) == 1
    # With a response declared, the same pixel is still flagged (linearisation path).
    doc = json.loads((d / "manifest.json").read_text())
    doc["response"] = {"gamma": 1.0}
    (d / "manifest.json").write_text(json.dumps(doc))
    dec = decode_camera(load_manifest(d), "cam")
    assert dec.flags[3, 5] & PhaseFlag.SATURATED and int((dec.flags & PhaseFlag.SATURATED).astype(bool).sum()) == 1


def test_values_beyond_declared_bit_depth_refused(tmp_path):
    d = tmp_path / "set"
    write_set(d, lambda dl: np.asarray(dl), bits=12)
    img = np.array(Image.open(d / "y_8_2.png"))
    img[0, 0] = 4096
    Image.fromarray(img).save(d / "y_8_2.png")
    with pytest.raises(ImageSetError, match=r"y_8_2.png.*4096.*12-bit range 0 … 4095"):
        decode_camera(load_manifest(d), "cam")


def test_float32_tiff_equals_integer_decode(tmp_path):
    write_set(tmp_path / "f", gamma_law(1.0), bits=12, fmt="tif", dtype=np.float32)
    write_set(tmp_path / "i", gamma_law(1.0), bits=12, fmt="tif")
    mf = load_manifest(tmp_path / "f")
    assert mf.instrument.full_scale == 4095.0
    dec_f = decode_camera(mf, "cam")
    dec_i = decode_camera(load_manifest(tmp_path / "i"), "cam")
    assert tifffile.imread(tmp_path / "f" / "x_10_0.tif").dtype == np.float32
    np.testing.assert_array_equal(dec_f.valid, dec_i.valid)
    # Float images are unquantised: closer to the truth than the 12-bit ones.
    assert coord_error(dec_f) < 1e-6 < coord_error(dec_i) < CAP_MM


def test_multipage_tiff_pages_read_and_refused_without_page(tmp_path):
    write_set(tmp_path / "m", gamma_law(1.0), bits=16, fmt="tif", multipage=True)
    write_set(tmp_path / "s", gamma_law(1.0), bits=16, fmt="tif")
    dec_m = decode_camera(load_manifest(tmp_path / "m"), "cam")
    dec_s = decode_camera(load_manifest(tmp_path / "s"), "cam")
    np.testing.assert_array_equal(dec_m.screen_xy_mm, dec_s.screen_xy_mm)
    doc = json.loads((tmp_path / "m" / "manifest.json").read_text())
    for e in doc["images"]:
        del e["page"]
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(doc))
    # Without 'page' the entries repeat one file: refused before any image is read …
    with pytest.raises(ImageSetError, match="repeats"):
        load_manifest(tmp_path / "m")
    # … and a single entry pointing at the stack is refused when read (never page 0 silently).
    doc["images"][0]["file"] = "stack.tif"
    for i, e in enumerate(doc["images"][1:], 1):
        e["file"] = f"{e['direction']}_{e['period_mm']:g}_{e['shift_index']}.tif"
        tifffile.imwrite(tmp_path / "m" / e["file"], tifffile.imread(tmp_path / "m" / "stack.tif", key=i))
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ImageSetError, match=r"stack.tif.*multi-page file with 16 pages.*'page'"):
        decode_camera(load_manifest(tmp_path / "m"), "cam")
    doc["images"][0]["page"] = 16
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ImageSetError, match=r"'page' = 16 is out of range \(the file has 16 page"):
        decode_camera(load_manifest(tmp_path / "m"), "cam")


def test_image_size_differs_from_setup(tmp_path):
    write_set(tmp_path / "s", gamma_law(1.0), bits=8, dtype=np.uint8)
    m = load_manifest(tmp_path / "s")
    with pytest.raises(ImageSetError, match=r"40×24 px \(W×H\), but the setup's cameras.cam.image_size_px is 1626×1236"):
        decode_camera(m, "cam", expected_size_px=(1626, 1236))
    assert decode_camera(m, "cam", expected_size_px=(W, H)).valid.any()


def test_mask_and_screen_map(tmp_path):
    d = tmp_path / "s"
    mask = np.zeros((H, W), np.uint8)
    mask[2:-2, 3:-3] = 255
    d.mkdir()
    Image.fromarray(mask).save(d / "mask.png")
    # A map that mirrors y and shifts x (an affine map: linear interpolation is exact on it).
    pat = np.array([[0, 0], [100, 0], [0, 80], [100, 80]], float)
    scr = np.stack([pat[:, 0] + 5.0, 80.0 - pat[:, 1]], axis=-1)
    write_set(d, gamma_law(1.0), bits=16, extra={"mask": {"file": "mask.png"},
                                                 "screen_map": {"pattern_xy_mm": pat.tolist(),
                                                                "screen_xy_mm": scr.tolist()}})
    dec = decode_camera(load_manifest(d), "cam")
    np.testing.assert_array_equal(dec.valid, mask > 0)
    assert (dec.flags[mask == 0] & PhaseFlag.DARK).all()
    t = true_xy()[dec.valid]
    np.testing.assert_allclose(dec.screen_xy_mm[dec.valid], np.stack([t[:, 0] + 5, 80 - t[:, 1]], -1), atol=1e-3)


@pytest.mark.parametrize("response, needle", [
    ({"gamma": 2.2, "file": "x.json"}, "exactly one of"),
    ({"gamma": "2"}, "response.gamma"),
    ({"display_levels": [0, 0.5, 1], "camera_levels": [0, 0.6, 0.5]}, "strictly increasing"),
    ({"file": "missing.h5"}, "does not exist"),
    ({"gamma": 2.0, "interpolation": "cubic"}, "'pchip' or 'linear'"),
    ({"gamma": 2.0, "shape": 1}, "unknown key"),
])
def test_bad_response_declarations(tmp_path, response, needle):
    write_set(tmp_path / "s", gamma_law(1.0), bits=8, extra={"response": response})
    with pytest.raises(ImageSetError, match="response") as ei:
        load_manifest(tmp_path / "s")
    assert needle in str(ei.value)


def test_declared_integration_method(tmp_path):
    """A manifest may name the integration ``pmdsim evaluate`` uses by default; anything but
    the two methods is refused naming the key."""
    write_set(tmp_path / "a", gamma_law(1.0), bits=8, extra={"method": "least_squares"})
    assert load_manifest(tmp_path / "a").instrument.method == "least_squares"
    write_set(tmp_path / "b", gamma_law(1.0), bits=8)
    assert load_manifest(tmp_path / "b").instrument.method is None
    write_set(tmp_path / "c", gamma_law(1.0), bits=8, extra={"method": "simpson"})
    with pytest.raises(ImageSetError, match="key 'method' must be 'stepwise' or 'least_squares', got 'simpson'"):
        load_manifest(tmp_path / "c")


def test_screen_map_sigma_up_to_the_maps_edge():
    """σ through a screen map is the map's local scale times the decoder's σ at every pixel
    the map covers, including the last step of pattern coordinates before the map's edge, where
    a forward difference would leave the map (a backward one is taken there). Closed form: an
    affine map screen = A·pattern + b scales σ_x, σ_y by the columns of A."""
    from pmdsim.evaluation.decoding import ScreenCoordinates
    from pmdsim.io.imageset_instrument import ScreenMap, apply_mask_and_map

    A = np.array([[1.25, 0.0], [0.0, 0.8]])
    pat = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 80.0], [100.0, 80.0]])
    smap = ScreenMap(pat, pat @ A.T + [3.0, -2.0])
    h = 1e-3 * 100.0  # apply_mask_and_map's step for this map
    x = np.array([[10.0, 50.0, 100.0 - h / 2, 100.0]])  # the last two within h of the right edge
    y = np.array([[40.0, 80.0 - h / 3, 40.0, 80.0]])  # the second and last within h of the top
    xy = np.stack([x, y], axis=-1)
    std = np.stack([np.full_like(x, 0.02), np.full_like(x, 0.03)], axis=-1)
    shape = x.shape
    dec = ScreenCoordinates(screen_xy_mm=xy, valid=np.ones(shape, bool), flags=np.zeros(shape, np.uint8),
                            std_xy_mm=std, modulation=np.ones(shape), offset=np.ones(shape))
    out = apply_mask_and_map(dec, screen_map=smap)
    np.testing.assert_allclose(out.screen_xy_mm, xy @ A.T + [3.0, -2.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.std_xy_mm[..., 0], 1.25 * 0.02, rtol=1e-9)
    np.testing.assert_allclose(out.std_xy_mm[..., 1], 0.8 * 0.03, rtol=1e-9)
