"""#670 AffineBodyRevoluteJointLimit: the angle of a revolute joint (base UID 18).

F = [B_i, N_i, B_j, N_j], with B_k = A_k b_k, N_k = A_k n_k, and

    cos = (B_i.B_j + N_i.N_j) / 2,   sin = (B_i.N_j - N_i.B_j) / 2,

so that turning body j by +phi about +t relative to body i gives x = +phi.
x is atan2(sin, cos) measured incrementally: its derivatives in (cos, sin) are
those of the polar angle, d(x) = (cos d(sin) - sin d(cos)) / r^2.

PSD notes (`projected_curvature`). With z_k = B_k + i N_k in C^3, w = c + i s = z_i^H z_j / 2 =
r e^{i theta} and x = Im log w, so d2x = Im(dz_i^H dz_j / w) - Im((dw / w)^2). In R^12:

    d2x/dF2 = (K (x) I_3) - (a b^T + b a^T) / r^2,

a = r grad x = cos_t g_s - sin_t g_c, b = r grad log r = cos_t g_c + sin_t g_s (g_c, g_s the
gradients of c, s). K (x) I_3 = lambda0 J with lambda0 = 1 / (2 r) and J a symmetric involution
(J^2 = I, eigenvalues +-1 on two 6-dim spaces, projectors P_+- = (I +- J) / 2). With
rho^2 = |F|^2 / 4 >= r: |a| = |b| = rho, a . b = 0, a . J a = b . J b = 0, b . J a = r.
The span S of P_+-(b +- a) (<= 4 dims) is J-invariant and holds a, b; on its complement the
matrix is lambda0 J. In the orthogonal basis P_+(b + a), P_+(b - a), P_-(b + a), P_-(b - a)
the matrix on S splits into two 2 x 2 blocks, +-(rho^2 [[1, 0], [0, 1]] + q [[0, 1], [1, 0]]) / (2 r^2),
q = sqrt(rho^4 - r^2). So the spectrum is +-1 / (2 r) (4 times each, generically) and
+-(rho^2 +- q) / (2 r^2), and with sigma = sign(E'), mu = |E'|, h1 = P_sigma(b + sigma a),
h3 = P_-sigma(b - sigma a), d = b - sigma a, the PSD part of E' d2x/dF2 is exactly

    mu [ lambda0 P_sigma - (h1 h1^T + h3 h3^T) / (2 r (rho^2 + r)) + d d^T / (2 r^2) ],

finite for every r > 0 (the degenerate rho^2 = r, a complex-parallel frame, included).
tests/core/test_psd_revolute.py checks it against `numpy.linalg.eigh`.

Frames whose r leaves 2^+-240 (`_unsafe`) are differentiated from each body's frames scaled by its own
power of two, 2^-e_i and 2^-e_j: not an orthogonal change of F, so their projection is not the scaled
frames' one carried back. It is the one at F / 2^max(e_i, e_j), one common power of two (which commutes
with the projection: P(F) = P(F / 2^m) / 4^m): there the gradients g are O(1) and rho^2 >= 1/16, only r is
tiny, kept as r_s 2^-|e_i - e_j| (r_s of the scaled frames), and every power of two goes into the
coefficients exactly (`_rescaled_projection`). tests/core/test_revolute_psd_scales.py checks it at scales
1e-100 ... 1e100 against a 50-digit reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.constitution import Array, Curvature, Facts, Progress
from jointlimits.service.core.kinematics import BLOCK_BODY, SMALL, CarefulFrames, component_major, cross, dot, finfo
from jointlimits.service.core.kinematics import frame_quantities, unit
from jointlimits.service.core.polar import squared_norms
from jointlimits.service.core.registry import register

FACTS = Facts(
    uid=670,
    base_uid=18,
    name="AffineBodyRevoluteJointLimit",
    base_name="AffineBodyRevoluteJoint",
    kind="revolute",
    unit="rad",
    coordinate="relative angle of body j about the edge axis +t (right-hand rule), incremental",
    origin='batch field origin: "q_ref" (default): x = 0 at q_ref; "absolute" (the engine): x = atan2(sin, cos) of the '
    "frames at q_ref plus the turn since (not 0 where the bodies' A_ref stretch differently) (v1.2)",
    offset_name="init_angle",
    state_name="angle",
    alpha=np.zeros(4),
    telescopes=False,  # the angle leaves (-pi, pi] over time steps: its state is the committed angle
    axis_by_rotation=True,
    unit_frames=True,
    engine_zero_axis=1e-24,  # AffineBodyRevoluteJoint refuses |t|^2 <= 1e-24
)

COLLAPSE_RATIO = 1e-12
"""A frame collapses where `cos^2 + sin^2 <= 2 COLLAPSE_RATIO^2 (|B_i|^2 |B_j|^2 + |N_i|^2 |N_j|^2)`: (cos, sin)
within rounding of zero relative to the frames' size, at any scale (as `polar.SINGULAR_RATIO`). Above it the
angle is as exact as its conditioning allows (up to ~1e-3 rad at the threshold; test_degenerate_scales.py)."""


def _cos_sin(F: Array) -> tuple[Array, Array]:
    if F.shape[0] > SMALL:  # dot by dot, each pass along the joints
        B_i, N_i, B_j, N_j = F[:, 0], F[:, 1], F[:, 2], F[:, 3]
        return 0.5 * (dot(B_i, B_j) + dot(N_i, N_j)), 0.5 * (dot(B_i, N_j) - dot(N_i, B_j))
    p = component_major(F.shape[0], (2, 2, 3), F.dtype)  # a few joints: the four dots' products in two passes
    np.multiply(F[:, :2], F[:, 2:], out=p[:, 0])  # B_i B_j, N_i N_j
    np.multiply(F[:, :2], F[:, 3:1:-1], out=p[:, 1])  # B_i N_j, N_i B_j
    d = p[..., 0] + p[..., 1] + p[..., 2]
    return 0.5 * (d[:, 0, 0] + d[:, 0, 1]), 0.5 * (d[:, 1, 0] - d[:, 1, 1])


def _step(F: Array, dF: Array, cs: tuple[Array, Array]) -> tuple[Array, tuple[Array, Array]]:
    """DeltaTheta(F + dF, F) and (cos, sin) at F + dF, from (cos, sin) `cs` at F: `sin_a cos_b - cos_a sin_b` is
    `dsin cos_b - dcos sin_b`, the increments of the bilinear cos and sin taken term by term (no cancellation)."""
    if F.shape[0] <= SMALL:  # a few joints: the eight dots in whole passes (the same products and sums, in order)
        i2, di, j, dj = F[:, :2] + dF[:, :2], dF[:, :2], F[:, 2:], dF[:, 2:]  # [B, N] of body i after the step, ...
        p = component_major(F.shape[0], (4, 2, 3), np.result_type(F, dF))  # F's layout: no strided copies
        for k, (a, b) in enumerate(((i2, dj), (di, j), (i2, dj[:, ::-1]), (di, j[:, ::-1]))):
            np.multiply(a, b, out=p[:, k])
        d = p[..., 0] + p[..., 1] + p[..., 2]  # (N, 4, 2): [B_i2.dB_j, N_i2.dN_j], [dB_i.B_j, dN_i.N_j], [B_i2.dN_j, ...], ...
        dc = 0.5 * (d[:, 0, 0] + d[:, 1, 0] + d[:, 0, 1] + d[:, 1, 1])
        ds = 0.5 * (d[:, 2, 0] + d[:, 3, 0] - d[:, 2, 1] - d[:, 3, 1])
    else:
        (B_i, N_i, B_j, N_j), (dB_i, dN_i, dB_j, dN_j) = F.transpose(1, 0, 2), dF.transpose(1, 0, 2)
        B_i2, N_i2 = B_i + dB_i, N_i + dN_i  # body i after the step
        dc = 0.5 * (dot(B_i2, dB_j) + dot(dB_i, B_j) + dot(N_i2, dN_j) + dot(dN_i, N_j))
        ds = 0.5 * (dot(B_i2, dN_j) + dot(dB_i, N_j) - dot(N_i2, dB_j) - dot(dN_i, B_j))
    c, s = cs
    c2, s2 = c + dc, s + ds
    return np.arctan2(ds * c - dc * s, c2 * c + s2 * s), (c2, s2)


def _pair_size(F: Array, side: int) -> Array:
    """|B| + |N| (N,) of one body's frame vectors (side 0: i, 1: j)."""
    B, N = F[:, 2 * side], F[:, 2 * side + 1]
    return np.sqrt(dot(B, B)) + np.sqrt(dot(N, N))


