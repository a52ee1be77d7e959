"""Spherical-triangle geometry of Cole & Crassidis (2006, section III), vectorised.

Every function takes arrays of unit vectors A, B, C of shape (..., 3) (one triangle per leading
index) or side lengths, and works on millions of triangles at once without Python loops.

Sides (eq. 16): a = angle(b1, b2), b = angle(b2, b3), c = angle(b3, b1), computed from the chord
(2 asin(|u - v| / 2)), which is accurate for small angles where acos(u . v) is not.

Area (eqs. 15-16, L'Huilier): A = 4 atan sqrt(tan(s/2) tan((s-a)/2) tan((s-b)/2) tan((s-c)/2)),
s = (a + b + c) / 2.

Area sigma (eqs. 20-24): H = dA/d(a, b, c) = 4 / (1 + z^2) dz/d(a, b, c) with z the square root in
eq. 15 and dz/da = (u1 - u2 + u3 + u4) / (8 z) etc. (eq. 22; the paper prints a leading minus sign,
which does not change the variance: d(z^2)/da = (u1 - u2 + u3 + u4) / 4 with the u of eq. 23).
The paper then takes sigma_A^2 = sigma^2 H H^T (eq. 24): the three sides as independent, each with
the star's variance sigma^2. A side between two stars each with a tangent-plane error of sigma per
axis has variance 2 sigma^2 (eq. 13), and two sides that share a star are correlated:
cov(side 1-2, side 1-3) = sigma^2 cos(vertex angle at star 1). With that covariance C (eq. 19's R),
sigma_A^2 = H C H^T, which is what a Monte Carlo of noisy stars gives (Monte Carlo / H C H^T on 300
random catalog triangles: 0.93, 0.99, 1.06 at the 5th, 50th, 95th percentiles). Eq. 24 under-states
it (by sqrt(3) for an equilateral triangle; Monte Carlo / eq. 24: median 1.17, 95th percentile 1.63)
and over-states it for slivers, whose correlated side errors cancel (5th percentile 0.14). Both are
here: `area_sigma_paper` and `area_sigma_stars`.

Polar moment (eq. 25): I_p = sum theta^2 dA over the pieces of a recursive subdivision: each
triangle is split into four by the midpoints of its sides (normalised onto the sphere: the pieces
are spherical triangles), `depth` times, so depth 3 gives 4^3 = 64 pieces; theta is the arc from a
piece's centroid to the whole triangle's centroid, dA the piece's L'Huilier area. The centroid of a
spherical triangle is taken as its normalised vertex mean (exact in the planar limit). In the planar
limit the depth-d sum is J (1 - 4^-d) exactly, J = A (a^2 + b^2 + c^2) / 36 the polar moment about
the centroid (parallel-axis theorem: every piece is the triangle scaled by 2^-d, so the pieces' own
moments add up to J 4^-d); depth 3 is 1.6 % below J, and the same for the catalog and the
measurement, which is all that matters for matching.

The search measures one to a few triangles at a time, where numpy's per-call overhead is the cost:
`triangle_sigmas`, `sides_few` and `lhuilier_few` (the area), `dot3` / `cross3` (plain floats) and `polar_moment_few`,
`lhuilier_zero_first` (fewer numpy calls) give the numbers of the vectorised functions to the last bit
(tests/test_triangle.py checks them bit for bit).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from skyview.core.catalog import einsum_c as _einsum

MOMENT_DEPTH = 3  # the paper's recursion depth: 4^3 = 64 pieces
_CHUNK = 1024  # triangles per vectorised block in polar_moment (~1 MB per array: stays in cache)


def normalize(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / _norm(v, keepdims=True)


def _norm(v: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """np.linalg.norm(v, axis=-1) of a float64 array, the same sums, without its per-call checks."""
    return np.sqrt(np.add.reduce(v * v, axis=-1, keepdims=keepdims))


def _stack3(x, y, z) -> np.ndarray:
    """np.stack([x, y, z]) of three arrays of one shape (float64), without its per-call overhead."""
    out = np.empty((3,) + np.shape(x))
    out[0], out[1], out[2] = x, y, z
    return out


def arc(u: np.ndarray, v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Angle between unit vectors (last axis), accurate for small angles (written to `out` if given)."""
    d = np.asarray(u, dtype=np.float64) - np.asarray(v, dtype=np.float64)
    return np.multiply(2.0, np.arcsin(np.minimum(np.sqrt(_einsum("...i,...i->...", d, d)) / 2.0, 1.0)), out=out)


