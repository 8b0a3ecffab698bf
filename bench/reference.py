"""An independent 50-digit reference for #670 / #669, written from CONTRACT.md alone.

It lives in bench/ because both the bench and the tests measure against it (`import bench.reference`,
from the repository root); its one dependency, mpmath, is in both the `test` and `bench` extras.

Nothing here is shared with `service/core`: the frames come from a Newton polar
iteration in mpmath, the coordinate `x` from the contract's formulas, and every
derivative from second-order forward-mode automatic differentiation (`Jet`)
rather than from hand-derived formulas. The revolute angle is differentiated as
`Im log(cos + i sin)` (complex jets), a different route from the usual
`atan2` partials. The chain rule `F -> q` uses `J = dF/dq` built from the
definition `F_k = alpha_k p + A v_k`, explicitly and sparsely.

Use `reference_request(request)` for a whole CONTRACT v1 / v1.1 request dict, or
`JointRef` for one joint (e.g. to finite-difference the reference energy). v1.1's
`offset` shifts the bounds (`l = lower - offset`, `u = upper - offset`, exactly, at 50 digits)
and the reported `coordinate = x + offset`; `prev_coordinate` replaces the accumulated angle
`DeltaTheta(q_prev, q_ref)` by `prev_coordinate - offset`. v1.2: body-local `local_edges`
(`JointRef(..., local_edge=...)`), `origin: "absolute"` (the frames' own coordinate at `q_ref` added
to `x`) and the engine's prismatic `psd`, projected in the 9 quantities `[C_j - C_i, T_i, -T_j]`
(differentiated in those variables directly, then carried to `F` by their linear map).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from mpmath import mp, mpc, mpf

DPS = 50

Vec = list  # a list of 3 mpf
Mat = list  # a list of lists of mpf


# ---------------------------------------------------------------- small mp linear algebra


def _mpv(a: Sequence[Any]) -> Vec:
    # Floats (also NumPy's) exactly; mp numbers (finite-difference steps) as they are.
    return [v if isinstance(v, mpf) else mpf(float(v)) for v in a]


def _dot(a: Vec, b: Vec) -> Any:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _normalize(a: Vec) -> Vec:
    n = mp.sqrt(_dot(a, a))
    return [v / n for v in a]


def _matvec(A: Mat, v: Vec) -> Vec:
    return [_dot(A[r], v) for r in range(3)]


def _tmatvec(A: Mat, v: Vec) -> Vec:
    """A^T v."""
    return [A[0][c] * v[0] + A[1][c] * v[1] + A[2][c] * v[2] for c in range(3)]


def _split(q: Sequence[float]) -> tuple[Vec, Mat]:
    q = _mpv(q)
    return q[:3], [q[3:6], q[6:9], q[9:12]]


def polar_rotation(A: Mat) -> Mat:
    """Orthogonal polar factor by the scaled Newton iteration `X <- (g X + X^-T / g) / 2`."""
    X = mp.matrix(A)
    for _ in range(200):
        Xi = mp.inverse(X)
        g = abs(mp.det(X)) ** (mpf(-1) / 3)
        Y = (g * X + Xi.T / g) / 2
        change = mp.mnorm(Y - X, 1)
        X = Y
        if change < mpf(10) ** (-(mp.dps - 3)):
            break
    else:  # pragma: no cover - a nonsingular A always converges
        raise ArithmeticError("polar iteration did not converge")
    R = [[X[r, c] for c in range(3)] for r in range(3)]
    # Orthogonal to working precision, or the frames below are not what the contract means.
    RtR = mp.matrix(R).T * mp.matrix(R) - mp.eye(3)
    assert mp.mnorm(RtR, 1) < mpf(10) ** (-(mp.dps - 8))
    return R


# ---------------------------------------------------------------- second-order forward-mode AD


class Jet:
    """A value with its gradient and Hessian in a few variables, both sparse (dicts)."""

    __slots__ = ("v", "g", "h")

    def __init__(self, v: Any, g: dict | None = None, h: dict | None = None) -> None:
        self.v, self.g, self.h = v, g or {}, h or {}

    @staticmethod
    def var(v: Any, i: int) -> Jet:
        return Jet(v, {i: mpf(1)})

    def _lift(self, o: Any) -> Jet:
        return o if isinstance(o, Jet) else Jet(o)

    def __add__(self, o: Any) -> Jet:
        o = self._lift(o)
        g = dict(self.g)
        for k, d in o.g.items():
            g[k] = g.get(k, 0) + d
        h = dict(self.h)
        for k, d in o.h.items():
            h[k] = h.get(k, 0) + d
        return Jet(self.v + o.v, g, h)

    __radd__ = __add__

    def __neg__(self) -> Jet:
        return Jet(-self.v, {k: -d for k, d in self.g.items()}, {k: -d for k, d in self.h.items()})

    def __sub__(self, o: Any) -> Jet:
        return self + (-self._lift(o))

    def __rsub__(self, o: Any) -> Jet:
        return self._lift(o) - self

    def __mul__(self, o: Any) -> Jet:
        if not isinstance(o, Jet):
            return Jet(self.v * o, {k: d * o for k, d in self.g.items()}, {k: d * o for k, d in self.h.items()})
        g: dict = {}
        for k, d in self.g.items():
            g[k] = g.get(k, 0) + d * o.v
        for k, d in o.g.items():
            g[k] = g.get(k, 0) + d * self.v
        h: dict = {}
        for k, d in self.h.items():
            h[k] = h.get(k, 0) + d * o.v
        for k, d in o.h.items():
            h[k] = h.get(k, 0) + d * self.v
        for a, da in self.g.items():
            for b, db in o.g.items():
                p = da * db
                h[(a, b)] = h.get((a, b), 0) + p
                h[(b, a)] = h.get((b, a), 0) + p
        return Jet(self.v * o.v, g, h)

    __rmul__ = __mul__

    def log(self) -> Jet:
        """Principal log (works for complex values): d log z = dz / z, d2 log z = d2z / z - dz dz^T / z^2."""
        z = self.v
        g = {k: d / z for k, d in self.g.items()}
        h = {k: d / z for k, d in self.h.items()}
        for a, da in self.g.items():
            for b, db in self.g.items():
                h[(a, b)] = h.get((a, b), 0) - da * db / (z * z)
        return Jet(mp.log(z), g, h)

    def imag(self) -> Jet:
        return Jet(mp.im(self.v), {k: mp.im(d) for k, d in self.g.items()}, {k: mp.im(d) for k, d in self.h.items()})

    def grad(self, n: int) -> list:
        return [self.g.get(i, mpf(0)) for i in range(n)]

    def hess(self, n: int) -> Mat:
        return [[self.h.get((i, j), mpf(0)) for j in range(n)] for i in range(n)]


def _jdot(a: Sequence[Any], b: Sequence[Any]) -> Any:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


# ---------------------------------------------------------------- the two coordinates


def _cos_sin(F: Sequence[Sequence[Any]]) -> tuple[Any, Any]:
    """Contract: cos = (B_i.B_j + N_i.N_j)/2, sin = (B_i.N_j - N_i.B_j)/2 (the corrected sign)."""
    B_i, N_i, B_j, N_j = F
    return (_jdot(B_i, B_j) + _jdot(N_i, N_j)) * mpf(0.5), (_jdot(B_i, N_j) - _jdot(N_i, B_j)) * mpf(0.5)


def _delta_theta(cs_a: tuple[Any, Any], cs_b: tuple[Any, Any]) -> Any:
    (ca, sa), (cb, sb) = cs_a, cs_b
    return mp.atan2(sa * cb - ca * sb, ca * cb + sa * sb)


def _theta(F: Sequence[Sequence[Any]]) -> Any:
    C_i, T_i, C_j, T_j = F
    D = [C_j[r] - C_i[r] for r in range(3)]
    S = [T_i[r] + T_j[r] for r in range(3)]
    return _jdot(D, S) * mpf(0.5)


# ---------------------------------------------------------------- one joint


@dataclass
class JointResult:
    """One joint at 50 digits: `gradient` (24), Hessians (24 x 24) in both modes (zeros inside the range; None when
    not asked for: `evaluate(..., hessians=False)`)."""

    x: Any
    energy: Any
    gradient: list
    hessian_exact: Mat | None
    hessian_psd: Mat | None
    coordinate: Any = None
    """x + offset (v1.1)."""

    def as_float(self) -> dict[str, np.ndarray]:
        f = lambda a: np.array([[float(v) for v in row] for row in a] if isinstance(a[0], list) else [float(v) for v in a])  # noqa: E731
        return dict(
            x=float(self.x),
            coordinate=float(self.x if self.coordinate is None else self.coordinate),
            energy=float(self.energy),
            gradient=f(self.gradient),
            hessian_exact=None if self.hessian_exact is None else f(self.hessian_exact),
            hessian_psd=None if self.hessian_psd is None else f(self.hessian_psd),
        )


def penalty_jet(x: Any, lower: float, upper: float, strength: float) -> tuple[Any, Any, Any]:
    """(E, E', E'') at x: s (g / w)^3 outside [l, u] (bounds inside), w = u - l or 1 when u == l."""
    lo, up, s = mpf(lower), mpf(upper), mpf(strength)
    X = Jet.var(x, 0)
    if x > up:
        g = X - up
    elif x < lo:
        g = lo - X
    else:
        return mpf(0), mpf(0), mpf(0)
    w = up - lo if up > lo else mpf(1)
    r = g * (1 / w)
    E = r * r * r * s
    return E.v, E.g.get(0, mpf(0)), E.h.get((0, 0), mpf(0))


class JointRef:
    """One joint's frames (from `q_ref` and the edge) and its evaluation at 50 digits."""

    def __init__(
        self,
        uid: int,
        q_ref_i: Sequence[float],
        q_ref_j: Sequence[float],
        edge: Sequence[Sequence[float]] | None = None,
        local_edge: Sequence[Sequence[Sequence[float]]] | None = None,
    ) -> None:
        """From a world `edge` [p0, p1] (v1) or a body-local `local_edge` [[l0, l1], [r0, r1]] (v1.2)."""
        assert uid in (669, 670), uid
        self.uid = uid
        with mp.workdps(DPS):
            refs = [_split(q_ref_i), _split(q_ref_j)]
            R = [polar_rotation(A) for _, A in refs]
            if local_edge is None:
                p0, p1 = _mpv(edge[0]), _mpv(edge[1])
                t = _normalize([p1[r] - p0[r] for r in range(3)])
                c = None
            else:
                (l0, l1), (r0, _) = ([_mpv(p) for p in side] for side in local_edge)
                # The engine carries the local edge to the world by R_i (670) or A_ref_i itself (669).
                turn = R[0] if uid == 670 else refs[0][1]
                t = _normalize(_matvec(turn, [l1[r] - l0[r] for r in range(3)]))
                c = [l0, r0]
            if uid == 670:
                test = [mpf(0), mpf(1), mpf(0)] if abs(t[0]) > mpf("0.9") else [mpf(1), mpf(0), mpf(0)]
                n = _normalize(_cross(t, test))
                b = _normalize(_cross(t, n))
                # F = [B_i, N_i, B_j, N_j]: local vectors R_k^T b, R_k^T n; all directions.
                self.local = [_tmatvec(R[0], b), _tmatvec(R[0], n), _tmatvec(R[1], b), _tmatvec(R[1], n)]
                self.alpha = [0, 0, 0, 0]
            else:
                # F = [C_i, T_i, C_j, T_j]: anchors c_k = A_ref_k^-1 (p0 - p_ref_k) (or as given), axes R_k^T t.
                if c is None:
                    c = []
                    for p_ref, A_ref in refs:
                        sol = mp.lu_solve(mp.matrix(A_ref), mp.matrix([p0[r] - p_ref[r] for r in range(3)]))
                        c.append([sol[r] for r in range(3)])
                self.local = [c[0], _tmatvec(R[0], t), c[1], _tmatvec(R[1], t)]
                self.alpha = [1, 0, 1, 0]
            self.t, self.R = t, R

    def frames(self, q_i: Sequence[float], q_j: Sequence[float]) -> list[Vec]:
        """The four frame quantities F_k = alpha_k p + A v_k of bodies i (k = 0, 1) and j (k = 2, 3)."""
        bodies = [_split(q_i), _split(q_j)]
        F = []
        for k in range(4):
            p, A = bodies[k // 2]
            Av = _matvec(A, self.local[k])
            F.append([Av[r] + p[r] for r in range(3)] if self.alpha[k] else Av)
        return F

    def absolute_zero(self, F_ref: list) -> Any:
        """v1.2 `origin: "absolute"`: x at q_ref from the frames' own zero (atan2(sin, cos), or theta)."""
        if self.uid == 670:
            c, s = _cos_sin(F_ref)
            return mp.atan2(s, c)
        return _theta(F_ref)

    def _x_value(self, F: list, F_prev: list, F_ref: list, theta_prev: Any = None, absolute: bool = False) -> Any:
        """x; `theta_prev` (v1.1, 670: prev_coordinate - offset) replaces DeltaTheta(q_prev, q_ref) and
        whatever origin; `absolute` (v1.2) adds `absolute_zero` otherwise."""
        x0 = self.absolute_zero(F_ref) if absolute and theta_prev is None else mpf(0)
        if self.uid == 670:
            cs_prev = _cos_sin(F_prev)
            if theta_prev is None:
                theta_prev = x0 + _delta_theta(cs_prev, _cos_sin(F_ref))
            return theta_prev + _delta_theta(_cos_sin(F), cs_prev)
        th_prev = _theta(F_prev)
        return x0 + (th_prev - _theta(F_ref)) + (_theta(F) - th_prev)

    def _x_jet(self, F: list) -> Jet:
        """dx/dF and d2x/dF2 (12 variables, index 3k + r) from the q-dependent term only."""
        FJ = [[Jet.var(F[k][r], 3 * k + r) for r in range(3)] for k in range(4)]
        if self.uid == 670:
            c, s = _cos_sin(FJ)
            # DeltaTheta(q, q_prev) = arg(z conj(z_prev)), z = cos + i sin: its q-derivatives are those of Im log z.
            return (c + s * mpc(0, 1)).log().imag()
        return _theta(FJ)

    def J(self) -> list[list[tuple[int, Any]]]:
        """Sparse dF/dq: row 3k + r -> [(dof column among the 24, coefficient)]."""
        rows = []
        for k in range(4):
            base = 12 * (k // 2)
            for r in range(3):
                row = [(base + 3 + 3 * r + c, self.local[k][c]) for c in range(3)]  # A[r, c] at 3 + 3r + c
                if self.alpha[k]:
                    row.append((base + r, mpf(1)))  # p[r]
                rows.append(row)
        return rows

    def x(self, q: Sequence[Sequence[float]], q_prev: Sequence[Sequence[float]], q_ref: Sequence[Sequence[float]]) -> Any:
        with mp.workdps(DPS):
            return self._x_value(self.frames(*q), self.frames(*q_prev), self.frames(*q_ref))

    def energy_at(self, q24: Sequence[Any], x_prev: Any, F_prev: list, lower: float, upper: float, strength: float) -> Any:
        """Energy at a current DOF vector given in mp (for 50-digit finite differences); x_prev = x at q = q_prev."""
        F = self.frames(q24[:12], q24[12:])
        if self.uid == 670:
            x = x_prev + _delta_theta(_cos_sin(F), _cos_sin(F_prev))
        else:
            x = x_prev + (_theta(F) - _theta(F_prev))
        return penalty_jet(x, lower, upper, strength)[0]

    def evaluate(
        self,
        q: Sequence[Sequence[float]],
        q_prev: Sequence[Sequence[float]],
        q_ref: Sequence[Sequence[float]],
        lower: float,
        upper: float,
        strength: float,
        derivatives: bool = True,
        offset: float = 0.0,
        prev_coordinate: float | None = None,
        origin: str = "q_ref",
        hessians: bool = True,
    ) -> JointResult:
        """x, E and (if asked) the gradient and both Hessians w.r.t. [q_i, q_j]; v1.1's `offset` and
        `prev_coordinate` (670 only) and v1.2's `origin` as CONTRACT.md defines them. `hessians=False`: the
        gradient without the Hessians (None), whose eigen-decomposition and congruences are most of the cost."""
        with mp.workdps(DPS):
            off = mpf(float(offset))
            theta_prev = None if prev_coordinate is None else mpf(float(prev_coordinate)) - off
            F = self.frames(*q)
            x = self._x_value(F, self.frames(*q_prev), self.frames(*q_ref), theta_prev, origin == "absolute")
            E, dE, d2E = penalty_jet(x, mpf(float(lower)) - off, mpf(float(upper)) - off, strength)
            zero_g = [mpf(0)] * 24
            zero_h = [[mpf(0)] * 24 for _ in range(24)] if hessians else None
            if not derivatives or dE == 0:
                return JointResult(x, E, zero_g, zero_h, zero_h and [row[:] for row in zero_h], x + off)
            xj = self._x_jet(F)
            dx = xj.grad(12)
            J = self.J()
            grad = [mpf(0)] * 24
            for f, row in enumerate(J):
                for col, coef in row:
                    grad[col] += dE * dx[f] * coef
            if not hessians:
                return JointResult(x, E, grad, None, None, x + off)
            Hx = xj.hess(12)
            rank1 = [[d2E * dx[a] * dx[b] for b in range(12)] for a in range(12)]
            curv = [[dE * Hx[a][b] for b in range(12)] for a in range(12)]
            M_exact = [[rank1[a][b] + curv[a][b] for b in range(12)] for a in range(12)]
            P = _psd(curv) if self.uid == 670 else _prismatic_psd(dE, F)
            M_psd = [[rank1[a][b] + P[a][b] for b in range(12)] for a in range(12)]
            return JointResult(x, E, grad, _congruence(J, M_exact), _congruence(J, M_psd), x + off)


def _psd(M: Mat) -> Mat:
    """Symmetric M with its negative eigenvalues clamped to 0 (mpmath eigsy)."""
    n = len(M)
    A = mp.matrix(n, n)
    for a in range(n):
        for b in range(n):
            A[a, b] = (M[a][b] + M[b][a]) / 2
    lam, V = mp.eigsy(A)
    keep = [i for i in range(n) if lam[i] > 0]
    return [[mp.fsum(V[a, i] * lam[i] * V[b, i] for i in keep) for b in range(n)] for a in range(n)]


def _prismatic_psd(dE: Any, F: list) -> Mat:
    """The engine's prismatic projection (v1.2): `E' d2x/dF01^2` projected in `F01 = [D, T_i, -T_j]`
    (9 variables, `D = C_j - C_i`, x = D . (T_i - (-T_j)) / 2 differentiated there), then `M^T P M`
    with `M = dF01/dF` (9 x 12)."""
    C_i, T_i, C_j, T_j = F
    F01 = [[C_j[r] - C_i[r] for r in range(3)], T_i, [-v for v in T_j]]
    V = [[Jet.var(F01[k][r], 3 * k + r) for r in range(3)] for k in range(3)]
    x = _jdot(V[0], [V[1][r] - V[2][r] for r in range(3)]) * mpf(0.5)
    H = x.hess(9)
    P = _psd([[dE * H[a][b] for b in range(9)] for a in range(9)])
    # M: D from -C_i + C_j, T_i from T_i, -T_j from T_j (blocks of F: C_i 0, T_i 1, C_j 2, T_j 3).
    M = [[mpf(0)] * 12 for _ in range(9)]
    for r in range(3):
        M[r][r], M[r][6 + r] = mpf(-1), mpf(1)
        M[3 + r][3 + r] = mpf(1)
        M[6 + r][9 + r] = mpf(-1)
    return [[mp.fsum(M[a][f] * P[a][b] * M[b][g] for a in range(9) for b in range(9) if M[a][f] and M[b][g])
             for g in range(12)] for f in range(12)]


def _congruence(J: list[list[tuple[int, Any]]], M: Mat) -> Mat:
    """J^T M J (24 x 24) with the sparse J of `JointRef.J`."""
    H = [[mpf(0)] * 24 for _ in range(24)]
    for f, row_f in enumerate(J):
        for g, row_g in enumerate(J):
            m = M[f][g]
            if m == 0:
                continue
            for a, ca in row_f:
                Ha = H[a]
                for b, cb in row_g:
                    Ha[b] += ca * m * cb
    return H


# ---------------------------------------------------------------- whole requests


def reference_request(request: Mapping[str, Any], derivatives: bool = True, hessians: bool = True) -> list[dict[str, Any]]:
    """Every joint of a CONTRACT v1 / v1.1 / v1.2 request dict, per batch, as float64 arrays rounded from 50 digits.

    Each batch: `x`, `coordinate`, `energy` (N,), `gradient` (N, 24), `hessian_exact`, `hessian_psd`
    (N, 24, 24; absent with `hessians=False`), and `mp` (the `JointResult`s). Inactive joints have exact zeros.
    """
    bodies = request["bodies"]
    q, q_prev, q_ref = (np.asarray(bodies[k], dtype=np.float64) for k in ("q", "q_prev", "q_ref"))
    out = []
    for batch in request["batches"]:
        res = []
        n = len(batch["body_ids"])
        offsets = batch.get("offset") or [0.0] * n
        prev = batch.get("prev_coordinate") or [None] * n
        strength = batch.get("strength") or [1.0] * n
        local = "local_edges" in batch and batch["local_edges"] is not None
        edges = batch["local_edges"] if local else batch["edges"]
        rows = zip(batch["body_ids"], edges, batch["lower"], batch["upper"], strength, offsets, prev)
        for (i, j), edge, lo, up, s, off, pc in rows:
            geometry = {"local_edge": edge} if local else {"edge": edge}
            ref = JointRef(int(batch["constitution_uid"]), q_ref[i], q_ref[j], **geometry)
            res.append(
                ref.evaluate((q[i], q[j]), (q_prev[i], q_prev[j]), (q_ref[i], q_ref[j]), lo, up, s, derivatives, off, pc,
                             batch.get("origin", "q_ref"), hessians)
            )
        flo = [r.as_float() for r in res]
        n = len(flo)
        out.append(
            dict(
                constitution_uid=int(batch["constitution_uid"]),
                x=np.array([f["x"] for f in flo]),
                coordinate=np.array([f["coordinate"] for f in flo]),
                energy=np.array([f["energy"] for f in flo]),
                gradient=np.array([f["gradient"] for f in flo]).reshape(n, 24),
                mp=res,
            )
        )
        if hessians:
            for key in ("hessian_exact", "hessian_psd"):
                out[-1][key] = np.array([f[key] for f in flo]).reshape(n, 24, 24)
    return out


def reference_total_energy(ref: list[dict[str, Any]]) -> float:
    with mp.workdps(DPS):
        return float(mp.fsum(r.energy for b in ref for r in b["mp"]))