def _careful_angle(careful: CarefulFrames) -> Array:
    """x (M,) of the careful joints: each step in the form with the smaller rounding bound, relative to
    `hypot(cos, sin)` (the angle's, up to a constant). Step form: `(cos, sin)` at the end is the start's plus the
    increment, rounding bounded by `(|B_i'| + |N_i'|)(|dB_j| + |dN_j|) + (|dB_i| + |dN_i|)(|B_j| + |N_j|)`: right
    when the step is small against the frame. Direct form: `(cos, sin)` of each state's own frames (scaled on
    their own), bounded by `(|B_i| + |N_i|)(|B_j| + |N_j|)` at both ends: right for a frame shrunk by 1e-12 in
    one step (in the step's common scaling it would keep few digits, or none).
    """
    x = 0.0  # a bound of inf or NaN loses the choice
    for k, (F, dF) in enumerate(zip(careful.starts, careful.steps)):
        c, s = _cos_sin(F)
        turn_step, (c2, s2) = _step(F, dF, (c, s))
        bound_step = _pair_size(F + dF, 0) * _pair_size(dF, 1) + _pair_size(dF, 0) * _pair_size(F, 1)
        bound_step = bound_step / np.hypot(c2, s2)
        S, E = careful.states[k], careful.states[k + 1]
        ca, sa = _cos_sin(S)
        ce, se = _cos_sin(E)
        turn_direct = np.arctan2(se * ca - ce * sa, ce * ca + se * sa)
        bound_direct = _pair_size(E, 0) * _pair_size(E, 1) / np.hypot(ce, se)
        bound_direct = bound_direct + _pair_size(S, 0) * _pair_size(S, 1) / np.hypot(ca, sa)
        steady = (np.abs(careful.exponents[k] - careful.exponents[k + 1]) <= _STEADY_EXPONENTS).all(axis=1)
        x = x + np.where(steady & (bound_step <= bound_direct), turn_step, turn_direct)
    return x


