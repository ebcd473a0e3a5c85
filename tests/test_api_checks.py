"""The notebook API checks what the CLI checks (issue 23 item 2): every misuse raises a
PmdsimError subclass naming the argument; images are validated against the bit depth; evaluate
warns with ConsistencyWarning; setups are hashable values; results are read-only; reprs fit a
screen; dir(pmdsim) is the public API."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

import pmdsim
from pmdsim.errors import ImageSetError, InputError, InputTypeError, PmdsimError, SetupError, UnknownCameraError
from pmdsim.evaluation.phase import PhaseFlag, ScreenCoordinates


@pytest.fixture(scope="module")
def setup(small_toml):
    import tomllib

    return pmdsim.parse_setup(tomllib.loads(small_toml))


@pytest.fixture(scope="module")
def measured(setup):
    return pmdsim.simulate(setup, "left")


def _images(setup, dtype=np.uint8, shape=(60, 96), n=None):
    seq = setup.patterns.sequence
    n = seq.n_shifts if n is None else n
    keys = [("x", p) for p in seq.periods_x_mm] + [("y", p) for p in seq.periods_y_mm]
    return {k: np.zeros((n, *shape), dtype) for k in keys}


def _coords(shape=(60, 96)):
    nan = np.full((*shape, 2), np.nan)
    z = np.zeros(shape)
    return ScreenCoordinates(nan, np.zeros(shape, bool), np.zeros(shape, np.uint8), nan, z, z)


# (call, expected PmdsimError subclass, words the message must name) — the misuse cases.
MISUSES = {
    "simulate: unknown camera": (lambda s: pmdsim.simulate(s, "middle"), UnknownCameraError, "cameras: left, right"),
    "simulate: camera not a name": (lambda s: pmdsim.simulate(s, 0), InputTypeError, "camera name"),
    "simulate: path instead of a Setup": (lambda s: pmdsim.simulate("setup.toml", "left"), InputTypeError, "Setup"),
    "decode: a list of images": (lambda s: pmdsim.decode([np.zeros((4, 6, 8))], s), InputTypeError, "dict"),
    "decode: missing stack": (lambda s: pmdsim.decode({k: v for k, v in list(_images(s).items())[1:]}, s),
                              ImageSetError, "no stack for"),
    "decode: wrong number of shifts": (lambda s: pmdsim.decode(_images(s, n=3), s), ImageSetError, "n_shifts"),
    "decode: stacks of different sizes": (
        lambda s: pmdsim.decode({**_images(s), ("y", s.patterns.sequence.periods_y_mm[0]): np.zeros((4, 5, 5), np.uint8)},
                                s), ImageSetError, "differs"),
    "decode: 2-D image instead of a stack": (
        lambda s: pmdsim.decode({k: v[0] for k, v in _images(s).items()}, s), ImageSetError, "(4, H, W)"),
    "decode: floats without a scale": (lambda s: pmdsim.decode(_images(s, np.float32), s), InputError, "scale="),
    "decode: uint16 with an 8-bit setup": (lambda s: pmdsim.decode(_images(s, np.uint16), s), InputError,
                                           "bit_depth"),
    "decode: signed integers": (lambda s: pmdsim.decode(_images(s, np.int32), s), InputTypeError, "uint8 or uint16"),
    "decode: a scale for integer images": (lambda s: pmdsim.decode(_images(s), s, scale=255), InputError, "float"),
    "decode: images of another size than the camera": (
        lambda s: pmdsim.decode(_images(s, shape=(50, 96)), s, camera="left"), ImageSetError, "96×60"),
    "decode: unknown camera": (lambda s: pmdsim.decode(_images(s), s, camera="middle"), UnknownCameraError, "middle"),
    "evaluate: not ScreenCoordinates": (lambda s: pmdsim.evaluate(np.zeros((60, 96, 2)), s, "left"), InputTypeError,
                                        "ScreenCoordinates"),
    "evaluate: unknown camera": (lambda s: pmdsim.evaluate(_coords(), s, "centre"), UnknownCameraError, "centre"),
    "evaluate: maps of another size": (lambda s: pmdsim.evaluate(_coords((30, 48)), s, "left"), InputError, "48×30"),
    "evaluate: unknown screen": (lambda s: pmdsim.evaluate(_coords(), s, "left", screen="curved"), InputError,
                                 "'planar' or 'setup'"),
    "evaluate: unknown method": (lambda s: pmdsim.evaluate(_coords(), s, "left", method="frankot"), InputError,
                                 "'stepwise' or 'least_squares'"),
    "evaluate: seed pixel outside the image": (lambda s: pmdsim.evaluate(_coords(), s, "left", seed_pixel=(60, 10)),
                                               InputError, "outside"),
    "evaluate: non-finite seed height": (lambda s: pmdsim.evaluate(_coords(), s, "left", seed_height_mm=np.nan),
                                         InputError, "finite"),
    "evaluate_stereo: one camera": (lambda s: pmdsim.evaluate_stereo({"left": _coords()}, s), InputError,
                                    "at least two"),
    "calibrate: nominal of a wrong type": (lambda s: pmdsim.calibrate([object()], "setup.toml"), InputTypeError,
                                           "CalibrationState"),
    "with_camera: unknown camera": (lambda s: s.with_camera("middle", focal_length_px=(1, 1)), SetupError, "middle"),
}


@pytest.mark.parametrize("case", list(MISUSES))
def test_misuse_raises_a_pmdsim_error_naming_the_fix(setup, case):
    call, kind, words = MISUSES[case]
    with pytest.raises(kind) as info:
        call(setup)
    assert isinstance(info.value, PmdsimError)
    assert words in str(info.value), str(info.value)
    assert "\n" not in str(info.value)


def test_unknown_camera_is_still_a_key_error(setup):
    with pytest.raises(KeyError):  # scripts that caught KeyError keep working
        pmdsim.simulate(setup, "middle")


def test_float_and_uint16_images_decode_like_the_grey_levels(setup, measured):
    """Float images in [0, 1] with scale=255, and 16-bit images of a 16-bit setup, decode to the
    true mapping as the uint8 images do (reference: the traced mapping)."""
    truth = measured.mapping.screen_xy_mm
    ref = pmdsim.decode(measured, setup)
    as_float = {k: v / 255.0 for k, v in measured.images.items()}
    dec_f = pmdsim.decode(as_float, setup, scale=255.0)
    # 8-bit grey levels × 257 in a 16-bit setup: declare their quantisation noise (257/√12), or the
    # consistency checks rightly find the periods disagreeing beyond the 16-bit σ
    s16 = setup.with_patterns(bit_depth=16, noise_std=257 / np.sqrt(12.0))
    dec_16 = pmdsim.decode({k: v.astype(np.uint16) * 257 for k, v in measured.images.items()}, s16)
    n_true = np.count_nonzero(measured.mapping.valid)
    for d in (ref, dec_f, dec_16):
        assert np.count_nonzero(d.valid) > 0.9 * n_true
        ok = d.valid & measured.mapping.valid
        assert np.nanmax(np.abs(d.screen_xy_mm[ok] - truth[ok])) < 0.05  # mm: a fraction of the finest 4 mm period
    np.testing.assert_array_equal(dec_f.valid, ref.valid)


def test_evaluate_warns_and_flags_a_dropped_frame(setup, measured):
    """A frame of the finest x period replaced by its neighbour in a band of columns (a torn,
    partly dropped frame): those pixels are flagged, evaluate warns with ConsistencyWarning (as
    the CLI does) and reconstructs the rest."""
    p = setup.patterns.sequence.periods_x_mm[-1]
    bad = dict(measured.images)
    stack = bad[("x", p)].copy()
    stack[2, :, :12] = stack[1, :, :12]
    bad[("x", p)] = stack
    with pytest.warns(pmdsim.ConsistencyWarning, match="consistency"):
        ev = pmdsim.evaluate(bad, setup, "left", seed_pixel=(30, 48))
    flagged = ev.flags != 0
    torn = np.zeros(flagged.shape, bool)
    torn[:, :12] = True
    assert flagged[torn & measured.mapping.valid].mean() > 0.9  # the torn band is found …
    assert flagged[~torn].mean() < 0.05  # … and little else
    assert not ev.reconstructed[flagged].any()
    assert ev.reconstructed[~torn].mean() > 0.9
    with warnings.catch_warnings():
        warnings.simplefilter("error", pmdsim.ConsistencyWarning)
        good = pmdsim.evaluate(measured, setup, "left", seed_pixel=(30, 48))  # clean images: no warning
    assert good.reconstructed.sum() > 0.9 * np.count_nonzero(measured.mapping.valid)


def test_results_are_read_only_and_reprs_fit_a_screen(setup, measured):
    ev = pmdsim.evaluate(pmdsim.decode(measured, setup, camera="left"), setup, "left")
    arrays = [measured.mapping.screen_xy_mm, *measured.images.values(), ev.height_mm, ev.flags,
              ev.registration.q_ref_mm, ev.decoded.screen_xy_mm]
    for a in arrays:
        with pytest.raises(ValueError, match="read-only"):
            a[(0,) * a.ndim] = 0
    for obj in (measured, ev, ev.decoded, ev.reconstruction, ev.registration, measured.mapping, setup):
        text = repr(obj)
        assert len(text.splitlines()) <= 1 and len(text) < 2000, (type(obj).__name__, len(text))


def test_setup_is_deeply_immutable_and_hashable(setup):
    import tomllib

    assert hash(setup) == hash(pmdsim.parse_setup(tomllib.loads(setup.to_toml())))
    assert setup.with_camera("left", focal_length_px=(221.0, 221.0)) not in {setup}
    assert setup.cameras["left"].camera.width_px == 96 and list(setup.cameras) == ["left", "right"]
    with pytest.raises(TypeError):
        setup.cameras["left"] = setup.cameras["right"]
    with pytest.raises(AttributeError):
        setup.cameras.clear()
    import pickle

    assert pickle.loads(pickle.dumps(setup)) == setup


def test_dir_is_the_public_api():
    names = dir(pmdsim)
    assert not {"os", "sys", "importlib"} & set(names)
    assert all(not n.startswith("_") or n == "__version__" for n in names)
    assert names == sorted(pmdsim.__all__)
    for n in names:
        assert getattr(pmdsim, n) is not None


def test_python_dash_m_pmdsim():
    r = subprocess.run([sys.executable, "-m", "pmdsim", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"pmdsim, version {pmdsim.__version__}"


@pytest.mark.parametrize("kind, radius_mm", [("sphere", -300.0), ("sphere", 1000.0)])
def test_api_checks_a_curved_sample_against_its_traced_mapping(kind, radius_mm):
    """The API's checks are the CLI's (issue 23) on curved samples too (issue 24, item 7): a
    concave R = −300 mm sphere inverts the image and a 1 m sphere bends it; against the nominal
    plane every pixel of the first was flagged GEOMETRY (0 valid). Truth: the tracer's mapping
    through the closed-form surface — every pixel valid and within 6 σ of it, none flagged."""
    from pmdsim.setup import default_setup
    from pmdsim.simulation.render import trace_setup_camera

    setup = default_setup().binned(16).with_sample_shape(kind, radius_mm=radius_mm)
    cam = "left"
    m = pmdsim.simulate(setup, cam)
    with warnings.catch_warnings():
        warnings.simplefilter("error", pmdsim.ConsistencyWarning)
        d = pmdsim.decode(m, setup, camera=cam)
    truth = trace_setup_camera(setup, cam)
    seen = np.isfinite(truth.screen_xy_mm).all(axis=-1)
    assert seen.sum() > 1000
    assert not ((d.flags & PhaseFlag.GEOMETRY) != 0).any()
    ok = d.valid & seen
    assert ok.sum() >= 0.98 * seen.sum()
    z = np.abs(d.screen_xy_mm[ok] - truth.screen_xy_mm[ok]) / d.std_xy_mm[ok]
    assert np.nanmax(z) < 6.0
