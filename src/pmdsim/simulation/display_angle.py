"""The LCD's viewing-angle response: an in-plane-switching cell between crossed polarisers
(issue 20; docs/conventions.md, "Display: viewing-angle response").

Frame: the display's own, z towards the viewer, x along the screen's x axis (y' = −y of the screen
frame when the screen's z points away from the viewer). A ray leaving the screen in the unit
direction (u_x, u_y, u_z) keeps its transverse wave vector k₀·(u_x, u_y) in every plane layer
(Snell), s² = u_x² + u_y² = sin²θ. In units of k₀ = 2π/λ:

* **Polarisers** (index n_p = 1.5, ideal O-type: the wave polarised across the absorption axis a
  passes): wave vector k_p = (u_x, u_y, √(n_p² − s²)), transmitted field ∝ k_p × a. The entrance
  polariser transmits along the rubbing direction ρ (a₁ = (−sin ρ, cos ρ, 0)), the analyser is
  crossed (a₂ = (cos ρ, sin ρ, 0)).
* **The cell**: a uniform uniaxial layer, director c = (cos(ρ + ψ), sin(ρ + ψ), 0) in the plane (the
  in-plane field turns it by ψ from the rubbing direction), gap d = Γ_nm/(n_e − n_o). The
  ordinary wave: k_o,z = √(n_o² − s²), field ∝ k_o × c. The extraordinary wave solves the Fresnel
  equation (k·c)²/n_o² + (|k|² − (k·c)²)/n_e² = 1, with k·c = s·cos(φ − ρ − ψ):

      k_e,z = √(n_e² − s²·[sin²(φ − ρ − ψ) + (n_e²/n_o²)·cos²(φ − ρ − ψ)]),

  its displacement D ∝ (k_e × c) × k_e, field E = ε⁻¹D (ε = n_o² I + (n_e² − n_o²) c cᵀ).
* **The extended Jones matrix** (A. Lien, Appl. Phys. Lett. 57, 2767 (1990); P. Yeh & C. Gu,
  *Optics of Liquid Crystal Displays*, 2nd ed., Wiley 2010; waves in a uniaxial layer and ideal
  absorptive polarisers: D. A. Yakovlev, V. G. Chigrinov & H.-S. Kwok, *Modeling and
  Optimization of LCD Optical Performance*, Wiley 2015, §1.3; the formulations' boundary
  matching compared with the 4 × 4 method: F. H. Yu & H. S. Kwok, J. Opt. Soc. Am. A 16, 2772
  (1999)), without interface reflections: the polariser's field is split into the cell's two modes by matching the transverse
  (x, y) field components, each mode gains exp(i·k₀·d·k_z), and the field leaving the cell is split
  into the analyser's transmitted and absorbed modes likewise; T = |transmitted amplitude|².

At normal incidence this is T = sin²(2ψ)·sin²(Γ/2), Γ = 2π·Γ_nm/λ. The commanded level d sets
ψ(d) so that the normal response is the display's gamma curve exactly: sin²(2ψ) = d^γ
(ψ = ½·asin(√(d^γ)) ∈ [0, π/4]), and the radiance is

    r(d; u) = b + (1 − b)·T(ψ(d); u)/sin²(Γ/2)

(b the black level, the cell's leakage taken as independent of the angle). Off the normal both
the white luminance and the curve's shape (the effective gamma) change.

The renderer needs r for every camera pixel's direction: :class:`AngularBasis` factors it as
Σ_m w_m(u)·B_m(ψ) (an interpolative decomposition over a grid of the directions present: B_m the model's curves
at R skeleton directions, R the smallest whose fit of every grid node is within
:data:`BASIS_TOLERANCE`), with w_m interpolated per pixel (cubic splines on the direction grid). Each basis function is rendered like a display response
and the images mix them with the pixel's weights (the render is linear in the response).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["POLARISER_INDEX", "BASIS_TOLERANCE", "ips_transmittance", "level_to_psi", "angular_response",
           "view_directions", "AngularBasis", "angular_basis"]

#: Refractive index of the polarisers' medium (TAC/PVA ≈ 1.5).
POLARISER_INDEX = 1.5
#: Largest residual of the rank-truncated factorisation on its direction grid (relative radiance).
BASIS_TOLERANCE = 1e-6
_PSI_SAMPLES = 2049  # ψ grid on [0, π/4]: linear interpolation error ≈ (π/4/2048)²/8·|T''| ≲ 1e-7
_PSI_COARSE = 257  # ψ samples of the table the skeleton directions are chosen on
_GRID = 16  # direction nodes per axis over the pixels' bounding box (cubic-spline interpolation)
_PAD = 3  # extra nodes beyond the bounding box on each side


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _split(field_t, mode_a_t, mode_b_t):
    """Coefficients (α, β) with field_t = α·mode_a_t + β·mode_b_t (transverse 2-vectors, (..., 2))."""
    det = mode_a_t[..., 0] * mode_b_t[..., 1] - mode_a_t[..., 1] * mode_b_t[..., 0]
    alpha = (field_t[..., 0] * mode_b_t[..., 1] - field_t[..., 1] * mode_b_t[..., 0]) / det
    beta = (mode_a_t[..., 0] * field_t[..., 1] - mode_a_t[..., 1] * field_t[..., 0]) / det
    return alpha, beta


def ips_transmittance(psi, ux, uy, *, retardation_nm: float, indices: tuple[float, float], rubbing_deg: float,
                      wavelength_nm: float, polariser_index: float = POLARISER_INDEX) -> np.ndarray:
    """Transmittance of the IPS cell between crossed polarisers (module docstring).

    Parameters
    ----------
    psi : array_like
        The director's rotation from the rubbing direction (radians).
    ux, uy : array_like
        Transverse components of the unit direction of the light leaving the screen (display frame,
        z towards the viewer); broadcast with ``psi``.
    retardation_nm, indices, rubbing_deg, wavelength_nm
        Γ_nm = d·Δn, (n_o, n_e), ρ (degrees from x), λ.

    Returns
    -------
    ndarray, the broadcast shape: T ∈ [0, 1] (1: all of the polarised light).
    """
    psi, ux, uy = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (psi, ux, uy)))
    no, ne = float(indices[0]), float(indices[1])
    rho = np.radians(float(rubbing_deg))
    s2 = ux * ux + uy * uy
    zero = np.zeros_like(ux)
    kp = np.stack([ux, uy, np.sqrt(polariser_index ** 2 - s2)], axis=-1)
    a1 = np.array([-np.sin(rho), np.cos(rho), 0.0])
    a2 = np.array([np.cos(rho), np.sin(rho), 0.0])
    e_in = _unit(np.cross(kp, a1))
    t_out = _unit(np.cross(kp, a2))
    x_out = _unit(np.cross(kp, t_out))
    c = np.stack([np.cos(rho + psi), np.sin(rho + psi), zero], axis=-1)
    ko = np.stack([ux, uy, np.sqrt(no * no - s2)], axis=-1)
    e_o = _unit(np.cross(ko, c))
    kc = ux * c[..., 0] + uy * c[..., 1]
    kez = np.sqrt(ne * ne - s2 - kc * kc * (ne * ne / (no * no) - 1.0))
    ke = np.stack([ux, uy, kez], axis=-1)
    d_e = np.cross(np.cross(ke, c), ke)
    e_e = _unit(d_e / (no * no) + (1.0 / (ne * ne) - 1.0 / (no * no)) * np.sum(c * d_e, axis=-1)[..., None] * c)
    alpha, beta = _split(e_in[..., :2], e_o[..., :2], e_e[..., :2])
    k0d = 2.0 * np.pi * float(retardation_nm) / (ne - no) / float(wavelength_nm)
    out = (alpha * np.exp(1j * k0d * ko[..., 2]))[..., None] * e_o[..., :2] \
        + (beta * np.exp(1j * k0d * kez))[..., None] * e_e[..., :2]
    gamma, _ = _split(out, t_out[..., :2], x_out[..., :2])
    return np.abs(gamma) ** 2


def level_to_psi(d, gamma: float | None) -> np.ndarray:
    """The director angle ψ(d) = ½·asin(√(d^γ)) that makes the normal response d^γ (γ None: 1)."""
    d = np.clip(np.asarray(d, dtype=float), 0.0, 1.0)
    g = d if gamma is None else d ** float(gamma)
    return 0.5 * np.arcsin(np.sqrt(np.clip(g, 0.0, 1.0)))


def _cell(im) -> dict:
    return dict(retardation_nm=im.lcd_retardation_nm, indices=im.lcd_indices, rubbing_deg=im.lcd_rubbing_deg,
                wavelength_nm=im.lcd_wavelength_nm)


def _response_of_psi(psi, ux, uy, im) -> np.ndarray:
    t0 = np.sin(np.pi * im.lcd_retardation_nm / im.lcd_wavelength_nm) ** 2
    b = im.display_black_level
    return b + (1.0 - b) * ips_transmittance(psi, ux, uy, **_cell(im)) / t0


def angular_response(d, ux, uy, im) -> np.ndarray:
    """r(d; u) = b + (1 − b)·T(ψ(d); u)/sin²(Γ/2) for commanded levels ``d`` seen from the
    direction (``ux``, ``uy``) (display frame), ``im`` an ImagingSetup with ``lcd_mode = "ips"``."""
    return _response_of_psi(level_to_psi(d, im.display_gamma), ux, uy, im)


def view_directions(T_world_screen, T_world_sample, p_sample_mm, q_screen_mm) -> np.ndarray:
    """(u_x, u_y) of the unit direction from each screen point towards its sample point in the
    display frame (z towards the viewer; the screen frame's x, and y flipped when the viewers
    are on the screen frame's −z side), shape (H, W, 2), NaN where not traced."""
    p = (T_world_screen.inv() @ T_world_sample).apply(p_sample_mm)
    v = p - np.asarray(q_screen_mm, dtype=float)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    flip = np.nanmedian(v[..., 2]) < 0.0  # the viewers' side: rotate by π about x
    return np.stack([v[..., 0], -v[..., 1] if flip else v[..., 1]], axis=-1)


@dataclass(frozen=True, eq=False)
class AngularBasis:
    """r(d; u) ≈ Σ_m w_m(u)·B_m(ψ(d)) over the directions of one camera's pixels.

    Attributes
    ----------
    psi_grid : ndarray (M,)
        Uniform ψ samples on [0, π/4].
    functions : ndarray (R, M)
        B_m at ``psi_grid`` (relative radiance, black level included).
    weights : ndarray (H, W, R)
        w_m per pixel (0 where the pixel has no direction).
    gamma : float or None
        The display gamma (for ψ(d)).
    residual : float
        Largest |r − Σ w·B| on the direction grid (the rank truncation's error).
    weights_max : ndarray (R,)
        max over the pixels of |w_m| (bounds of the mixed coefficients for the series' truncation).
    """

    psi_grid: np.ndarray
    functions: np.ndarray
    weights: np.ndarray
    gamma: float | None
    residual: float
    weights_max: np.ndarray

    @property
    def rank(self) -> int:
        return int(self.functions.shape[0])

    def at_levels(self, d) -> np.ndarray:
        """B_m(ψ(d)) for commanded levels ``d`` (any shape): shape (R,) + d.shape."""
        psi = level_to_psi(d, self.gamma)
        flat = psi.reshape(-1)
        return np.stack([np.interp(flat, self.psi_grid, f) for f in self.functions]).reshape((self.rank,) + psi.shape)


def angular_basis(im, directions: np.ndarray, *, tolerance: float = BASIS_TOLERANCE, grid: int = _GRID,
                  max_rank: int = 12) -> AngularBasis:
    """The factorisation of :class:`AngularBasis` for the per-pixel ``directions`` (H, W, 2).

    The model is tabulated on a ``grid`` × ``grid`` grid of directions over the pixels' bounding
    box (plus :data:`_PAD` nodes each side, so that every pixel is interpolated away from the
    spline's boundary) and on :data:`_PSI_COARSE` ψ samples. A pivoted Gram–Schmidt on that
    table picks R skeleton directions u_m (the smallest R whose least-squares fit of every node's curve is
    within ``tolerance``): B_m is the model's own curve at u_m (tabulated on the fine ψ grid), and
    the weights are the fit's coefficients, interpolated per pixel by cubic splines.
    """
    from scipy.ndimage import spline_filter

    u = np.ascontiguousarray(directions, dtype=float)
    box = np.array([np.inf, np.inf, -np.inf, -np.inf])
    _bounding_box(u, box)
    lo, hi = (box[:2], box[2:]) if np.all(np.isfinite(box)) else (np.zeros(2), np.zeros(2))
    span = np.maximum(hi - lo, 1e-6)
    step = span / (grid - 1)
    n_nodes = grid + 2 * _PAD
    gx = lo[0] + step[0] * (np.arange(n_nodes) - _PAD)
    gy = lo[1] + step[1] * (np.arange(n_nodes) - _PAD)
    ux, uy = np.meshgrid(gx, gy)  # (grid y, grid x)
    psi_c = np.linspace(0.0, 0.25 * np.pi, _PSI_COARSE)
    table = _response_of_psi(psi_c[None, None, :], ux[..., None], uy[..., None], im).reshape(-1, psi_c.size)
    # Pivoted Gram–Schmidt: the node whose curve is worst represented joins the skeleton.
    rest = table.copy()
    piv = []
    for rank in range(1, min(max_rank, table.shape[0]) + 1):
        i = int(np.argmax(np.einsum("ij,ij->i", rest, rest)))
        piv.append(i)
        q = rest[i] / np.linalg.norm(rest[i])
        rest -= np.outer(rest @ q, q)
        resid = float(np.max(np.abs(rest)))
        if resid <= tolerance:
            break
    piv = np.array(piv)
    coef = np.linalg.lstsq(table[piv].T, table.T, rcond=None)[0]  # (R, nodes)
    psi = np.linspace(0.0, 0.25 * np.pi, _PSI_SAMPLES)
    functions = _response_of_psi(psi[None, :], ux.reshape(-1)[piv[:rank], None], uy.reshape(-1)[piv[:rank], None], im)
    node_w = coef.T.reshape(n_nodes, n_nodes, rank)
    spline = np.stack([spline_filter(node_w[..., m], order=3, mode="mirror") for m in range(rank)], axis=-1)
    weights = np.zeros(u.shape[:2] + (rank,))
    _spline_weights(np.ascontiguousarray(u), np.ascontiguousarray(spline), gx[0], gy[0], step[0], step[1], weights)
    wmax = np.zeros(rank)
    _abs_max(weights, wmax)
    return AngularBasis(psi, np.ascontiguousarray(functions), weights, im.display_gamma, resid, wmax)


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _spline_weights(u, coef, x0, y0, hx, hy, out):
    """Cubic B-spline interpolation of the prefiltered node coefficients ``coef`` (Ny, Nx, R) at
    each pixel's direction ``u`` (H, W, 2) (what scipy.ndimage.map_coordinates(order=3) gives at
    nodes ≥ 2 from the grid's edge); 0 where ``u`` is not finite."""
    h, w = u.shape[0], u.shape[1]
    ny, nx, nr = coef.shape
    for v in numba.prange(0, h):
        for c in range(w):
            fx = (u[v, c, 0] - x0) / hx
            fy = (u[v, c, 1] - y0) / hy
            if not (np.isfinite(fx) and np.isfinite(fy)):
                for m in range(nr):
                    out[v, c, m] = 0.0
                continue
            ix = min(max(int(np.floor(fx)), 1), nx - 3)
            iy = min(max(int(np.floor(fy)), 1), ny - 3)
            tx = fx - ix
            ty = fy - iy
            bx0 = (1.0 - tx) ** 3 / 6.0
            bx1 = (3.0 * tx ** 3 - 6.0 * tx * tx + 4.0) / 6.0
            bx2 = (-3.0 * tx ** 3 + 3.0 * tx * tx + 3.0 * tx + 1.0) / 6.0
            bx3 = tx ** 3 / 6.0
            by0 = (1.0 - ty) ** 3 / 6.0
            by1 = (3.0 * ty ** 3 - 6.0 * ty * ty + 4.0) / 6.0
            by2 = (-3.0 * ty ** 3 + 3.0 * ty * ty + 3.0 * ty + 1.0) / 6.0
            by3 = ty ** 3 / 6.0
            for m in range(nr):
                acc = 0.0
                for j in range(4):
                    by = by0 if j == 0 else (by1 if j == 1 else (by2 if j == 2 else by3))
                    row = iy - 1 + j
                    acc += by * (bx0 * coef[row, ix - 1, m] + bx1 * coef[row, ix, m] + bx2 * coef[row, ix + 1, m]
                                 + bx3 * coef[row, ix + 2, m])
                out[v, c, m] = acc


@numba.njit(cache=True, error_model="numpy")
def _bounding_box(u, box):
    """box = (min u_x, min u_y, max u_x, max u_y) over the pixels whose direction is finite."""
    h, w = u.shape[0], u.shape[1]
    for v in range(h):
        for c in range(w):
            x, y = u[v, c, 0], u[v, c, 1]
            if np.isfinite(x) and np.isfinite(y):
                box[0] = min(box[0], x)
                box[1] = min(box[1], y)
                box[2] = max(box[2], x)
                box[3] = max(box[3], y)


@numba.njit(cache=True, error_model="numpy")
def _abs_max(weights, out):
    """out[m] = max over the pixels of |weights[..., m]|."""
    h, w, nr = weights.shape
    for v in range(h):
        for c in range(w):
            for m in range(nr):
                a = abs(weights[v, c, m])
                if a > out[m]:
                    out[m] = a