_STEADY_EXPONENTS = 60
"""A body whose A changes by more than 2^60 in one step takes the direct form for that step."""


def _unsafe(F: Array, cs: tuple[Array, Array]) -> NDArray[np.bool_]:
    """(N,) True where hypot(cos, sin) (`cs` at `F`) leaves `2^+-240` (`2^+-16` in float32), beyond which
    `r^4` or a product in `_polar_derivatives` would not be a normal number."""
    e = finfo(F.dtype).maxexp // 4 - 16
    r = np.hypot(*cs)
    return ~((r >= 2.0**-e) & (r <= 2.0**e))


@dataclass
class _RescaledCurvature(Curvature):
    """A revolute curvature whose rows `rows` (M,) were formed from frames scaled per body by `2^-exponents`
    (M, 2), `scaled` their curvature there (`Revolute.derivatives`): what `_rescaled_projection` needs."""

    rows: NDArray[np.intp] | None = None
    exponents: NDArray[np.int32] | None = None
    scaled: Curvature | None = None


_EYE4 = np.eye(4)
_SIGMAS = np.array([[1.0], [-1.0]])  # h1 from u takes +sigma J u, h3 from d takes -sigma J d
_J_SIGNS = np.array([1.0, -1.0, -1.0, 1.0]).reshape(2, 2, 1, 1)  # the signs of c in J's blocks
_G_BLOCKS = np.array([2, 3, 0, 1, 3, 2, 1, 0])
_G_HALVES = np.array([0.5, 0.5, 0.5, 0.5, 0.5, -0.5, -0.5, 0.5])[:, None]
"""d cos/dF (blocks 0-3) and d sin/dF (4-7): each the block `_G_BLOCKS` of F times `_G_HALVES`."""
_COS_AT, _SIN_AT, _MINUS_SIN_AT = np.array([2, 7, 8, 13]), np.array([3, 12]), np.array([6, 9])
"""The flat entries of K (4 x 4) that are x_c / 2 ((0, 2), (1, 3) and transposed), x_s / 2, -x_s / 2."""