def sides(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sides (a, b, c) = (angle(A, B), angle(B, C), angle(C, A)) as in eq. 16."""
    return arc(A, B), arc(B, C), arc(C, A)


def lhuilier(a, b, c) -> np.ndarray:
    """Spherical excess (area on the unit sphere) from the three sides, eqs. 15-16.

    A degenerate triangle (one side equal to the sum of the others, up to rounding) has area 0.
    """
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    s = 0.5 * (a + b + c)
    p = np.tan(0.5 * s) * np.tan(0.5 * (s - a)) * np.tan(0.5 * (s - b)) * np.tan(0.5 * (s - c))
    return 4.0 * np.arctan(np.sqrt(np.maximum(p, 0.0)))


def lhuilier_zero_first(S: np.ndarray) -> np.ndarray:
    """lhuilier(S[1], S[2], S[3]) of sides stacked (4, ...) after a row of zeros, the same numbers: as
    s - 0 = s, the four tangents are one np.tan call (for small arrays the calls are the cost)."""
    s = 0.5 * np.add.reduce(S[1:], axis=0)  # (a + b) + c: a reduction over the first axis adds in order
    T = np.tan(0.5 * (s - S))
    return 4.0 * np.arctan(np.sqrt(np.maximum(np.multiply.reduce(T, axis=0), 0.0)))


def area(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Area of the spherical triangle(s) with vertices A, B, C (L'Huilier)."""
    return lhuilier(*sides(A, B, C))


def area_jacobian(a, b, c) -> np.ndarray:
    """H = dA/d(a, b, c), eqs. 20-23; shape (..., 3).

    Where the triangle is degenerate (z = 0) the derivative is unbounded; it is returned as inf so
    that a bound built on it accepts everything rather than nothing.
    """
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    q = np.empty((4,) + np.broadcast_shapes(a.shape, b.shape, c.shape))  # all four at once
    q[0], q[1], q[2], q[3] = (a + b + c) / 4.0, (b + c - a) / 4.0, (a + c - b) / 4.0, (a + b - c) / 4.0
    t1, t2, t3, t4 = np.tan(q)
    s1, s2, s3, s4 = 1.0 / np.cos(q) ** 2
    u1 = s1 * t2 * t3 * t4  # eq. 23a
    u2 = t1 * s2 * t3 * t4  # eq. 23b
    u3 = t1 * t2 * s3 * t4  # eq. 23c
    u4 = t1 * t2 * t3 * s4  # eq. 23d
    z2 = np.maximum(t1 * t2 * t3 * t4, 0.0)
    z = np.sqrt(z2)  # eq. 21
    with np.errstate(divide="ignore", invalid="ignore"):
        dz = np.empty(z.shape + (3,))
        dz[..., 0], dz[..., 1], dz[..., 2] = u1 - u2 + u3 + u4, u1 + u2 - u3 + u4, u1 + u2 + u3 - u4
        dz /= 8.0 * z[..., None]
    H = 4.0 / (1.0 + z2[..., None]) * dz  # eq. 20
    return np.where(np.isfinite(H), H, np.inf)


def area_sigma_paper(a, b, c, sigma: float) -> np.ndarray:
    """sigma_A = sigma sqrt(H H^T), eq. 24 as printed (sides independent, variance sigma^2 each)."""
    H = area_jacobian(a, b, c)
    return float(sigma) * np.sqrt(np.sum(H * H, axis=-1))


def vertex_angles(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cos of the spherical angles at A, B and C (between the tangents towards the other two)."""
    A, B, C = (np.asarray(x, dtype=np.float64) for x in (A, B, C))
    P, Q, R = _stack3(A, B, C), _stack3(B, C, A), _stack3(C, A, B)  # the three vertices at once
    tq = Q - np.einsum("...i,...i->...", Q, P)[..., None] * P
    tr = R - np.einsum("...i,...i->...", R, P)[..., None] * P
    nq, nr = _norm(tq), _norm(tr)
    with np.errstate(divide="ignore", invalid="ignore"):
        cs = np.einsum("...i,...i->...", tq, tr) / (nq * nr)
    cs[np.isnan(cs)] = 1.0  # = np.clip(np.nan_to_num(cs, nan=1.0), -1.0, 1.0): +-inf clip to +-1 either way
    np.minimum(np.maximum(cs, -1.0, out=cs), 1.0, out=cs)
    return cs[0], cs[1], cs[2]


def side_covariance(A: np.ndarray, B: np.ndarray, C: np.ndarray, sigma: float) -> np.ndarray:
    """Covariance (..., 3, 3) of the measured sides (a, b, c) for a tangent-plane error of sigma per axis.

    var = 2 sigma^2 (eq. 13); sides sharing a star: sigma^2 cos(vertex angle at that star).
    """
    cA, cB, cC = vertex_angles(A, B, C)
    s2 = float(sigma) ** 2
    shape = np.shape(cA)
    Cm = np.empty(shape + (3, 3))
    Cm[..., 0, 0] = Cm[..., 1, 1] = Cm[..., 2, 2] = 2.0 * s2
    Cm[..., 0, 1] = Cm[..., 1, 0] = s2 * cB  # a = AB and b = BC share B
    Cm[..., 1, 2] = Cm[..., 2, 1] = s2 * cC  # b = BC and c = CA share C
    Cm[..., 0, 2] = Cm[..., 2, 0] = s2 * cA  # c = CA and a = AB share A
    return Cm


def area_sigma_stars(A: np.ndarray, B: np.ndarray, C: np.ndarray, sigma: float) -> np.ndarray:
    """sigma_A = sqrt(H C H^T) with C the side covariance of noisy stars (eq. 19 with the right R)."""
    H = area_jacobian(*sides(A, B, C))
    Cm = side_covariance(A, B, C, sigma)
    with np.errstate(invalid="ignore"):
        v = np.einsum("...i,...ij,...j->...", H, Cm, H)
    return np.sqrt(np.where(np.isfinite(v), np.maximum(v, 0.0), np.inf))


def centroid(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Normalised vertex mean."""
    return normalize(np.asarray(A) + np.asarray(B) + np.asarray(C))


def subdivide(A: np.ndarray, B: np.ndarray, C: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 4^depth pieces of each triangle: arrays (n, 4^depth, 3) of their vertices.

    Each level splits (P, Q, R) into (P, pq, rp), (pq, Q, qr), (rp, qr, R) and (pq, qr, rp), with pq the
    normalised midpoint of P and Q.
    """
    P = np.asarray(A, dtype=np.float64).reshape(-1, 1, 3)
    Q = np.asarray(B, dtype=np.float64).reshape(-1, 1, 3)
    R = np.asarray(C, dtype=np.float64).reshape(-1, 1, 3)
    for _ in range(int(depth)):
        pq, qr, rp = normalize(P + Q), normalize(Q + R), normalize(R + P)
        P, Q, R = (np.concatenate([P, pq, rp, pq], axis=1), np.concatenate([pq, Q, qr, qr], axis=1),
                   np.concatenate([rp, qr, R, rp], axis=1))
    return P, Q, R


@lru_cache(maxsize=None)
def _plan(depth: int):
    """Index plan of the depth-`depth` subdivision, evaluated on its shared vertices and edges.

    The recursive split makes a triangular grid of (n + 1)(n + 2) / 2 points, n = 2^depth (45 at
    depth 3), with integer barycentric coordinates (i, j, n - i - j). Level L adds the points whose
    coordinates at that level's spacing have two odd entries: each is the normalised sum of the two
    points of the coarser level on either side of it (exactly the pq = normalise(P + Q) of
    `subdivide`). Returns the number of points, the corner indices (A, B, C), the levels as
    (new, end1, end2) index arrays, the 4^depth pieces as point triples, the distinct edges and each
    piece's edges (so that every side is computed once: 108 arcs instead of 192 at depth 3).
    """
    n = 2 ** depth
    pts = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    index = {p: m for m, p in enumerate(pts)}
    corners = (index[(n, 0)], index[(0, n)], index[(0, 0)])
    levels = []
    for L in range(1, depth + 1):
        step = 2 ** (depth - L)
        new, e1, e2 = [], [], []
        for i, j in pts:
            if i % step or j % step:
                continue
            a, b, c = i // step, j // step, (n - i - j) // step
            if a % 2 == 0 and b % 2 == 0 and c % 2 == 0:
                continue  # a point of the coarser level
            if a % 2 and b % 2:
                p1, p2 = (a + 1, b - 1), (a - 1, b + 1)
            elif a % 2:
                p1, p2 = (a + 1, b), (a - 1, b)
            else:
                p1, p2 = (a, b + 1), (a, b - 1)
            new.append(index[(i, j)])
            e1.append(index[(p1[0] * step, p1[1] * step)])
            e2.append(index[(p2[0] * step, p2[1] * step)])
        levels.append((np.array(new, dtype=np.intp), np.array(e1, dtype=np.intp), np.array(e2, dtype=np.intp)))
    tris = []
    for i in range(n):
        for j in range(n - i):
            tris.append((index[(i + 1, j)], index[(i, j + 1)], index[(i, j)]))
            if i + j < n - 1:
                tris.append((index[(i + 1, j + 1)], index[(i, j + 1)], index[(i + 1, j)]))
    tris = np.array(tris, dtype=np.intp).reshape(-1, 3)
    all_edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    edges, inverse = np.unique(all_edges, axis=0, return_inverse=True)
    tri_edges = inverse.reshape(3, -1).T
    return len(pts), corners, levels, tris, edges, tri_edges


def polar_moment(A: np.ndarray, B: np.ndarray, C: np.ndarray, depth: int = MOMENT_DEPTH) -> np.ndarray:
    """Polar moment about the centroid by recursive subdivision (eq. 25), one value per triangle.

    Same pieces as `subdivide` (the reference), evaluated on the shared grid of `_plan`, in blocks
    of _CHUNK triangles.
    """
    if int(depth) < 0:
        raise ValueError("depth must be >= 0")
    A = np.asarray(A, dtype=np.float64)
    shape = A.shape[:-1]
    A = A.reshape(-1, 3)
    B = np.asarray(B, dtype=np.float64).reshape(-1, 3)
    C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
    n_pts, corners, levels, tris, edges, tri_edges = _plan(int(depth))
    out = np.empty(len(A))
    for s in range(0, len(A), _CHUNK):
        e = min(s + _CHUNK, len(A))
        P = np.empty((n_pts, e - s, 3))
        P[corners[0]], P[corners[1]], P[corners[2]] = A[s:e], B[s:e], C[s:e]
        for new, e1, e2 in levels:
            P[new] = normalize(P[e1] + P[e2])
        side = arc(P[edges[:, 0]], P[edges[:, 1]])
        dA = lhuilier(side[tri_edges[:, 0]], side[tri_edges[:, 1]], side[tri_edges[:, 2]])
        G = centroid(A[s:e], B[s:e], C[s:e])
        theta = arc(normalize(P[tris[:, 0]] + P[tris[:, 1]] + P[tris[:, 2]]), G[None])
        out[s:e] = np.einsum("ij,ij->j", theta * theta, dA)
    return out.reshape(shape)


def planar_polar_moment(a, b, c) -> np.ndarray:
    """Polar moment of a plane triangle about its centroid, A (a^2 + b^2 + c^2) / 36 (Heron's A)."""
    a, b, c = (np.asarray(x, dtype=np.float64) for x in (a, b, c))
    s = 0.5 * (a + b + c)
    A = np.sqrt(np.maximum(s * (s - a) * (s - b) * (s - c), 0.0))
    return A * (a * a + b * b + c * c) / 36.0


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v over the last axis (np.cross without its per-call overhead)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out


def triple(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """A . (B x C): positive when A, B, C run counter-clockwise seen from outside the sphere.

    A rotation keeps its sign, a mirror flips it: the handedness of a triangle.
    """
    return np.einsum("...i,...i->...", np.asarray(A, dtype=np.float64), cross(B, C))


def triple_sigma(A: np.ndarray, B: np.ndarray, C: np.ndarray, sigma: float) -> np.ndarray:
    """1-sigma of the triple product for a tangent-plane error of sigma per axis on each vertex."""
    A, B, C = (np.asarray(x, dtype=np.float64) for x in (A, B, C))
    P = _stack3(A, B, C)  # the three vertices at once
    g = cross(_stack3(B, C, A), _stack3(C, A, B))  # the gradient of the triple product at each
    g = g - np.einsum("...i,...i->...", g, P)[..., None] * P  # the part a tangent-plane error sees
    v = np.einsum("...i,...i->...", g, g)
    return float(sigma) * np.sqrt(v[0] + v[1] + v[2])


def enclosing_cap_radius(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Radius of the smallest spherical cap holding the three points (for triangles under a hemisphere).

    The cap on the longest side as diameter when it holds the third point (an obtuse triangle),
    else the circumscribed cap.
    """
    A, B, C = (np.asarray(x, dtype=np.float64) for x in (A, B, C))
    s = np.stack(sides(A, B, C), axis=-1)
    V = np.stack([A, B, C], axis=-2)
    k = np.argmax(s, axis=-1)
    p = np.take_along_axis(V, k[..., None, None], axis=-2)[..., 0, :]
    q = np.take_along_axis(V, ((k + 1) % 3)[..., None, None], axis=-2)[..., 0, :]
    r = np.take_along_axis(V, ((k + 2) % 3)[..., None, None], axis=-2)[..., 0, :]
    r_diam = 0.5 * np.max(s, axis=-1)
    inside = arc(normalize(p + q), r) <= r_diam * (1.0 + 1e-12)
    n = cross(B - A, C - A)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = n / nn
    n = n * np.sign(np.einsum("...i,...i->...", n, A + B + C))[..., None]
    r_circ = arc(n, A)
    return np.where(inside | ~np.all(np.isfinite(n), axis=-1), r_diam, r_circ)


def dot3(x, y) -> float:
    """x . y of two 3-sequences of floats, summed as np.einsum("...i,...i->...") sums three terms (the
    first and third, then the second), so that it gives its numbers to the last bit."""
    return (x[0] * y[0] + x[2] * y[2]) + x[1] * y[1]


def sign(v: float) -> int:
    """np.sign of a float, as an int (0 for 0)."""
    return (v > 0.0) - (v < 0.0)


def cross3(u, v) -> tuple[float, float, float]:
    """u x v of two 3-sequences of floats (the operations of `cross`)."""
    return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]


def triangle_sigmas(A, B, C, a, b, c, sigma: float) -> tuple[list[float], list[float]] | None:
    """(area_sigma_stars(A, B, C, sigma), triple_sigma(A, B, C, sigma)) of a few triangles (arrays or lists
    of 3-vectors), with their sides (a, b, c) = sides(A, B, C) already measured: the same numbers to the
    last bit (the same operations in the same order; tan and cos from numpy, whose SIMD forms differ
    from math's in the last bit), as lists of floats. For one to a few triangles the numpy forms cost
    ~90 us in call overheads; this costs ~10 us a triangle. None when a triangle is degenerate (a zero
    division: use the numpy forms, which turn it into inf)."""
    A, B, C, a, b, c = (x.tolist() if isinstance(x, np.ndarray) else x for x in (A, B, C, a, b, c))
    n = len(A)
    q = []  # the four quarter sums of eq. 23 of every triangle, for one np.tan and one np.cos call
    for x, y, z in zip(a, b, c):
        q += ((x + y + z) / 4.0, (y + z - x) / 4.0, (x + z - y) / 4.0, (x + y - z) / 4.0)
    q = np.array(q)
    tan, cos = np.tan(q).tolist(), np.cos(q).tolist()
    s2 = float(sigma) ** 2
    sig = float(sigma)
    out_area, out_triple = [], []
    # (dot3 and cross3 written out: the same operations in the same order, without the calls)
    for k in range(n):
        t1, t2, t3, t4 = tan[4 * k:4 * k + 4]
        c1, c2, c3, c4 = cos[4 * k:4 * k + 4]
        s1, s2_, s3, s4 = 1.0 / (c1 * c1), 1.0 / (c2 * c2), 1.0 / (c3 * c3), 1.0 / (c4 * c4)
        u1, u2, u3, u4 = s1 * t2 * t3 * t4, t1 * s2_ * t3 * t4, t1 * t2 * s3 * t4, t1 * t2 * t3 * s4  # eq. 23
        z2 = t1 * t2 * t3 * t4
        if not z2 > 0.0:
            return None
        z = math.sqrt(z2)
        den = 8.0 * z
        w = 4.0 / (1.0 + z2)
        h0, h1, h2 = w * ((u1 - u2 + u3 + u4) / den), w * ((u1 + u2 - u3 + u4) / den), w * ((u1 + u2 + u3 - u4) / den)
        # cos of the vertex angles at A, B, C (vertex_angles) and the triple product's gradients (triple_sigma)
        P = (A[k], B[k], C[k])
        cs, v = [], []
        for i in range(3):
            (p0, p1, p2), (q0, q1, q2), (r0, r1, r2) = P[i], P[(i + 1) % 3], P[(i + 2) % 3]
            qp, rp = (q0 * p0 + q2 * p2) + q1 * p1, (r0 * p0 + r2 * p2) + r1 * p1
            x0, x1, x2 = q0 - qp * p0, q1 - qp * p1, q2 - qp * p2  # q's tangent part at p
            y0, y1, y2 = r0 - rp * p0, r1 - rp * p1, r2 - rp * p2  # r's
            nn = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) * math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
            if not nn > 0.0:
                return None
            cs.append(min(max(((x0 * y0 + x2 * y2) + x1 * y1) / nn, -1.0), 1.0))
            g0, g1, g2 = q1 * r2 - q2 * r1, q2 * r0 - q0 * r2, q0 * r1 - q1 * r0  # q x r
            gp = (g0 * p0 + g2 * p2) + g1 * p1
            g0, g1, g2 = g0 - gp * p0, g1 - gp * p1, g2 - gp * p2
            v.append((g0 * g0 + g2 * g2) + g1 * g1)
        cA, cB, cC = cs
        d = 2.0 * s2
        eB, eA, eC = s2 * cB, s2 * cA, s2 * cC
        # H C H^T summed term by term in row order, as the loop over (i, j) from 0.0 did
        var = ((((((((h0 * d * h0 + h0 * eB * h1) + h0 * eA * h2) + h1 * eB * h0) + h1 * d * h1) + h1 * eC * h2)
                 + h2 * eA * h0) + h2 * eC * h1) + h2 * d * h2)
        out_area.append(math.sqrt(max(var, 0.0)) if math.isfinite(var) else np.inf)
        out_triple.append(sig * math.sqrt(v[0] + v[1] + v[2]))
    return out_area, out_triple


def sides_few(A, B, C) -> list[tuple[float, float, float]]:
    """sides(A, B, C) of a few triangles (sequences of 3-vectors) as (a, b, c) tuples of floats: the same
    numbers to the last bit (each chord summed in order, as np.einsum and np.add.reduce sum three terms;
    one numpy arcsin call for all of them). c, the angle of C and A, is also verify.angular_distance(C, A)."""
    half = []
    for P in zip(A, B, C):
        for (x0, x1, x2), (y0, y1, y2) in ((P[0], P[1]), (P[1], P[2]), (P[2], P[0])):  # a, b, c of `sides`
            d0, d1, d2 = x0 - y0, x1 - y1, x2 - y2
            half.append(min(math.sqrt((d0 * d0 + d2 * d2) + d1 * d1) / 2.0, 1.0))  # (dot3, written out)
    side = [2.0 * x for x in np.arcsin(half).tolist()]  # (doubling is exact: numpy's 2.0 * arcsin)
    return [(side[k], side[k + 1], side[k + 2]) for k in range(0, len(side), 3)]


def lhuilier_few(sides) -> list[float]:
    """lhuilier(a, b, c) of a few triangles' (a, b, c) as a list of floats: the same numbers to the last bit
    (tan and arctan from numpy, one call each for every triangle)."""
    arg = []
    for a, b, c in sides:
        s = 0.5 * (a + b + c)
        arg += (0.5 * s, 0.5 * (s - a), 0.5 * (s - b), 0.5 * (s - c))
    tan = np.tan(arg).tolist()
    # math.sqrt rounds as np.sqrt does (IEEE), and 4.0 * is exact
    p = [math.sqrt(max(tan[k] * tan[k + 1] * tan[k + 2] * tan[k + 3], 0.0)) for k in range(0, len(tan), 4)]
    return [4.0 * x for x in np.arctan(p).tolist()]


@lru_cache(maxsize=None)
def _few_plan(depth: int):
    """`_plan(depth)` relabelled for `polar_moment_few`: the corners, then each level's new points in one
    contiguous block ((start, stop, (2, k) ends) per level: written in place); the ends of every difference
    whose arc is taken, (2, e + 1 + pieces) into the points followed by the pieces' centroids: the edges,
    a last, zero-length edge (0, 0), whose arc is exactly 0, then each piece's centroid and the whole
    triangle's; each piece's (zero, a, b, c) edges as (4, pieces) (then s - 0 = s: the four L'Huilier
    tangents in one call); the pieces as (3, pieces + 1) with a last "piece" (A, B, C), whose normalised
    vertex sum is the centroid. Returns (points, blocks, arc ends, edges + 1, piece edges, pieces)."""
    n_pts, corners, levels, tris, edges, tri_edges = _plan(depth)
    order = list(corners) + [int(p) for new, _, _ in levels for p in new]
    relabel = np.empty(n_pts, dtype=np.intp)
    relabel[order] = np.arange(n_pts)
    blocks, pos = [], 3
    for new, e1, e2 in levels:
        blocks.append((pos, pos + len(new), np.stack([relabel[e1], relabel[e2]])))
        pos += len(new)
    edge_ends = np.concatenate([relabel[edges], [[0, 0]]]).T
    centroids = n_pts + np.arange(len(tris))
    arc_ends = np.concatenate([edge_ends, [centroids, np.full(len(tris), n_pts + len(tris))]], axis=1)
    piece_edges = np.concatenate([np.full((1, len(tris)), len(edges)), tri_edges.T])
    pieces = np.concatenate([relabel[tris], [[0, 1, 2]]]).T
    return n_pts, blocks, arc_ends, edge_ends.shape[1], piece_edges, pieces


def polar_moment_few(A, B, C, depth: int = MOMENT_DEPTH) -> np.ndarray:
    """polar_moment(A, B, C, depth) of (n, 3) arrays (or lists of n 3-vectors), the same numbers to the last
    bit (the same operations on the same values, the same final np.einsum), in half of the numpy calls: each
    level's points written in place, one gather per group of points (`ndarray.take`, a third of the cost of
    an index), sums of two or three terms added in order (as a reduction over the first axis adds), the
    centroid normalised with the pieces' vertex sums, the arcs of the sides and of the pieces' centroids in
    one pass, the four L'Huilier tangents in one call. For a few triangles, where the calls are the cost.

    The arcs are kept as half-angles x (arc = 2 x, exactly: doubling is exact), which saves three
    multiplications: L'Huilier's s = 0.5 (a + b + c) is (x + y + z) and 0.5 (s - a) is 0.5 s - x, to the
    bit (halving and doubling commute with rounding); its 4 arctan and theta^2 = 4 x^2 make each term of
    the final sum 16 times x^2 arctan, and so the sum 16 times the sum of those (every partial sum scaled
    by 16, exactly)."""
    n_pts, blocks, arc_ends, n_edges, piece_edges, pieces = _few_plan(int(depth))
    out = np.empty(len(A))
    for s in range(0, len(A), _CHUNK):
        e = min(s + _CHUNK, len(A))
        P = np.empty((n_pts, e - s, 3))
        P[:3] = (A[s:e], B[s:e], C[s:e])  # arrays or lists of 3-vectors: one conversion
        for lo, hi, ends in blocks:
            E = P.take(ends, axis=0)
            v = E[0] + E[1]
            np.divide(v, np.sqrt(np.add.reduce(v * v, axis=-1, keepdims=True)), out=P[lo:hi])  # normalize
        E = P.take(pieces, axis=0)
        Q = E[0] + E[1] + E[2]  # the pieces' vertex sums (in order, as np.add.reduce), then the whole triangle's
        Q /= np.sqrt(np.add.reduce(Q * Q, axis=-1, keepdims=True))  # centroids (normalize)
        E = np.concatenate([P, Q]).take(arc_ends, axis=0)  # the sides' ends, then each piece's centroid and G
        d = E[0] - E[1]
        half = np.arcsin(np.minimum(np.sqrt(_einsum("...i,...i->...", d, d)) / 2.0, 1.0))  # `arc` / 2
        S = half.take(piece_edges, axis=0)  # each piece's (zero, a, b, c) / 2
        T = np.tan(0.5 * np.add.reduce(S[1:], axis=0) - S)  # `lhuilier_zero_first`'s tangents
        excess = np.arctan(np.sqrt(np.maximum(np.multiply.reduce(T, axis=0), 0.0)))  # dA / 4
        theta = half[n_edges:]  # theta / 2
        out[s:e] = _einsum("ij,ij->j", theta * theta, excess)
    return out * 16.0
