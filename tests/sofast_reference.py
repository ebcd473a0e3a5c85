"""Test/benchmark-only: an independent re-implementation of how SOFAST (Sandia's OpenCSP,
``opencsp/app/sofast/lib``) locates a facet's measure point in the image, written from the
method as OpenCSP describes it (its docstrings and parameters), not copied:

1. raw mask (``calc_mask_raw``): histogram of light − dark in 100 bins; the dark and the light
   peak; the threshold halfway (``hist_thresh`` = 0.5) between the upper edge of the emptiest bin
   between the peaks and the light peak's bin; a 9 × 9 box filter keeps pixels with more than
   4 lit pixels around them;
2. edge points (``edges_from_mask``): every pixel that differs from its upper or left
   4-neighbour, at (column − ½, row − ½) — the pixel boundary, quantised to the pixel grid;
3. perimeter (``refine_mask_perimeter``): per side of an expected outline, the edge points in
   a rectangle 50 px beyond the side's ends and 50 px to either side; a line by RANSAC (two
   random points, 1000 draws from numpy's MT19937 seeded with SeedSequence(1), the most points
   within 2 px kept) and a least-squares fit of the perpendicular distances to those points;
   adjacent lines intersected;
4. pose (``calc_rt_from_img_pts``): perspective-n-point of the facet's corners, then the measure
   point projected.

Validated against SOFAST's own stored intermediates in ``test_sofast_reproduces_its_pixel``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.signal import find_peaks


def mask_threshold(delta: np.ndarray, tie: int = 0) -> float:
    """Step 1's threshold of the light − dark image. Several bins between the peaks may be equally
    empty (on the shared facet six bins hold one pixel each); which one ``argmin`` picks then
    depends on the last bits of the bins' widths, i.e. on the numpy version. ``tie`` picks the
    tie-th of them (0: the first, as numpy 2.4 does here)."""
    hist, edges = np.histogram(np.asarray(delta, np.float32).ravel(), bins=100, density=True)
    peaks = []
    for dist in range(10, 100, 10):
        peaks = find_peaks(hist, height=0.002, distance=dist)[0]
        if len(peaks) == 2:
            break
    if len(peaks) != 2:
        raise ValueError("no dark and light peak in the histogram")
    counts = np.histogram(np.asarray(delta, np.float32).ravel(), bins=edges)[0][peaks[0]:peaks[1]]
    ties = np.flatnonzero(counts == counts.min()) + peaks[0]
    i_min = int(np.argmin(hist[peaks[0]:peaks[1]])) + peaks[0] if tie == 0 else int(ties[tie])
    lo, hi = edges[i_min + 1], edges[peaks[1]]
    return float(lo + 0.5 * (hi - lo))


def mask_raw(dark: np.ndarray, light: np.ndarray, tie: int = 0, threshold: float | None = None) -> np.ndarray:
    """Step 1: SOFAST-like raw mask (``threshold`` given: that level instead of the histogram's)."""
    delta = light.astype(np.float32) - dark.astype(np.float32)
    m = delta > (mask_threshold(delta, tie) if threshold is None else threshold)
    filt = ndimage.uniform_filter(m.astype(np.float32), 9, mode="mirror") > np.float32(4 / 81)
    return m & filt


def pixel_edges(mask: np.ndarray) -> np.ndarray:
    """Step 2: edge points (u, v), (K, 2), row-major order."""
    m = np.asarray(mask, int)
    e = np.zeros(m.shape, bool)
    e[1:, :] |= m[1:, :] != m[:-1, :]
    e[:, 1:] |= m[:, 1:] != m[:, :-1]
    v, u = np.nonzero(e)
    return np.stack([u - 0.5, v - 0.5], -1).astype(float)


def _tls(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    n = np.linalg.svd(p - c)[2][-1]
    return n, float(n @ c)


def ransac_line(p: np.ndarray, band: float = 2.0, seed: int = 1, draws: int = 1000) -> tuple[np.ndarray, float]:
    """Step 3's line through points (K, 2): unit normal n and c with n·p = c."""
    from numpy.random import MT19937, RandomState, SeedSequence

    rs = RandomState(MT19937(SeedSequence(seed)))
    n_pts = len(p)
    if n_pts <= 15:
        raise ValueError(f"a line needs > 15 edge points, got {n_pts}")
    best, keep = 0, None
    for _ in range(draws):
        i1 = int(np.floor(rs.rand() * n_pts))
        i2 = int(np.floor(rs.rand() * n_pts))
        while p[i1, 0] == p[i2, 0] and p[i1, 1] == p[i2, 1]:
            i2 = int(np.floor(rs.rand() * n_pts))
        d = p[i2] - p[i1]
        nrm = np.array([d[1], -d[0]]) / np.linalg.norm(d)
        near = np.abs((p - p[i1]) @ nrm) < band
        k = int(near.sum())
        if k > best:
            best, keep = k, near
        if k > int(0.99 * n_pts):
            break
    return _tls(p[keep])


def perimeter(edges: np.ndarray, quad_expected: np.ndarray, d_ax: float = 50.0, d_perp: float = 50.0,
              band: float = 2.0) -> np.ndarray:
    """Step 3: refined corners (4, 2) (u, v); corner i between sides i − 1 and i, side i from the
    expected corner i to i + 1."""
    lines = []
    for i in range(4):
        p1, p2 = quad_expected[i], quad_expected[(i + 1) % 4]
        L = float(np.linalg.norm(p2 - p1))
        a = (p2 - p1) / L
        t = (edges - p1) @ a
        s = (edges - p1) @ np.array([a[1], -a[0]])
        sel = (t >= -d_ax) & (t <= L + d_ax) & (np.abs(s) <= d_perp)
        lines.append(ransac_line(edges[sel], band))
    out = []
    for i in range(4):
        (n1, c1), (n2, c2) = lines[i - 1], lines[i]
        out.append(np.linalg.solve(np.stack([n1, n2]), np.array([c1, c2])))
    return np.array(out)


def sofast_like_pixel(dark, light, cam, corners_obj, quad_expected, point_obj=(0.0, 0.0, 0.0)):
    """Steps 1–4: (pixel (u, v) of the point by the pose fit, corners (4, 2), mask)."""
    from pmdsim.io.importers.outline import outline_pose

    m = mask_raw(dark, light)
    corners = perimeter(pixel_edges(m), np.asarray(quad_expected, float))
    pose = outline_pose(cam, corners, corners_obj)
    return pose.pixel_of(cam, point_obj), corners, m


# ---------------------------------------------------------------------------- edges and a renderer
SIDES = ("bottom", "left", "top", "right")  # side i runs from corner i to i + 1 (SOFAST's order here)


def edge_profiles(delta: np.ndarray, corners: np.ndarray, n_lines: int = 40, half_width: int = 5) -> dict:
    """Per side of the quadrilateral ``corners`` (4, 2) (u, v) — named by where it lies in the image
    — the light − dark profile across the edge on ``n_lines`` rows/columns between 15 % and 85 % of
    the side, each fitted (scipy least squares) by d + s·Φ((x − x0)/σ): an edge blurred by a
    Gaussian, sampled by pixels. Returns {side: (n_lines, 4) array of (d, s, x0 inward-signed, σ)}
    with x0 measured in the direction into the region."""
    from scipy.optimize import least_squares
    from scipy.special import ndtr

    c = np.asarray(corners, float)
    centre = c.mean(axis=0)
    out = {}
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        mid = 0.5 * (a + b)
        vertical = abs(b[0] - a[0]) < abs(b[1] - a[1])
        name = ("left" if mid[0] < centre[0] else "right") if vertical else ("top" if mid[1] < centre[1] else "bottom")
        sgn = 1.0 if name in ("left", "top") else -1.0  # + into the region
        rows = []
        for t in np.linspace(0.15, 0.85, n_lines):
            p = a + t * (b - a)
            k0 = int(round(p[0] if vertical else p[1]))
            ks = np.arange(k0 - half_width, k0 + half_width + 1)
            ys = delta[int(round(p[1])), ks] if vertical else delta[ks, int(round(p[0]))]
            xs = sgn * ks.astype(float)

            def f(q):
                return q[0] + q[1] * ndtr((xs - q[2]) / abs(q[3])) - ys

            q0 = [ys.min(), ys.max() - ys.min(), sgn * k0, 0.5]
            rows.append(least_squares(f, q0).x)
        r = np.array(rows)
        r[:, 3] = np.abs(r[:, 3])
        out[name] = r
    return out


def render_facet(cam, R_cam_facet, t_cam_facet_mm, half_mm: float, sigma_px: dict, dark, lit,
                 n: int = 8) -> np.ndarray:
    """Light − dark image (H, W) of a square facet (±half_mm in its x, y) at pose (R, t) (facet →
    camera, mm): each pixel the mean of n × n sub-pixel samples of dark + (lit − dark)·Π Φ(d_s/σ_s)
    — d_s the sample's distance inside side s (in the facet plane, mm), σ_s = ``sigma_px[side]``
    (optical blur, px, by the side's place in the image) × the facet's mm per px. Pixel
    integration comes from the sub-sampling; σ = 0 gives a sharp edge. ``dark``, ``lit``: levels,
    scalars or (H, W) arrays (the level outside and inside the facet at each pixel)."""
    from scipy.special import ndtr

    R = np.asarray(R_cam_facet, float)
    t = np.asarray(t_cam_facet_mm, float)
    v, u = np.mgrid[0:cam.height_px * n, 0:cam.width_px * n]
    uv = np.stack([(u + 0.5) / n - 0.5, (v + 0.5) / n - 0.5], -1).reshape(-1, 2)
    rays, ok = cam.view_rays(uv)
    normal = R[:, 2]
    s = (t @ normal) / (rays @ normal)
    loc = (s[:, None] * rays - t) @ R  # facet coordinates
    # Which facet side is where in the image: project the side midpoints.
    mids = {"+x": [half_mm, 0, 0], "-x": [-half_mm, 0, 0], "+y": [0, half_mm, 0], "-y": [0, -half_mm, 0]}
    uvm = {k: cam.project((R @ np.array(p, float) + t)[None])[0] for k, p in mids.items()}
    cen = cam.project(t[None])[0]
    side_px = np.linalg.norm(uvm["+x"] - uvm["-x"]) / 2 + np.linalg.norm(uvm["+y"] - uvm["-y"]) / 2
    mm_per_px = 2 * half_mm / side_px

    def name(k):
        d = uvm[k] - cen
        if abs(d[0]) > abs(d[1]):
            return "right" if d[0] > 0 else "left"
        return "bottom" if d[1] > 0 else "top"

    w = np.ones(len(loc))
    for k, dist in (("+x", half_mm - loc[:, 0]), ("-x", half_mm + loc[:, 0]), ("+y", half_mm - loc[:, 1]),
                    ("-y", half_mm + loc[:, 1])):
        sg = sigma_px[name(k)] * mm_per_px
        w *= (dist >= 0) if sg <= 0 else ndtr(dist / sg)
    w = np.where(ok, w, 0.0)
    cover = w.reshape(cam.height_px, n, cam.width_px, n).mean(axis=(1, 3))
    return dark + (np.asarray(lit, float) - dark) * cover


def level_fields(delta: np.ndarray, mask: np.ndarray, band_px: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Smooth outside and inside levels (H, W) of a light − dark image near the outline of
    ``mask``: quadratic polynomials in (u, v) fitted (least squares) to the pixels within
    ``band_px`` outside resp. inside the mask, 2 px away from its boundary (off the partial pixels)."""
    m = np.asarray(mask, bool)
    d_out = ndimage.distance_transform_edt(~m)
    d_in = ndimage.distance_transform_edt(m)
    v, u = np.mgrid[0:m.shape[0], 0:m.shape[1]].astype(float)
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], -1) / [1, 100, 100, 1e4, 1e4, 1e4]
    out = []
    for sel in ((d_out >= 2) & (d_out <= band_px), (d_in >= 3) & (d_in <= band_px)):
        c, *_ = np.linalg.lstsq(A[sel], delta[sel], rcond=None)
        out.append(A @ c)
    return out[0], out[1]