def _polar_derivatives(F: Array, second: bool, cs: tuple[Array, Array] | None = None) -> tuple[Array, Curvature | None]:
    """dx/dF (N, 4, 3) and d2x/dF2: `d(x) = (cos d(sin) - sin d(cos)) / r^2`, `r^2 = cos^2 + sin^2`
    (`cs`: cos and sin at `F` if already known)."""
    n, dtype = F.shape[0], F.dtype
    c, s = _cos_sin(F) if cs is None else cs
    cc, ss = c * c, s * s
    r2 = cc + ss
    xcs = np.empty((2, n), dtype=dtype)  # rows x_c, x_s: dx_coef (N, 2) is its transpose
    np.divide(-s, r2, out=xcs[0])
    np.divide(c, r2, out=xcs[1])
    # d cos/dF and d sin/dF, (N, 2, 4, 3): each block is one other block of F, halved.
    g8 = component_major(n, (8, 3), dtype)
    np.multiply(F[:, _G_BLOCKS], _G_HALVES, out=g8)  # one pass: block (e, k) is F's block _G_BLOCKS[4 e + k], halved
    g = g8.reshape(n, 2, 4, 3)
    p = g8.transpose(1, 2, 0).reshape(2, 4, 3, n) * xcs[:, None, None]  # x_c g_c, x_s g_s, joints last
    dx = (p[0] + p[1]).transpose(2, 0, 1)
    if not second:
        return dx, None
    r4 = r2 * r2
    coef = np.empty((4, n), dtype=dtype)  # C (N, 2, 2), component-major
    np.divide(2.0 * c * s, r4, out=coef[0])
    np.negative(coef[0], out=coef[3])
    np.divide(ss - cc, r4, out=coef[1])
    coef[2] = coef[1]
    # K (N, 4, 4) = x_c COS_PAIRS + x_s SIN_PAIRS, component-major (the assembly reads it entry by entry).
    kron = np.zeros((16, n), dtype=dtype)
    half = 0.5 * xcs
    kron[_COS_AT], kron[_SIN_AT], kron[_MINUS_SIN_AT] = half[0], half[1], -half[1]
    return dx, Curvature(kron=kron.reshape(4, 4, n).transpose(2, 0, 1), basis=g,
                         coef=coef.reshape(2, 2, n).transpose(2, 0, 1), dx_coef=xcs.T)


class Revolute:
    facts = FACTS

    def local_vectors(self, t: Array, anchors: Array | None, R_ref: Array) -> Array:
        # n = t x test with test = e_y where |t . e_x| > 0.9, else e_x; written out, both cases at once.
        y = np.abs(t[:, 0]) > 0.9
        n = component_major(t.shape[0], (3,), t.dtype)
        n[:, 0] = np.where(y, -t[:, 2], 0.0)
        n[:, 1] = np.where(y, 0.0, t[:, 2])
        n[:, 2] = np.where(y, t[:, 0], -t[:, 1])
        n = unit(n)
        b = unit(cross(t, n))
        w = component_major(t.shape[0], (4, 3), t.dtype)  # (b, n, b, n), body-local b_k = R_k^T b: the frames of R^T
        w[:, 0::2], w[:, 1::2] = b[:, None], n[:, None]
        return frame_quantities(None, R_ref.transpose(0, 1, 3, 2), FACTS.alpha, w)

    def value(self, F: Array) -> Array:
        return np.arctan2(*_cos_sin(F)[::-1])

    def begin(self, F: Array) -> Progress:
        cs = _cos_sin(F)
        return Progress(None, cs, [cs])

    def advance(self, progress: Progress, F: Array, dF: Array) -> Progress:
        # (cos, sin) at the end of the step in increment form: what `collapsed` reads there.
        turn, cs = _step(F, dF, progress.state)
        return Progress((0.0 if progress.x is None else progress.x) + turn, cs, [*progress.known, cs])

    careful_coordinate = staticmethod(_careful_angle)

    def collapsed(self, F: Array, known: tuple[Array, Array] | None = None, size_bound: Array | None = None) -> np.ndarray:
        # Squares of frames from A inside kinematics.plain_range (or scaled) stay normal numbers
        # unless the frame is far below its own rounding; then both sides are 0 and it collapses.
        # (Other frames may overflow here: the caller judges those joints on scaled frames.)
        # `known`: (cos, sin) at F as the coordinate formed them (at the end of a step, in increment
        # form: within rounding of the direct ones, far inside the collapse ratio's 1e-12).
        c, s = _cos_sin(F) if known is None else known
        r2 = c * c + s * s
        ratio2 = 2.0 * COLLAPSE_RATIO * COLLAPSE_RATIO
        if size_bound is not None:
            # size2 <= 2 |A_i|^2 |A_j|^2 (|b_k| = |n_k| = 1) <= size_bound / 2: a joint above the bound's
            # threshold is above the test's own; only the others (none, commonly) form their sizes.
            rows = (~(r2 > ratio2 * size_bound)).nonzero()[0]
            out = np.zeros(F.shape[0], dtype=bool)
            if rows.shape[0]:
                out[rows] = self.collapsed(F[rows], (c[rows], s[rows]))
            return out
        B_i, N_i, B_j, N_j = F[:, 0], F[:, 1], F[:, 2], F[:, 3]
        return r2 <= ratio2 * (dot(B_i, B_i) * dot(B_j, B_j) + dot(N_i, N_i) * dot(N_j, N_j))

    def derivatives(self, F: Array, second: bool) -> tuple[Array, Curvature | None]:
        # Rows whose r^4 would under- or overflow (frames beyond ~1e+-36; only those can overflow in the first
        # pass): the same from each body's frames scaled by a power of two, scaled back block by block (exact).
        cs = _cos_sin(F)
        bad = _unsafe(F, cs).nonzero()[0]
        dx, curvature = _polar_derivatives(F, second, cs)
        if bad.shape[0]:
            e = np.frexp(np.abs(F[bad]).max(axis=2).reshape(-1, 2, 2).max(axis=2))[1]  # (M, 2) per body
            eb = e[:, BLOCK_BODY]  # (M, 4)
            dx_b, cv_b = _polar_derivatives(np.ldexp(F[bad], -eb[:, :, None]), second)
            dx[bad] = np.ldexp(dx_b, -eb[:, :, None])
            if second:
                curvature.kron[bad] = np.ldexp(cv_b.kron, -(eb[:, :, None] + eb[:, None, :]))
                curvature.basis[bad] = np.ldexp(cv_b.basis, -eb[:, None, :, None])
                curvature.coef[bad], curvature.dx_coef[bad] = cv_b.coef, cv_b.dx_coef
                # The PSD projection of these rows needs their scaled frames' quantities (`_rescaled_projection`).
                curvature = _RescaledCurvature(**vars(curvature), rows=bad, exponents=e, scaled=cv_b)
        return dx, curvature

    def projected_curvature(self, dE: Array, curvature: Curvature) -> Curvature:
        """The PSD part of `dE d2x/dF2` in closed form (the PSD notes above), for every frame with r > 0 (collapsed
        ones are refused): kron (N, 4, 4), basis (N, 3, 4, 3) = (h1, h3, d), coef (N, 3, 3) diagonal."""
        x_c, x_s = curvature.dx_coef[:, 0], curvature.dx_coef[:, 1]  # -s / r^2, c / r^2
        # The rows `scaled` names hold nothing meaningful here (their r^2 is not a normal number): overwritten below.
        r = 1.0 / np.hypot(x_c, x_s)
        mu = np.abs(dE)
        basis, rho2, sign = _psd_vectors(dE, curvature.basis, x_c, x_s, r)
        coef = np.zeros((dE.shape[0], 3, 3), dtype=dE.dtype)
        coef[:, 0, 0] = coef[:, 1, 1] = -mu / (2.0 * r * (rho2 + r))
        coef[:, 2, 2] = mu / (2.0 * r * r)
        # mu lambda0 P_sigma = |E'| / (4 r) I_4 + E' K / 2, as block coefficients.
        kron = curvature.kron.transpose(1, 2, 0).reshape(16, -1) * (0.5 * dE)  # (16, N), component-major
        kron += _EYE4.reshape(16, 1).astype(dE.dtype, copy=False) * (mu / (4.0 * r))
        kron = kron.reshape(4, 4, -1).transpose(2, 0, 1)
        if isinstance(curvature, _RescaledCurvature):
            rows = curvature.rows
            kron[rows], basis[rows], coef[rows] = _rescaled_projection(dE[rows], curvature)
        return Curvature(kron=kron, basis=basis, coef=coef, diagonal=True)


def _psd_vectors(dE: Array, g: Array, x_c: Array, x_s: Array, r: Array) -> tuple[Array, Array, Array]:
    """(h1, h3, d) (N, 3, 4, 3) of the PSD notes, rho^2 and sigma = sign(E') (N,), from g = (g_c, g_s) (N, 2, 4, 3)
    and `dE`; `x_c`, `x_s`, `r` (N,) give cos_t = x_s r and sin_t = -x_c r. Linear in g (rho^2 quadratic)."""
    rho2 = squared_norms(g[:, 0].transpose(1, 2, 0).reshape(12, -1))  # |g_c|^2 = |g_s|^2 = |F|^2 / 4
    sign = np.where(dE >= 0, 1.0, -1.0).astype(dE.dtype, copy=False)
    c, s = x_s * r, -x_c * r  # cos_t, sin_t: w = r e^{i theta}
    # Joints last ((..., N) views of the component-major arrays): each pass runs along the joints, the per-joint
    # scalars broadcast whole (few joints: few passes; many: contiguous ones).
    n, dtype = g.shape[0], g.dtype
    gt = g.transpose(1, 2, 3, 0)  # (g_c, g_s) (2, 4, 3, N)
    cg, sg = gt * c, gt * s
    b = cg[0] + sg[1]  # r grad(log r)
    sa = (cg[1] - sg[0]) * sign  # sigma r grad(x)
    ud = np.empty((2, 4, 3, n), dtype=dtype)  # u, d = b +- sigma a
    np.add(b, sa, out=ud[0])
    np.subtract(b, sa, out=ud[1])
    # J = (K / lambda0) (x) I_3 (an involution, eigenvalues +-1) on u and d at once: blocks (B_i, N_i, B_j, N_j) of
    # J w are (c N_j - s B_j, -c B_j - s N_j, -c N_i - s B_i, c B_i - s N_i), views of w's reversed ((-c) w is -(c w)).
    u5 = ud.reshape(2, 2, 2, 3, n)  # (u or d, body, frame, r, joint)
    Jud = (_J_SIGNS.astype(dtype, copy=False) * c) * u5[:, ::-1, ::-1]
    Jud -= s * u5[:, ::-1]
    Jud *= (_SIGMAS.astype(dtype, copy=False) * sign)[:, None, None, None]  # sigma J u, -sigma J d
    basis = np.empty((3, 4, 3, n), dtype=dtype)  # component-major (N, 3, 4, 3)
    basis[2] = ud[1]  # d
    u5 += Jud
    np.multiply(0.5, ud, out=basis[:2])  # h1 = P_sigma u, h3 = P_-sigma d
    basis = basis.transpose(3, 0, 1, 2)
    return basis, rho2, sign


def _rescaled_projection(dE: Array, scaled: _RescaledCurvature) -> tuple[Array, Array, Array]:
    """kron, basis, coef of `projected_curvature` for rows differentiated from scaled frames.

    The frames are F = D F_s, body k's scaled by 2^e_k; the projection is taken at F / 2^m, m = max(e_i, e_j),
    a common scale that commutes with it (module docstring). There g = (g_c, g_s) is g_s with body i's blocks
    times 2^(e_j - m) and body j's times 2^(e_i - m) (each block of g is the other body's frame, halved),
    so |g| = O(1) and rho^2 >= 1/16 (the larger body's max entry is in [1/2, 1)); r = r_s 2^(e_i + e_j - 2m),
    which may underflow: it enters only beside rho^2 and as r_s times a power of two. The basis (h1, h3, d)
    is taken there, O(1); the coefficients carry 4^-m and the remaining powers of two, and E' as its
    mantissa and exponent, by `ldexp` (one rounding, only where the result itself leaves the normal range):
    an answer beyond float64 becomes inf (the caller's overflow error), never a wrong finite number.
    """
    e = scaled.exponents.astype(np.int64)
    cv = scaled.scaled
    x_c, x_s = cv.dx_coef[:, 0], cv.dx_coef[:, 1]
    r = 1.0 / np.hypot(x_c, x_s)  # r_s: O(1) frames, far from collapse (validation)
    top = e.max(axis=1)
    spread = e[:, 0] + e[:, 1] - 2 * top  # <= 0
    shift = (e[:, ::-1] - top[:, None])[:, BLOCK_BODY]  # (M, 4): block k of g times 2^(e_other - m)
    g = np.ldexp(cv.basis, shift[:, None, :, None])
    mant, p = np.frexp(np.abs(dE))  # |E'| = mant 2^p, mant in [1/2, 1) (or 0, inf, NaN as |E'|)
    basis, rho2, sign = _psd_vectors(dE, g, x_c, x_s, r)
    # P(F) = P(F / 2^m) / 4^m: each coefficient at F / 2^m (r there is r_s 2^spread), times 4^-m.
    ij = p - (e[:, 0] + e[:, 1])  # 2^(-spread - 2m) = 2^-(e_i + e_j)
    coef = np.zeros((dE.shape[0], 3, 3), dtype=dE.dtype)
    coef[:, 0, 0] = coef[:, 1, 1] = -np.ldexp(mant / (2.0 * r * (rho2 + np.ldexp(r, spread))), ij)
    coef[:, 2, 2] = np.ldexp(mant / (2.0 * r * r), p - 2 * e.min(axis=1))  # 2^(-2 spread - 2m) = 4^-min(e_i, e_j)
    kron = (0.5 * sign * mant)[:, None, None] * cv.kron  # K_s = K 2^(e_i + e_j)
    kron += (mant / (4.0 * r))[:, None, None] * _EYE4.astype(dE.dtype, copy=False)
    return np.ldexp(kron, ij[:, None, None]), basis, coef


REVOLUTE = register(Revolute())
