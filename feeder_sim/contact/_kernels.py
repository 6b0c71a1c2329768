"""Numba kernels of the contact step: collision narrow phase, islands, contact velocities,
the small-island Baraff-Dantzig solver and the large-island projected Gauss-Seidel.

Who calls what: ``collision.find_contacts`` -> ``narrow_phase``, ``clean_contacts``;
``dynamics.islands`` and ``TimeStepper`` -> ``island_groups``; ``TimeStepper`` ->
``drift``, ``speed_bounds``, ``contact_rows``, ``solve_small`` (-> ``dantzig``; also the position
projection's normal-row problems), ``solve_pgs``, ``apply_impulses``, ``feature_gaps``.
Each kernel reproduces the numpy / ``lcp`` code it replaces with the same arithmetic where
that code is the reference (the collision kernels give the same bits as the numpy version).

Compile time. Every kernel is compiled with ``cache=True``: the first run on a machine (or
after this file changes) compiles, about 28 s on a 2-core VM for what a single-box
time-stepping run needs (``solve_small`` with ``dantzig`` ~17 s, ``narrow_phase`` +
``clean_contacts`` ~7 s, the rest ~4 s, ``contact_rows`` the largest of it; ``solve_pgs``,
first used by piles, ~4 s more); later runs load the machine code from ``__pycache__`` in
~0.5 s. The position projection reuses ``solve_small`` rather than a kernel of its own, which
would compile ``dantzig`` (17 s) a second time. To keep compile time down the code
avoids numba's library sorts, ``searchsorted``, sets, ``lstsq``, ``@`` and array slice
assignment (each pulls in seconds of generic code, string formatting for errors included),
and is kept flat: numba generates every callee again inside each caller, so deep call trees
multiply the compile time (the Dantzig port is three functions for that reason).
"""

from __future__ import annotations

import numpy as np

from feeder_sim._jit import inner, jit


@inner
def _finite(a):
    """All entries finite (a loop: numpy's reductions are slow to compile)."""
    for v in a.flat:
        if not (v - v == 0.0):
            return False
    return True


@inner
def _argsort(keys):
    """Stable argsort (bottom-up merge sort). Hand-written because ``np.argsort`` with a
    ``kind`` compiles numba's generic sorts and string handling: seconds of compile time."""
    n = keys.shape[0]
    idx = np.empty(n, np.int64)
    for i in range(n):
        idx[i] = i
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        lo = 0
        while lo < n:
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i, j, k = lo, mid, lo
            while i < mid and j < hi:
                if keys[idx[j]] < keys[idx[i]]:
                    tmp[k] = idx[j]
                    j += 1
                else:
                    tmp[k] = idx[i]
                    i += 1
                k += 1
            while i < mid:
                tmp[k] = idx[i]
                i += 1
                k += 1
            while j < hi:
                tmp[k] = idx[j]
                j += 1
                k += 1
            lo += 2 * width
        idx, tmp = tmp, idx
        width *= 2
    return idx


@inner
def _where(mask):
    n = 0
    for v in mask:
        n += v
    out = np.empty(n, np.int64)
    q = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            out[q] = i
            q += 1
    return out


@inner
def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@jit
def island_groups(n_bodies, dynamic, a, b):
    """Islands of dynamic bodies joined by contacts (static / kinematic bodies never join).

    Returns ``(order, starts, bodies, body_starts)``: island i owns the contacts
    ``order[starts[i]:starts[i+1]]`` (ascending) and the dynamic bodies
    ``bodies[body_starts[i]:body_starts[i+1]]`` (ascending); islands are ordered by their
    smallest body index.
    """
    k = a.shape[0]
    parent = np.arange(n_bodies)
    for c in range(k):
        i, j = a[c], b[c]
        if dynamic[i] and dynamic[j]:
            ri, rj = _find(parent, i), _find(parent, j)
            if ri != rj:
                if ri < rj:
                    parent[rj] = ri
                else:
                    parent[ri] = rj
    # island number of every root, ascending root order
    root_of = np.empty(k, np.int64)
    used = np.zeros(n_bodies, np.bool_)
    for c in range(k):
        owner = a[c] if dynamic[a[c]] else b[c]
        r = _find(parent, owner)
        root_of[c] = r
        used[r] = True
    island_of_root = -np.ones(n_bodies, np.int64)
    n_isl = 0
    for r in range(n_bodies):
        if used[r]:
            island_of_root[r] = n_isl
            n_isl += 1
    # contacts: counting sort by island, stable
    starts = np.zeros(n_isl + 1, np.int64)
    for c in range(k):
        starts[island_of_root[root_of[c]] + 1] += 1
    for i in range(n_isl):
        starts[i + 1] += starts[i]
    fill = starts[:-1].copy()
    order = np.empty(k, np.int64)
    for c in range(k):
        i = island_of_root[root_of[c]]
        order[fill[i]] = c
        fill[i] += 1
    # bodies: dynamic bodies that appear in a contact, by island then index
    member = np.zeros(n_bodies, np.bool_)
    for c in range(k):
        if dynamic[a[c]]:
            member[a[c]] = True
        if dynamic[b[c]]:
            member[b[c]] = True
    body_starts = np.zeros(n_isl + 1, np.int64)
    for i in range(n_bodies):
        if member[i]:
            body_starts[island_of_root[_find(parent, i)] + 1] += 1
    for i in range(n_isl):
        body_starts[i + 1] += body_starts[i]
    bfill = body_starts[:-1].copy()
    bodies = np.empty(body_starts[n_isl], np.int64)
    for i in range(n_bodies):
        if member[i]:
            isl = island_of_root[_find(parent, i)]
            bodies[bfill[isl]] = i
            bfill[isl] += 1
    return order, starts, bodies, body_starts


@inner
def _rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia):
    """Per-row Jacobian blocks of contacts: rows [N_0..N_{c-1}, T_0..T_{c-1}].

    ``ja[i] = (d, r_a x d)`` acts on body a, ``jb[i] = -(d, r_b x d)`` on body b; ``ma`` /
    ``mb`` are the same blocks multiplied by the inverse mass (so ``dv = M^-1 J^T x``)."""
    c = a.shape[0]
    m = 2 * c
    ja = np.empty((m, 3))
    jb = np.empty((m, 3))
    ma = np.empty((m, 3))
    mb = np.empty((m, 3))
    for i in range(m):
        k = i if i < c else i - c
        if i < c:
            dx, dy = normal[k, 0], normal[k, 1]
        else:
            dx, dy = tangent[k, 0], tangent[k, 1]
        ia, ib = a[k], b[k]
        ja[i, 0] = dx
        ja[i, 1] = dy
        ja[i, 2] = r_a[k, 0] * dy - r_a[k, 1] * dx
        jb[i, 0] = -dx
        jb[i, 1] = -dy
        jb[i, 2] = -(r_b[k, 0] * dy - r_b[k, 1] * dx)
        for q in range(2):
            ma[i, q] = inv_mass[ia] * ja[i, q]
            mb[i, q] = inv_mass[ib] * jb[i, q]
        ma[i, 2] = inv_inertia[ia] * ja[i, 2]
        mb[i, 2] = inv_inertia[ib] * jb[i, 2]
    return ja, jb, ma, mb


@jit
def apply_impulses(dv, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, p_n, p_t):
    """``dv[body] += M^-1 J^T p`` for contact impulses (p_n, p_t); dv is (n_bodies, 3).

    Summed like ``IslandJacobian.velocity_change`` (``inv_mass * (J.T @ impulse)``): per body
    and component, the normal rows in contact order, then the tangent rows, then one
    multiplication by the inverse mass, so the velocities match the numpy path."""
    n = dv.shape[0]
    s = np.zeros((n, 3))
    for rows in range(2):
        d = normal if rows == 0 else tangent
        p = p_n if rows == 0 else p_t
        for k in range(a.shape[0]):
            dx, dy = d[k, 0], d[k, 1]
            ia, ib = a[k], b[k]
            s[ia, 0] += dx * p[k]
            s[ia, 1] += dy * p[k]
            s[ia, 2] += (r_a[k, 0] * dy - r_a[k, 1] * dx) * p[k]
            s[ib, 0] += -dx * p[k]
            s[ib, 1] += -dy * p[k]
            s[ib, 2] += -(r_b[k, 0] * dy - r_b[k, 1] * dx) * p[k]
    for i in range(n):
        dv[i, 0] += inv_mass[i] * s[i, 0]
        dv[i, 1] += inv_mass[i] * s[i, 1]
        dv[i, 2] += inv_inertia[i] * s[i, 2]


@inner
def _row_w(i, k, a, b, ja, jb, dv, bias):
    ia, ib = a[k], b[k]
    return (bias + ja[i, 0] * dv[ia, 0] + ja[i, 1] * dv[ia, 1] + ja[i, 2] * dv[ia, 2]
            + jb[i, 0] * dv[ib, 0] + jb[i, 1] * dv[ib, 1] + jb[i, 2] * dv[ib, 2])


@inner
def _row_add(i, k, a, b, ma, mb, dv, delta):
    ia, ib = a[k], b[k]
    dv[ia, 0] += ma[i, 0] * delta
    dv[ia, 1] += ma[i, 1] * delta
    dv[ia, 2] += ma[i, 2] * delta
    dv[ib, 0] += mb[i, 0] * delta
    dv[ib, 1] += mb[i, 1] * delta
    dv[ib, 2] += mb[i, 2] * delta


@inner
def _island_residual(lo_c, hi_c, a, b, ja, jb, dv, b_n, b_t, box, mu_lo, mu_hi, x_n, x_t,
                     diag, c, w_t_out):
    """Two measures of how far one island's impulses are from solving its LCP.

    * ``lcp.residual`` of the assembled problem (scale-free; the assembled matrix is
      symmetric positive semi-definite, so ``max|A|`` is its largest diagonal entry);
    * the natural-map residual in m/s: the largest velocity change a further projected
      Gauss-Seidel step would make, ``A_ii |x_i - proj(x_i - w_i / A_ii)|``. Unlike the
      former it does not scale with the largest ``|b|`` of the island (speculative contacts
      far apart have b ~ gap / h ~ 1 m/s), so it bounds the velocity error of every contact.

    Also writes the tangential w (new tangential velocity) of every contact to ``w_t_out``.
    Returns (lcp residual, velocity residual)."""
    amax = 0.0
    bmax = 0.0
    xmax = 0.0
    for k in range(lo_c, hi_c):
        amax = max(amax, diag[k])
        bmax = max(bmax, abs(b_n[k]))
        xmax = max(xmax, abs(x_n[k]))
        if box[k]:
            amax = max(amax, diag[k + c])
            bmax = max(bmax, abs(b_t[k]))
            xmax = max(xmax, abs(x_t[k]))
    if not (xmax - xmax == 0.0):
        return np.inf, np.inf
    s_w = max(1e-300, max(bmax, amax * xmax))
    s_x = s_w / amax if amax > 0.0 else max(1e-300, xmax)
    r = 0.0
    rv = 0.0
    for k in range(lo_c, hi_c):
        w = _row_w(k, k, a, b, ja, jb, dv, b_n[k])
        x = x_n[k]
        r = max(r, max(-x / s_x, max(-w / s_w, abs(x * w) / (s_x * s_w))))
        if diag[k] > 0.0:
            rv = max(rv, abs(x - max(x - w / diag[k], 0.0)) * diag[k])
        wt = _row_w(k + c, k, a, b, ja, jb, dv, b_t[k])
        w_t_out[k] = wt
        if box[k]:
            xj = max(x, 0.0)
            xk = x_t[k]
            dl = xk + mu_lo[k] * xj
            dh = mu_hi[k] * xj - xk
            away = wt * max(dl, 0.0) if wt > 0.0 else -wt * max(dh, 0.0)
            r = max(r, max(-dl / s_x, max(-dh / s_x, away / (s_x * s_w))))
            if diag[k + c] > 0.0:
                y = min(max(xk - wt / diag[k + c], -mu_lo[k] * xj), mu_hi[k] * xj)
                rv = max(rv, abs(xk - y) * diag[k + c])
    return max(r, 0.0), rv


@jit
def contact_velocities(a, b, normal, r_a, r_b, velocity, omega):
    """Normal and tangential relative velocity of every contact (``dynamics.relative_velocity``
    with the same operation order, so the same bits)."""
    k = a.shape[0]
    v_n = np.empty(k)
    v_t = np.empty(k)
    for i in range(k):
        ia, ib = a[i], b[i]
        pax = velocity[ia, 0] + omega[ia] * -r_a[i, 1]
        pay = velocity[ia, 1] + omega[ia] * r_a[i, 0]
        pbx = velocity[ib, 0] + omega[ib] * -r_b[i, 1]
        pby = velocity[ib, 1] + omega[ib] * r_b[i, 0]
        rx, ry = pax - pbx, pay - pby
        nx, ny = normal[i, 0], normal[i, 1]
        v_n[i] = rx * nx + ry * ny
        v_t[i] = rx * -ny + ry * nx
    return v_n, v_t


@jit
def drift(idx, position, angle, velocity, omega, half_h, out_position, out_angle):
    """``out = position + half_h * velocity`` (and the same for the angles) for the bodies
    ``idx``: a half step of Moreau's midpoint scheme, with the bits of numpy's
    ``position[idx] + 0.5 * h * velocity[idx]`` (``half_h = 0.5 * h``)."""
    for q in range(idx.shape[0]):
        i = idx[q]
        out_position[i, 0] = position[i, 0] + half_h * velocity[i, 0]
        out_position[i, 1] = position[i, 1] + half_h * velocity[i, 1]
        out_angle[i] = angle[i] + half_h * omega[i]


@jit
def speed_bounds(velocity, omega, radius, dynamic):
    """The largest ``|v| + |omega| r`` (speed bound of a body's points) of the dynamic bodies
    and of the others, the largest ``omega^2 r`` of the dynamic bodies, and a bound on the
    speed at which points of two dynamic bodies close on each other (twice the largest
    ``|v - c| + |omega| r``, c the centre of the dynamic velocities' bounding box): the
    reductions of ``TimeStepper.margin`` / ``_slip_tol`` (NaN propagates)."""
    v_dyn = 0.0
    v_other = 0.0
    spin = 0.0
    lo_x = lo_y = np.inf
    hi_x = hi_y = -np.inf
    for i in range(velocity.shape[0]):
        s = (np.sqrt(velocity[i, 0] * velocity[i, 0] + velocity[i, 1] * velocity[i, 1])
             + abs(omega[i]) * radius[i])
        if dynamic[i]:
            v_dyn = s if s > v_dyn or s != s else v_dyn
            q = omega[i] * omega[i] * radius[i]
            spin = q if q > spin or q != q else spin
            lo_x, hi_x = min(lo_x, velocity[i, 0]), max(hi_x, velocity[i, 0])
            lo_y, hi_y = min(lo_y, velocity[i, 1]), max(hi_y, velocity[i, 1])
        else:
            v_other = s if s > v_other or s != s else v_other
    cx, cy = 0.5 * (lo_x + hi_x), 0.5 * (lo_y + hi_y)
    spread = 0.0
    for i in range(velocity.shape[0]):
        if dynamic[i]:
            s = (np.sqrt((velocity[i, 0] - cx) ** 2 + (velocity[i, 1] - cy) ** 2)
                 + abs(omega[i]) * radius[i])
            spread = s if s > spread or s != s else spread
    return v_dyn, v_other, spin, 2.0 * spread


@jit
def contact_rows(a, b, point, normal, gap, order, starts, position, v_end, w_end, v_pre, w_pre,
                 mu_s_body, mu_d_body, e_body, h, touch, max_rows, push_out, push_max, slop,
                 collide_speed, slip_tol, friction_impulse, piece_a, piece_b, piece_width,
                 spec_depth, reach):
    """The per-contact part of ``TimeStepper._contacts`` in one pass (the numpy expressions it
    replaces are quoted; same operations in the same order, so the same bits).

    Contacts come as found at the midpoint configuration (``position``); ``order`` / ``starts``
    are their islands (``island_groups``). A contact is kept when its island is a pile
    (``2 * size > max_rows``), it touches (``gap <= touch``) or it would close its gap by the
    end of the step (``gap + 0.5 * h * v_N_free <= touch``): a Newton row. A contact of a small
    island kept for none of these is speculative when ``gap + allow <= reach`` (``allow`` =
    ``spec_depth`` x the smaller width of its two pieces, ``reach`` the distance a point can
    travel in the step): its row ``v'_N + (gap + allow) / h >= 0`` lets it close by at most
    ``gap + allow`` before the next midpoint. Returns the kept indices, then per
    kept contact: ``dynamics.contact_set``'s tangent, r_a, r_b, mu_static, mu_dynamic,
    restitution; the free end-of-step velocities v_N, v_T (``v_end`` / ``w_end``); the
    pre-step slip v_T (``v_pre`` / ``w_pre``); pile, colliding, the normal rows' b, then
    ``dynamics.friction_rows``' BOX flag, mu_lo, mu_hi; and the smallest kept gap."""
    n = a.shape[0]
    size = np.empty(n, np.int64)
    for i in range(starts.shape[0] - 1):
        for q in range(starts[i], starts[i + 1]):
            size[order[q]] = starts[i + 1] - starts[i]
    r_a = np.empty((n, 2))
    r_b = np.empty((n, 2))
    vn_free = np.empty(n)
    vt_free = np.empty(n)
    keep = np.empty(n, np.int64)
    allow = np.zeros(n)
    spec = np.zeros(n, np.bool_)
    m = 0
    for i in range(n):
        ia, ib = a[i], b[i]
        for q in range(2):
            r_a[i, q] = point[i, q] - position[ia, q]
            r_b[i, q] = point[i, q] - position[ib, q]
        # contact_velocities at the end-of-step free velocities
        pax = v_end[ia, 0] + w_end[ia] * -r_a[i, 1]
        pay = v_end[ia, 1] + w_end[ia] * r_a[i, 0]
        pbx = v_end[ib, 0] + w_end[ib] * -r_b[i, 1]
        pby = v_end[ib, 1] + w_end[ib] * r_b[i, 0]
        rx, ry = pax - pbx, pay - pby
        nx, ny = normal[i, 0], normal[i, 1]
        vn_free[i] = rx * nx + ry * ny
        vt_free[i] = rx * -ny + ry * nx
        if (2 * size[i] > max_rows or gap[i] <= touch
                or gap[i] + 0.5 * h * vn_free[i] <= touch):
            keep[m] = i
            m += 1
        else:
            wa, wb = piece_width[piece_a[i]], piece_width[piece_b[i]]
            d = spec_depth * (wa if wa < wb else wb)
            if gap[i] + d <= reach:
                allow[i] = d
                spec[i] = True
                keep[m] = i
                m += 1
    keep = keep[:m]
    tangent = np.empty((m, 2))
    ra = np.empty((m, 2))
    rb = np.empty((m, 2))
    mu_s = np.empty(m)
    mu_d = np.empty(m)
    rest = np.empty(m)
    v_n = np.empty(m)
    v_t = np.empty(m)
    slip = np.empty(m)
    pile = np.empty(m, np.bool_)
    colliding = np.empty(m, np.bool_)
    b_n = np.empty(m)
    box = np.empty(m, np.bool_)
    mu_lo = np.empty(m)
    mu_hi = np.empty(m)
    gap_min = np.inf
    for q in range(m):
        i = keep[q]
        ia, ib = a[i], b[i]
        nx, ny = normal[i, 0], normal[i, 1]
        tangent[q, 0] = -ny
        tangent[q, 1] = nx
        for j in range(2):
            ra[q, j] = r_a[i, j]
            rb[q, j] = r_b[i, j]
        # world.mix: friction the geometric mean, restitution the larger value
        x, y = mu_s_body[ia], mu_s_body[ib]
        mu_s[q] = x if x == y else np.sqrt(x * y)
        x, y = mu_d_body[ia], mu_d_body[ib]
        mu_d[q] = x if x == y else np.sqrt(x * y)
        x, y = e_body[ia], e_body[ib]
        rest[q] = x if x == y else max(x, y)
        v_n[q] = vn_free[i]
        v_t[q] = vt_free[i]
        # contact_velocities at the pre-step velocities
        pax = v_pre[ia, 0] + w_pre[ia] * -r_a[i, 1]
        pay = v_pre[ia, 1] + w_pre[ia] * r_a[i, 0]
        pbx = v_pre[ib, 0] + w_pre[ib] * -r_b[i, 1]
        pby = v_pre[ib, 1] + w_pre[ib] * r_b[i, 0]
        rx, ry = pax - pbx, pay - pby
        vn_pre = rx * nx + ry * ny
        vt_pre = rx * -ny + ry * nx
        slip[q] = vt_pre
        g = gap[i]
        gap_min = min(gap_min, g)
        pl = 2 * size[i] > max_rows
        pile[q] = pl
        touching = g <= touch
        # colliding = (touching | ~pile) & (v_n_pre < -2 g h)
        colliding[q] = (touching or not pl) and vn_pre < collide_speed
        # newton = v_n_free + e min(v_n_pre, 0);
        # push = min(push_out max(-gap - slop, 0) 2 / h, push_max).
        # np.minimum / np.maximum return the second operand on a tie (the sign of a zero) and
        # propagate NaN; numba's min / max return the first, hence the explicit forms.
        newton = vn_free[i] + rest[q] * (vn_pre if vn_pre < 0.0 or vn_pre != vn_pre else 0.0)
        if not pl:
            b_n[q] = vn_free[i] + (g + allow[i]) / h if spec[i] else newton
        elif touching:
            depth = -g - slop
            depth = depth if depth > 0.0 or depth != depth else 0.0
            push = push_out * depth * 2.0 / h
            b_n[q] = newton - (push if push < push_max or push != push else push_max)
        else:
            b_n[q] = vn_free[i] + 2.0 * g / h
        # friction_rows (Kawachi): the pre-step slip picks static or one-sided dynamic
        sliding = abs(vt_pre) > slip_tol
        mu = mu_d[q] if sliding else mu_s[q]
        box[q] = mu > 0.0 and (friction_impulse or not colliding[q])
        mu_lo[q] = 0.0 if sliding and vt_pre < 0 else mu
        mu_hi[q] = 0.0 if sliding and vt_pre > 0 else mu
    return (keep, tangent, ra, rb, mu_s, mu_d, rest, v_n, v_t, slip, pile, colliding, b_n, box,
            mu_lo, mu_hi, gap_min)


@jit
def feature_gaps(idx, vertex, edge, vertices, normals, vertex_body, position, cos, sin):
    """Gaps of the vertex-edge features of contacts ``idx`` at another configuration:
    ``collision.evaluate_gaps`` (its gap) with the same arithmetic, so the same bits; ``cos`` /
    ``sin`` of the body angles are numpy's. Used by the position projection, which needs the
    gaps of a few contacts, where evaluate_gaps' numpy calls cost ~70 us whatever their number."""
    out = np.empty(idx.shape[0])
    for q in range(idx.shape[0]):
        i = idx[q]
        v, e = vertex[i], edge[i]
        ba, bb = vertex_body[v], vertex_body[e]
        c, s = cos[ba], sin[ba]
        x, y = vertices[v, 0], vertices[v, 1]
        px = position[ba, 0] + (c * x - s * y)
        py = position[ba, 1] + (s * x + c * y)
        c, s = cos[bb], sin[bb]
        x, y = vertices[e, 0], vertices[e, 1]
        qx = position[bb, 0] + (c * x - s * y)
        qy = position[bb, 1] + (s * x + c * y)
        x, y = normals[e, 0], normals[e, 1]
        out[q] = (c * x - s * y) * (px - qx) + (s * x + c * y) * (py - qy)
    return out


# ---------------------------------------------------------------------------------------------
# island solvers: Dantzig for small islands, projected Gauss-Seidel for large ones


@inner
def _affine(A, x, b):
    """``A @ x + b`` (a loop: cheaper to compile than the BLAS binding, as fast at this size)."""
    m, n = A.shape
    out = np.empty(m)
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += A[i, j] * x[j]
        out[i] = s + b[i]
    return out


@inner
def _dense_residual(A, b, x, w, nof, lo, hi):
    """``lcp.residual`` of ``w = A x + b`` (w given)."""
    m = b.shape[0]
    amax = 0.0
    bmax = 0.0
    xmax = 0.0
    for i in range(m):
        bmax = max(bmax, abs(b[i]))
        xmax = max(xmax, abs(x[i]))
        for j in range(m):
            amax = max(amax, abs(A[i, j]))
    if not np.isfinite(xmax):
        return np.inf
    s_w = max(1e-300, max(bmax, amax * xmax))
    s_x = s_w / amax if amax > 0.0 else max(1e-300, xmax)
    r = 0.0
    for k in range(m):
        xk, wk = x[k], w[k]
        j = nof[k]
        if j < 0:
            r = max(r, max(-xk / s_x, max(-wk / s_w, abs(xk * wk) / (s_x * s_w))))
        else:
            xj = max(x[j], 0.0)
            dl = xk + lo[k] * xj
            dh = hi[k] * xj - xk
            away = wk * max(dl, 0.0) if wk > 0.0 else -wk * max(dh, 0.0)
            r = max(r, max(-dl / s_x, max(-dh / s_x, away / (s_x * s_w))))
    return max(r, 0.0)


# Columns of a contact's record in the projected Gauss-Seidel (``_pgs_records``): the Jacobian
# blocks of its normal row (ja, jb: 0-5) and their M^-1 multiples (ma, mb: 6-11), the same for
# its friction row (12-23), then b_N, b_T, the SOR steps, the diagonal entries A_ii and the
# friction bounds.
_R_BN, _R_BT, _R_SN, _R_ST, _R_DN, _R_DT, _R_LO, _R_HI = range(24, 32)
_R_WIDTH = 32


@inner
def _pgs_records(a, b, ja, jb, ma, mb, step, diag, b_n, b_t, mu_lo, mu_hi, inv_mass,
                 inv_inertia):
    """Everything a sweep reads about contact k in row k of one (c, 32) array, so that a sweep
    streams through memory once instead of gathering from a dozen arrays, and per contact
    whether its vertex / edge body is fixed (zero inverse mass and inertia)."""
    c = a.shape[0]
    R = np.empty((c, _R_WIDTH))
    fixed_a = np.empty(c, np.bool_)
    fixed_b = np.empty(c, np.bool_)
    for k in range(c):
        t = k + c
        for q in range(3):
            R[k, q] = ja[k, q]
            R[k, 3 + q] = jb[k, q]
            R[k, 6 + q] = ma[k, q]
            R[k, 9 + q] = mb[k, q]
            R[k, 12 + q] = ja[t, q]
            R[k, 15 + q] = jb[t, q]
            R[k, 18 + q] = ma[t, q]
            R[k, 21 + q] = mb[t, q]
        R[k, _R_BN] = b_n[k]
        R[k, _R_BT] = b_t[k]
        R[k, _R_SN] = step[k]
        R[k, _R_ST] = step[t]
        R[k, _R_DN] = diag[k]
        R[k, _R_DT] = diag[t]
        R[k, _R_LO] = mu_lo[k]
        R[k, _R_HI] = mu_hi[k]
        fixed_a[k] = inv_mass[a[k]] == 0.0 and inv_inertia[a[k]] == 0.0
        fixed_b[k] = inv_mass[b[k]] == 0.0 and inv_inertia[b[k]] == 0.0
    return R, fixed_a, fixed_b


@inner(inline='always')
def _push(dv, R, k, ia, ib, col, d):
    """Add the velocity change of an impulse change ``d`` on row ``k`` to both its bodies
    (``R[k, col:col + 6]`` hold M^-1 J^T for body a, then body b)."""
    dv[ia, 0] += R[k, col] * d
    dv[ia, 1] += R[k, col + 1] * d
    dv[ia, 2] += R[k, col + 2] * d
    dv[ib, 0] += R[k, col + 3] * d
    dv[ib, 1] += R[k, col + 4] * d
    dv[ib, 2] += R[k, col + 5] * d


@inner
def _pgs_island(lo_c, hi_c, a, b, R, fixed_a, fixed_b, dv, box, x_n, x_t, sweeps):
    """``sweeps`` projected Gauss-Seidel sweeps over contacts lo_c..hi_c-1 in order, each
    normal followed by its friction row, whose bounds use the normal just updated (velocity
    form: ``dv`` holds M^-1 J^T x of the island's bodies; contact data in ``R``, see
    ``_pgs_records``; steps are the SOR factor / A_ii, 0 for a row without a positive pivot).
    Always forward: alternating directions can cycle between two fixed points when contacts
    are redundant (two corners of a box edge give identical friction rows). The row updates
    are written out (no helper calls) because this is the innermost loop. Returns the largest
    velocity change ``A_ii |dx_i|`` of the last sweep (m/s).

    A row's w is ``b + ja . dv_a + jb . dv_b`` summed left to right. The sweep is bound by the
    latency of that chain of additions, so the three terms of a fixed body (the track, a
    wall) are left out: its dv stays exactly +0.0 (it only ever receives 0 * d), its terms are
    +-0.0, and adding them can only turn a w of -0.0 into +0.0, which changes no impulse (the
    update is skipped when d is zero) nor any other bit of the answer."""
    change = 0.0
    for _ in range(sweeps):
        change = 0.0
        for k in range(lo_c, hi_c):
            ia, ib = a[k], b[k]
            w = R[k, _R_BN]
            if not fixed_a[k]:
                w = w + R[k, 0] * dv[ia, 0] + R[k, 1] * dv[ia, 1] + R[k, 2] * dv[ia, 2]
            if not fixed_b[k]:
                w = w + R[k, 3] * dv[ib, 0] + R[k, 4] * dv[ib, 1] + R[k, 5] * dv[ib, 2]
            xo = x_n[k]
            xn = xo - R[k, _R_SN] * w
            if xn < 0.0:
                xn = 0.0
            d = xn - xo
            if d != 0.0:
                change = max(change, abs(d) * R[k, _R_DN])
                _push(dv, R, k, ia, ib, 6, d)
                x_n[k] = xn
            # (xn now equals x_n[k] bit for bit: x_n never holds -0.0)
            if xn == 0.0:
                # an open contact carries no friction: no need to evaluate its row
                d = -x_t[k]
                if d != 0.0:
                    change = max(change, abs(d) * R[k, _R_DT])
                    _push(dv, R, k, ia, ib, 18, d)
                    x_t[k] = 0.0
            elif box[k]:
                w = R[k, _R_BT]
                if not fixed_a[k]:
                    w = w + R[k, 12] * dv[ia, 0] + R[k, 13] * dv[ia, 1] + R[k, 14] * dv[ia, 2]
                if not fixed_b[k]:
                    w = w + R[k, 15] * dv[ib, 0] + R[k, 16] * dv[ib, 1] + R[k, 17] * dv[ib, 2]
                xo = x_t[k]
                xt = xo - R[k, _R_ST] * w
                xt = min(max(xt, -R[k, _R_LO] * xn), R[k, _R_HI] * xn)
                d = xt - xo
                if d != 0.0:
                    change = max(change, abs(d) * R[k, _R_DT])
                    _push(dv, R, k, ia, ib, 18, d)
                    x_t[k] = xt
    return change


@inner
def _island_dense(lo_c, hi_c, c, a, b, ja, jb, ma, mb, b_n, b_t, box, mu_lo, mu_hi):
    """The assembled problem of contacts lo_c..hi_c-1 (``dynamics.assemble``'s layout: the
    normals, then the friction rows of contacts with ``box``): A, b, normal_of, mu_lo, mu_hi,
    and for each row its contact and whether it is a friction row."""
    nc = hi_c - lo_c
    m = nc
    for k in range(lo_c, hi_c):
        if box[k]:
            m += 1
    rc = np.empty(m, np.int64)
    rf = np.zeros(m, np.bool_)
    p = nc
    for q in range(nc):
        rc[q] = lo_c + q
        if box[lo_c + q]:
            rc[p] = lo_c + q
            rf[p] = True
            p += 1
    A = np.empty((m, m))
    bb = np.empty(m)
    nof = -np.ones(m, np.int64)
    lo = np.zeros(m)
    hi = np.zeros(m)
    for i in range(m):
        k = rc[i]
        gi = k + c if rf[i] else k
        if rf[i]:
            bb[i] = b_t[k]
            nof[i] = k - lo_c
            lo[i] = mu_lo[k]
            hi[i] = mu_hi[k]
        else:
            bb[i] = b_n[k]
        for j in range(i, m):
            kj = rc[j]
            gj = kj + c if rf[j] else kj
            s = 0.0
            if a[k] == a[kj]:
                s += ma[gi, 0] * ja[gj, 0] + ma[gi, 1] * ja[gj, 1] + ma[gi, 2] * ja[gj, 2]
            if a[k] == b[kj]:
                s += ma[gi, 0] * jb[gj, 0] + ma[gi, 1] * jb[gj, 1] + ma[gi, 2] * jb[gj, 2]
            if b[k] == a[kj]:
                s += mb[gi, 0] * ja[gj, 0] + mb[gi, 1] * ja[gj, 1] + mb[gi, 2] * ja[gj, 2]
            if b[k] == b[kj]:
                s += mb[gi, 0] * jb[gj, 0] + mb[gi, 1] * jb[gj, 1] + mb[gi, 2] * jb[gj, 2]
            A[i, j] = s
            A[j, i] = s
    return A, bb, nof, lo, hi, rc, rf


@jit
def solve_small(select, starts, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n,
                b_t, box, mu_lo, mu_hi, x_n, x_t, w_t):
    """The islands with ``select`` (contacts grouped by ``starts``, CSR) by Baraff-Dantzig
    (``dantzig``), from scratch.

    An island's problem has its normal rows, then the friction rows of the contacts with
    ``box[k]`` (bounds ``[-mu_lo x_N, mu_hi x_N]``; other contacts keep x_T = 0), exactly
    ``dynamics.assemble``'s layout. Writes the impulses to ``x_n`` / ``x_t`` and the new
    tangential velocity of contacts with a friction row to ``w_t``; returns per island the
    residual (``lcp.residual``), the pivots and the Dantzig abort codes (pass, retry)."""
    n_isl = starts.shape[0] - 1
    c = a.shape[0]
    ja, jb, ma, mb = _rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia)
    res = np.zeros(n_isl)
    work = np.zeros(n_isl, np.int64)
    codes = np.zeros((n_isl, 2), np.int64)
    for isl in range(n_isl):
        if not select[isl]:
            continue
        A, bb, nof, lo, hi, rc, rf = _island_dense(starts[isl], starts[isl + 1], c, a, b, ja,
                                                   jb, ma, mb, b_n, b_t, box, mu_lo, mu_hi)
        m = bb.shape[0]
        x, piv, c1, c2 = dantzig(A, bb, nof, lo, hi, 50 * m + 50)
        wv = _affine(A, x, bb)
        res[isl] = _dense_residual(A, bb, x, wv, nof, lo, hi)
        work[isl] = piv
        codes[isl, 0], codes[isl, 1] = c1, c2
        for k in range(starts[isl], starts[isl + 1]):
            x_t[k] = 0.0
        for i in range(m):
            k = rc[i]
            if rf[i]:
                x_t[k] = x[i]
                w_t[k] = wv[i]
            else:
                x_n[k] = x[i]
    return res, work, codes


@jit
def solve_pgs(select, starts, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n, b_t,
              box, mu_lo, mu_hi, x_n, x_t, w_t, dv, tol, max_sweeps, check, omega):
    """The islands with ``select`` by projected Gauss-Seidel in velocity form
    (``_pgs_island``).

    ``x_n`` / ``x_t`` hold the warm start (the previous step's impulses of the same
    features, 0 for new ones) on entry and the answer on return; ``dv`` (n_bodies, 3) is
    scratch and must be zero. Each island is swept until its velocity residual (m/s, see
    ``_island_residual``, checked every ``check`` sweeps) is <= ``tol`` or ``max_sweeps``
    is reached. Writes the new tangential velocities to ``w_t``; returns per island the
    ``lcp.residual``, the velocity residual and the sweeps."""
    c = a.shape[0]
    n_isl = starts.shape[0] - 1
    ja, jb, ma, mb = _rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia)
    diag = np.empty(2 * c)
    for i in range(2 * c):
        diag[i] = (ja[i, 0] * ma[i, 0] + ja[i, 1] * ma[i, 1] + ja[i, 2] * ma[i, 2]
                   + jb[i, 0] * mb[i, 0] + jb[i, 1] * mb[i, 1] + jb[i, 2] * mb[i, 2])
    step = np.zeros(2 * c)
    for i in range(2 * c):
        if diag[i] > 0.0:
            step[i] = omega / diag[i]
    R, fixed_a, fixed_b = _pgs_records(a, b, ja, jb, ma, mb, step, diag, b_n, b_t, mu_lo, mu_hi,
                                       inv_mass, inv_inertia)
    res = np.zeros(n_isl)
    vres = np.zeros(n_isl)
    work = np.zeros(n_isl, np.int64)
    for isl in range(n_isl):
        if not select[isl]:
            continue
        lo_c, hi_c = starts[isl], starts[isl + 1]
        for k in range(lo_c, hi_c):
            # project the warm start and accumulate its velocity change
            if not (x_n[k] > 0.0):
                x_n[k] = 0.0
            if box[k]:
                x_t[k] = min(max(x_t[k], -mu_lo[k] * x_n[k]), mu_hi[k] * x_n[k])
            else:
                x_t[k] = 0.0
            _row_add(k, k, a, b, ma, mb, dv, x_n[k])
            _row_add(k + c, k, a, b, ma, mb, dv, x_t[k])
        # sweep until a sweep changes no velocity by more than tol, then confirm with the
        # residual at the final point (the stopping test, recorded with lcp.residual)
        r, rv = _island_residual(lo_c, hi_c, a, b, ja, jb, dv, b_n, b_t, box, mu_lo, mu_hi,
                                 x_n, x_t, diag, c, w_t)
        s = 0
        while rv > tol and s < max_sweeps:
            n = min(check, max_sweeps - s)
            change = _pgs_island(lo_c, hi_c, a, b, R, fixed_a, fixed_b, dv, box, x_n, x_t, n)
            s += n
            if change <= tol or s >= max_sweeps:
                r, rv = _island_residual(lo_c, hi_c, a, b, ja, jb, dv, b_n, b_t, box, mu_lo,
                                         mu_hi, x_n, x_t, diag, c, w_t)
        res[isl] = r
        vres[isl] = rv
        work[isl] = s
    return res, vres, work


# ---------------------------------------------------------------------------------------------
# collision detection: broad and narrow phase of ``collision.find_contacts``


@inner
def _vertex_edge(pv_lo, pv_hi, qe_lo, qe_hi, w, nw, active, internal, nxt, prv, elen, margin,
                 depth, tie, param_tol, angle_tol, out_v, out_e, out_g, out_t, n_out):
    """Vertices pv_lo..pv_hi-1 of one piece against edges qe_lo..qe_hi-1 of another: the
    per-vertex body of ``collision._vertices_vs_edges`` (same arithmetic, same bits)."""
    for v in range(pv_lo, pv_hi):
        if not active[v]:
            continue
        px, py = w[v, 0], w[v, 1]
        dmax = -np.inf
        for e in range(qe_lo, qe_hi):
            if not internal[e]:
                d = nw[e, 0] * (px - w[e, 0]) + nw[e, 1] * (py - w[e, 1])
                if d > dmax:
                    dmax = d
        if not (dmax - tie <= margin and dmax >= -depth):
            continue
        ip, ix = prv[v], nxt[v]
        ux, uy = w[ip, 0] - px, w[ip, 1] - py
        xx, xy = w[ix, 0] - px, w[ix, 1] - py
        slack_u = max(margin, angle_tol * elen[ip])
        slack_x = max(margin, angle_tol * elen[v])
        best = -np.inf
        best_e = -1
        best_t = 0.0
        for e in range(qe_lo, qe_hi):
            if internal[e]:
                continue
            nx, ny = nw[e, 0], nw[e, 1]
            dx, dy = px - w[e, 0], py - w[e, 1]
            d = nx * dx + ny * dy
            q1 = nxt[e]
            ex, ey = w[q1, 0] - w[e, 0], w[q1, 1] - w[e, 1]
            t = (dx * ex + dy * ey) / (ex * ex + ey * ey)
            if not (t >= -param_tol and t <= 1.0 + param_tol):
                continue
            if not (ux * nx + uy * ny >= -slack_u and xx * nx + xy * ny >= -slack_x):
                continue
            if d > best:
                best, best_e, best_t = d, e, t
        if best_e >= 0 and best <= margin and best >= -depth:
            out_v[n_out] = v
            out_e[n_out] = best_e
            out_g[n_out] = best
            out_t[n_out] = best_t
            n_out += 1
    return n_out


@jit
def narrow_phase(w, nw, lo, hi, piece_start, piece_body, take, dyn, bp_margin, margin,
                 depth, piece_width, depth_fraction, coord, radius, tie_rel, active, internal,
                 nxt, prv, elen, param_tol, angle_tol):
    """Vertex-edge contacts of all piece pairs whose AABBs are within ``bp_margin``.

    The pair set is that of ``collision.candidate_pairs`` (closed AABB overlap on both axes,
    pieces of different bodies, both taking part, at least one dynamic), found by a sweep
    along x; the per-pair test is ``collision._vertices_vs_edges`` in both directions.
    ``depth < 0`` means the default per pair (``depth_fraction`` x the smaller piece width).
    Returns unordered (vertex, edge, gap, edge_param) and the number of candidate pairs."""
    n_p = piece_body.shape[0]
    ids = np.empty(n_p, np.int64)
    n_t = 0
    for p in range(n_p):
        if take[p]:
            ids[n_t] = p
            n_t += 1
    ids = ids[:n_t]
    key = np.empty(n_t)
    for q in range(n_t):
        key[q] = lo[ids[q], 0]
    order = ids[_argsort(key)]
    cap = 64
    out_v = np.empty(cap, np.int64)
    out_e = np.empty(cap, np.int64)
    out_g = np.empty(cap)
    out_t = np.empty(cap)
    n_out = 0
    n_pairs = 0
    for ii in range(n_t):
        p = order[ii]
        reach = hi[p, 0] + bp_margin
        for jj in range(ii + 1, n_t):
            q = order[jj]
            if lo[q, 0] > reach:
                break
            if piece_body[p] == piece_body[q] or not (dyn[p] or dyn[q]):
                continue
            if not (lo[p, 1] <= hi[q, 1] + bp_margin and lo[q, 1] <= hi[p, 1] + bp_margin):
                continue
            if not (lo[q, 0] <= hi[p, 0] + bp_margin and lo[p, 0] <= hi[q, 0] + bp_margin):
                continue
            n_pairs += 1
            a, b = min(p, q), max(p, q)
            a0, a1 = piece_start[a], piece_start[a + 1]
            b0, b1 = piece_start[b], piece_start[b + 1]
            need = n_out + (a1 - a0) + (b1 - b0)
            if need > cap:
                while need > cap:
                    cap *= 2
                nv = np.empty(cap, np.int64)
                ne = np.empty(cap, np.int64)
                ng = np.empty(cap)
                nt = np.empty(cap)
                for q in range(n_out):
                    nv[q], ne[q], ng[q], nt[q] = out_v[q], out_e[q], out_g[q], out_t[q]
                out_v, out_e, out_g, out_t = nv, ne, ng, nt
            if depth < 0.0:
                dp = depth_fraction * min(piece_width[a], piece_width[b])
            else:
                dp = depth
            tie = tie_rel * (coord[piece_body[a]] + coord[piece_body[b]] + radius[a]
                             + radius[b])
            n_out = _vertex_edge(a0, a1, b0, b1, w, nw, active, internal, nxt, prv, elen,
                                 margin, dp, tie, param_tol, angle_tol, out_v, out_e, out_g,
                                 out_t, n_out)
            n_out = _vertex_edge(b0, b1, a0, a1, w, nw, active, internal, nxt, prv, elen,
                                 margin, dp, tie, param_tol, angle_tol, out_v, out_e, out_g,
                                 out_t, n_out)
    return out_v[:n_out], out_e[:n_out], out_g[:n_out], out_t[:n_out], n_pairs


# ---------------------------------------------------------------------------------------------
# Baraff-Dantzig pivoting: a port of ``lcp._Dantzig`` to numba with the same sets, events,
# tie-breaking, tolerances, cycling and fold handling, normals-first retry and polish. One
# difference: a (nearly) singular clamped system gets a basic solution by complete pivoting
# (dependent unknowns 0) where ``lcp`` takes the minimum-norm least-squares one; both are
# exact for a consistent system. The code is flat on purpose (three functions): numba
# re-generates every callee inside each caller, so deep call trees multiply compile time.

_U, _C, _NC, _L, _H, _DEAD, _Z = 0, 1, 2, 3, 4, 5, 6
(_DONE_C, _DONE_L, _DONE_H, _BAD, _C_NC, _NC_C, _C_L, _C_H, _SL_C,
 _Z_C) = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
_EPS_W = 1e-12
_EPS_ROW = 1e-13      # ``lcp._Dantzig.EPS_ROW``: a normal row's own round-off scale
_EPS_RATE = 1e-11
# abort codes (0 = success); ``time_stepping._ABORTS`` spells them out
_OK, _PIVOT_CAP, _NO_STEP, _NONFINITE, _BAD_END, _CYCLING, _BUDGET, _NUMERIC = range(8)


@inner
def _dz_solve(M, r, amax, cnt):
    """``lcp._Dantzig._solve``: closed forms for n <= 2, else LU with partial pivoting; a
    (nearly) singular system (counted in cnt[1]) gets the basic solution of complete
    pivoting with two steps of iterative refinement. M and r are not modified."""
    n = r.shape[0]
    y = np.zeros(n)
    if n == 0:
        return y
    if n == 1:
        if abs(M[0, 0]) > 1e-13 * amax:
            y[0] = r[0] / M[0, 0]
            return y
    elif n == 2:
        a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
        det = a * d - b * c
        if abs(det) > 1e-12 * (abs(a * d) + abs(b * c)):
            y[0] = (d * r[0] - b * r[1]) / det
            y[1] = (a * r[1] - c * r[0]) / det
            return y
    else:
        LU = M.copy()
        z = r.copy()
        ok = True
        for k in range(n):
            p = k
            best = abs(LU[k, k])
            for i in range(k + 1, n):
                if abs(LU[i, k]) > best:
                    best, p = abs(LU[i, k]), i
            if best == 0.0:
                ok = False
                break
            if p != k:
                for j in range(n):
                    LU[k, j], LU[p, j] = LU[p, j], LU[k, j]
                z[k], z[p] = z[p], z[k]
            for i in range(k + 1, n):
                f = LU[i, k] / LU[k, k]
                if f != 0.0:
                    for j in range(k + 1, n):
                        LU[i, j] -= f * LU[k, j]
                    z[i] -= f * z[k]
        if ok:
            umin, umax = np.inf, 0.0
            for k in range(n):
                umin = min(umin, abs(LU[k, k]))
                umax = max(umax, abs(LU[k, k]))
            if umin > 1e-12 * umax:
                finite = True
                for k in range(n - 1, -1, -1):
                    s = z[k]
                    for j in range(k + 1, n):
                        s -= LU[k, j] * y[j]
                    y[k] = s / LU[k, k]
                    finite = finite and (y[k] - y[k] == 0.0)
                if finite:
                    return y
    # Redundant clamped rows (a tiny pivot): keep the consistent part exact instead of
    # sending the null-space component to 1e16.
    cnt[1] += 1
    for k in range(n):
        y[k] = 0.0
    LU = M.copy()
    rowp = np.arange(n)
    colp = np.arange(n)
    rank = n
    pmax = 0.0
    for k in range(n):
        best, bi, bj = 0.0, k, k
        for i in range(k, n):
            for j in range(k, n):
                if abs(LU[i, j]) > best:
                    best, bi, bj = abs(LU[i, j]), i, j
        if k == 0:
            pmax = best
        if not (best > 1e-12 * pmax):
            rank = k
            break
        for j in range(n):
            LU[k, j], LU[bi, j] = LU[bi, j], LU[k, j]
        rowp[k], rowp[bi] = rowp[bi], rowp[k]
        for i in range(n):
            LU[i, k], LU[i, bj] = LU[i, bj], LU[i, k]
        colp[k], colp[bj] = colp[bj], colp[k]
        for i in range(k + 1, n):
            f = LU[i, k] / LU[k, k]
            LU[i, k] = f
            for j in range(k + 1, n):
                LU[i, j] -= f * LU[k, j]
    res = r.copy()
    z = np.empty(n)
    u = np.empty(n)
    for _ in range(3):            # solve, then two refinement steps on the residual
        for i in range(n):
            s = res[rowp[i]]
            for k in range(min(i, rank)):
                s -= LU[i, k] * z[k]
            z[i] = s
        for k in range(n):
            u[k] = 0.0
        for k in range(rank - 1, -1, -1):
            s = z[k]
            for j in range(k + 1, rank):
                s -= LU[k, j] * u[j]
            u[k] = s / LU[k, k]
        for k in range(n):
            y[colp[k]] += u[k]
        for i in range(n):
            s = r[i]
            for j in range(n):
                s -= M[i, j] * y[j]
            res[i] = s
    return y


@inner
def _dz_direction(A, b, st, nof, lo, hi, d, sigma, amax, cnt):
    """``lcp._Dantzig._direction`` (d >= 0): the unit move (dx, dw) of x_d by sigma keeping
    clamped rows' w fixed, slaved friction columns substituted into their normals' (the
    free unknowns are the clamped rows and d). With d < 0 the ``_polish`` solve instead:
    the clamped rows alone with w = 0, returned as (x, w)."""
    m = A.shape[0]
    nc = 0
    for i in range(m):
        if st[i] == _C:
            nc += 1
    nv = nc + 1 if d >= 0 else nc
    V = np.empty(nv, np.int64)
    pos = -np.ones(m, np.int64)
    q = 0
    for i in range(m):
        if st[i] == _C:
            V[q] = i
            pos[i] = q
            q += 1
    if d >= 0:
        V[nc] = d
        pos[d] = nc
    cols = np.empty((m, nv))
    for p in range(nv):
        for i in range(m):
            cols[i, p] = A[i, V[p]]
    coef = np.zeros(m)          # slaved rows: x_k = coef[k] x_nof[k]
    slaved = np.zeros(m, np.bool_)
    for k in range(m):
        s = st[k]
        if s == _L or s == _H:
            p = pos[nof[k]]
            if p >= 0:
                c = -lo[k] if s == _L else hi[k]
                if c != 0.0:
                    for i in range(m):
                        cols[i, p] += c * A[i, k]
                coef[k] = c
                slaved[k] = True
    xv = np.empty(nv)
    if d >= 0:
        xv[nc] = sigma
    if nc:
        M = np.empty((nc, nc))
        r = np.empty(nc)
        for p in range(nc):
            for s in range(nc):
                M[p, s] = cols[V[p], s]
            r[p] = -sigma * cols[V[p], nc] if d >= 0 else -b[V[p]]
        y = _dz_solve(M, r, amax, cnt)
        for p in range(nc):
            xv[p] = y[p]
    dx = np.zeros(m)
    dw = np.zeros(m)
    for i in range(m):
        s = 0.0 if d >= 0 else b[i]
        for p in range(nv):
            s += cols[i, p] * xv[p]
        dw[i] = s
    for p in range(nv):
        dx[V[p]] = xv[p]
    for k in range(m):
        if slaved[k]:
            dx[k] = coef[k] * dx[nof[k]]
    return dx, dw


@inner
def dantzig(A, b, nof, lo, hi, max_pivots):
    """``lcp._dantzig``: a Baraff-Dantzig pass from x = 0 and, with friction, when it
    aborts, one retry treating every normal before any friction row. Returns (x, pivots,
    abort code of the pass, abort code of the retry); codes are 0 on success."""
    m = b.shape[0]
    amax = 0.0
    bmax = 0.0
    nfr = 0
    for i in range(m):
        bmax = max(bmax, abs(b[i]))
        nfr += nof[i] >= 0
        for j in range(m):
            amax = max(amax, abs(A[i, j]))
    if amax == 0.0:
        amax = 1.0
    st = np.empty(m, np.int64)
    x = np.zeros(m)
    w = np.empty(m)
    nodefer = np.zeros(m, np.bool_)
    cnt = np.zeros(2, np.int64)           # pivots, singular solves
    best_x = np.zeros(m)
    best_r = np.inf
    codes = np.zeros(2, np.int64)
    ct = np.empty(2 * m + 4)              # ratio-test candidates: step, priority, row, event
    cp = np.empty(2 * m + 4, np.int64)
    ci = np.empty(2 * m + 4, np.int64)
    cc = np.empty(2 * m + 4, np.int64)
    seen = np.empty(4 * m + 16, np.int64)
    total = 0
    for attempt in range(2):
        normals_first = attempt == 1
        cap = max_pivots - total
        for k in range(m):
            st[k] = _DEAD if nof[k] >= 0 and lo[k] == 0.0 and hi[k] == 0.0 else _U
            x[k] = 0.0
            w[k] = b[k]
            nodefer[k] = False
        cnt[0] = 0
        cnt[1] = 0
        code = _OK
        budget = 20 * (cap + m) + 100
        while True:
            budget -= 1
            if budget < 0:
                code = _BUDGET
                break
            xmax = 0.0
            for v in x:
                xmax = max(xmax, abs(v))
            eps = _EPS_W * max(max(bmax, amax * xmax), 1e-300)
            nr0 = -1
            jmin = -1
            for i in range(m):
                if st[i] == _U and nof[i] < 0:
                    if nr0 < 0:
                        nr0 = i
                    if jmin < 0 or w[i] < w[jmin]:
                        jmin = i
            fr0 = -1
            for k in range(m):
                if st[k] == _U and nof[k] >= 0 and st[nof[k]] == _C:
                    fr0 = k
                    break
            d = -1
            sigma = 1.0
            if fr0 >= 0 and not (normals_first and nr0 >= 0):
                k = fr0
                if abs(w[k]) <= eps:
                    dependent = False
                    if not nodefer[k]:
                        dx, dw = _dz_direction(A, b, st, nof, lo, hi, k, 1.0, amax, cnt)
                        dxmax = 1.0
                        for v in dx:
                            dxmax = max(dxmax, abs(v))
                        dependent = abs(dw[k]) <= _EPS_RATE * amax * dxmax
                    st[k] = _Z if dependent else _C
                elif w[k] > 0.0:
                    if lo[k] == 0.0:
                        st[k] = _L
                    else:
                        d, sigma = k, -1.0
                elif hi[k] == 0.0:
                    st[k] = _H
                else:
                    d, sigma = k, 1.0
            elif nr0 >= 0:
                if w[jmin] >= -eps:
                    # zero on the problem's scale; some row may still approach on its own
                    # (``lcp._Dantzig._approaching``)
                    floor = _EPS_W * max(bmax, 1e-300)
                    late = -1
                    for i in range(m):
                        if st[i] == _U and nof[i] < 0 and w[i] < 0.0:
                            s_i = 0.0
                            for j in range(m):
                                s_i += abs(A[i, j]) * abs(x[j])
                            if w[i] < -max(floor, _EPS_ROW * s_i) and (
                                    late < 0 or w[i] < w[late]):
                                late = i
                    if late >= 0:
                        d, sigma = late, 1.0
                    else:
                        for i in range(m):
                            if st[i] == _U and nof[i] < 0:
                                st[i] = _NC
                else:
                    d, sigma = jmin, 1.0
            else:
                # deferred (dependent) friction rows are fine at x = 0 while their w stays 0
                bad = -1
                for k in range(m):
                    if st[k] == _Z and st[nof[k]] == _C and abs(w[k]) > eps:
                        bad = k
                        break
                if bad < 0:
                    break
                st[bad] = _U
                nodefer[bad] = True
            if d < 0:
                continue
            # ---- drive row d (``lcp._Dantzig._drive``) --------------------------------------
            isn_d = nof[d] < 0
            n_seen = 0
            prev_i, prev_code = -1, -1
            while True:
                if cnt[0] >= cap:
                    code = _PIVOT_CAP
                    break
                dx, dw = _dz_direction(A, b, st, nof, lo, hi, d, sigma, amax, cnt)
                finite = True
                dxmax = 1.0
                for r_ in range(m):
                    finite = finite and (dx[r_] - dx[r_] == 0.0) and (dw[r_] - dw[r_] == 0.0)
                    dxmax = max(dxmax, abs(dx[r_]))
                if not finite:
                    code = _NUMERIC
                    break
                dtol = _EPS_RATE * amax * dxmax
                xr = 1e-13 * dxmax
                n = 0
                if isn_d:
                    if dw[d] > dtol:
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[d] / dw[d]), 0, d, _DONE_C
                        n += 1
                    if sigma < 0.0:
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, x[d]), 2, d, _BAD
                        n += 1
                else:
                    if (w[d] > 0.0 and dw[d] < -dtol) or (w[d] < 0.0 and dw[d] > dtol):
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[d] / dw[d]), 0, d, _DONE_C
                        n += 1
                    j = nof[d]
                    rate = -dx[d] - lo[d] * dx[j]
                    if rate > xr:
                        good = w[d] > 0.0
                        ct[n] = max(0.0, (x[d] + lo[d] * x[j]) / rate)
                        cp[n], ci[n], cc[n] = (0 if good else 2), d, (_DONE_L if good else _BAD)
                        n += 1
                    rate = dx[d] - hi[d] * dx[j]
                    if rate > xr:
                        good = w[d] < 0.0
                        ct[n] = max(0.0, (hi[d] * x[j] - x[d]) / rate)
                        cp[n], ci[n], cc[n] = (0 if good else 2), d, (_DONE_H if good else _BAD)
                        n += 1
                for i in range(m):
                    s = st[i]
                    if i == d or s == _U or s == _DEAD:
                        continue
                    j = nof[i]
                    if j < 0:
                        if s == _C:
                            if dx[i] < -xr:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, x[i] / -dx[i]), 1, i, _C_NC
                                n += 1
                        elif dw[i] < -dtol:
                            ct[n], cp[n], ci[n], cc[n] = max(0.0, w[i] / -dw[i]), 1, i, _NC_C
                            n += 1
                        continue
                    if s == _C:
                        # the bounds move with the normal: x_i + t dx_i = mu (x_j + t dx_j)
                        rate = -dx[i] - lo[i] * dx[j]
                        if rate > xr:
                            ct[n] = max(0.0, (x[i] + lo[i] * x[j]) / rate)
                            cp[n], ci[n], cc[n] = 1, i, _C_L
                            n += 1
                        rate = dx[i] - hi[i] * dx[j]
                        if rate > xr:
                            ct[n] = max(0.0, (hi[i] * x[j] - x[i]) / rate)
                            cp[n], ci[n], cc[n] = 1, i, _C_H
                            n += 1
                    elif st[j] == _C or j == d:
                        if s == _L:
                            if dw[i] < -dtol:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, w[i] / -dw[i]), 1, i, _SL_C
                                n += 1
                        elif s == _H:
                            if dw[i] > dtol:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[i] / dw[i]), 1, i, _SL_C
                                n += 1
                        elif abs(dw[i]) > dtol:
                            # a clamped row it depended on has left C: clamp it now
                            ct[n], cp[n], ci[n], cc[n] = 0.0, 1, i, _Z_C
                            n += 1
                if n == 0:
                    code = _NO_STEP
                    break
                smin = ct[0]
                for q in range(1, n):
                    smin = min(smin, ct[q])
                if not (smin - smin == 0.0):
                    code = _NONFINITE
                    break
                lim = smin * (1.0 + 1e-12)
                sel = -1
                for q in range(n):
                    if ct[q] <= lim and (sel < 0 or cp[q] < cp[sel]
                                         or (cp[q] == cp[sel] and ci[q] < ci[sel])):
                        sel = q
                prio, i, ev = cp[sel], ci[sel], cc[sel]
                if ev == _BAD:
                    code = _BAD_END
                    break
                cnt[0] += 1
                xscale = max(bmax / amax, 1e-300)
                for v in x:
                    xscale = max(xscale, abs(v))
                if smin * dxmax > 1e-13 * xscale:
                    n_seen = 0
                else:
                    key = np.int64(1469598103934665603)
                    for v in st:
                        key = (key ^ np.int64(v)) * np.int64(1099511628211)
                    key = (key ^ np.int64(i + 1000)) * np.int64(1099511628211)
                    key = (key ^ np.int64(ev + 100)) * np.int64(1099511628211)
                    key = (key ^ np.int64(1 if sigma > 0 else 2)) * np.int64(1099511628211)
                    repeated = False
                    for q in range(n_seen):
                        if seen[q] == key:
                            repeated = True
                            break
                    if repeated:
                        # rescue: clamp waiting friction rows of active normals with w = 0
                        xmax = 0.0
                        for v in x:
                            xmax = max(xmax, abs(v))
                        eps2 = _EPS_W * max(max(bmax, amax * xmax), 1e-300)
                        rescued = False
                        for k in range(m):
                            jk = nof[k]
                            if (st[k] == _U and jk >= 0 and (st[jk] == _C or jk == d)
                                    and abs(w[k]) <= eps2):
                                st[k] = _C
                                rescued = True
                        if not rescued:
                            code = _CYCLING
                            break
                        n_seen = 0
                        prev_i = -1
                        continue
                    if n_seen == seen.shape[0]:
                        grown = np.empty(2 * n_seen, np.int64)
                        for q in range(n_seen):
                            grown[q] = seen[q]
                        seen = grown
                    seen[n_seen] = key
                    n_seen += 1
                    if prev_i >= 0 and prev_i == i and (
                            ((prev_code == _C_L or prev_code == _C_H) and ev == _SL_C)
                            or (prev_code == _SL_C and (ev == _C_L or ev == _C_H))
                            or (prev_code == _C_NC and ev == _NC_C)
                            or (prev_code == _NC_C and ev == _C_NC)):
                        # a fold of the solution path: follow it backwards in x_d
                        sigma = -sigma
                        prev_i = -1
                        continue
                prev_i, prev_code = i, ev
                for r_ in range(m):
                    x[r_] += smin * dx[r_]
                if ev == _DONE_C:
                    st[d] = _C
                elif ev == _DONE_L:
                    st[d] = _L
                elif ev == _DONE_H:
                    st[d] = _H
                elif ev == _C_NC:
                    st[i] = _NC
                    x[i] = 0.0
                    for k in range(m):
                        if nof[k] == i and st[k] != _DEAD:
                            st[k] = _U
                            x[k] = 0.0
                elif ev == _NC_C or ev == _SL_C or ev == _Z_C:
                    st[i] = _C
                elif ev == _C_L:
                    st[i] = _L
                else:
                    st[i] = _H
                # sync: re-impose the x fixed by each row's set, then refresh w
                for r_ in range(m):
                    s = st[r_]
                    if r_ == d or s == _C:
                        continue
                    if s == _L or s == _H:
                        j = nof[r_]
                        if st[j] == _C or j == d:
                            x[r_] = (-lo[r_] if s == _L else hi[r_]) * x[j]
                        else:
                            x[r_] = 0.0
                    else:
                        x[r_] = 0.0
                for r_ in range(m):
                    s = b[r_]
                    for q in range(m):
                        s += A[r_, q] * x[q]
                    w[r_] = s
                if prio == 0:
                    break
            if code != _OK:
                break
        total += cnt[0]
        codes[attempt] = code
        if code == _OK:
            # polish: the final sets solved in one piece (skipped after a few
            # well-conditioned pivots)
            nc = 0
            for i in range(m):
                nc += st[i] == _C
            if nc and (cnt[0] > 4 or cnt[1] > 0):
                no_row = m - m - 1      # -1, typed like d (a literal would compile anew)
                xp, wp = _dz_direction(A, b, st, nof, lo, hi, no_row, 0.0, amax, cnt)
                finite = True
                for v in xp:
                    finite = finite and (v - v == 0.0)
                if finite and (_dense_residual(A, b, xp, wp, nof, lo, hi)
                               <= _dense_residual(A, b, x, w, nof, lo, hi)):
                    for k in range(m):
                        x[k] = xp[k]
            return x, total, _OK, _OK
        r = _dense_residual(A, b, x, w, nof, lo, hi)
        if r < best_r:
            best_r = r
            for k in range(m):
                best_x[k] = x[k]
        if nfr == 0 or total >= max_pivots:
            break
    return best_x, total, codes[0], codes[1]


@jit
def clean_contacts(vert, edge, gap, t, cover_start, cover_lo, cover_hi, nxt, canon, vbody,
                   nw, n_vertices, n_bodies, param_tol, angle_tol):
    """The clean-up of ``collision.find_contacts`` after the narrow phase, same results:
    ``_not_internal`` and ``_vertex_vertex_keep`` on the raw contacts, ``_merge_duplicates``
    on the survivors, then the order by (min body, max body, piece_a, vertex, piece_b, edge)
    (pieces are numbered in vertex order, so vertex and edge imply the pieces). Returns the
    indices of the kept contacts in that order."""
    k = vert.shape[0]
    keep = np.ones(k, np.bool_)
    # contacts on internal portions of compound-body edges
    for i in range(k):
        e = edge[i]
        tc = min(max(t[i], 0.0), 1.0)
        for q in range(cover_start[e], cover_start[e + 1]):
            lo, hi = cover_lo[q], cover_hi[q]
            if (((tc > lo + param_tol) or (lo <= param_tol))
                    and ((tc < hi - param_tol) or (hi >= 1.0 - param_tol))):
                keep[i] = False
    # vertex on vertex: keep the contact whose edge belongs to the lower-numbered body
    end = -np.ones(k, np.int64)
    n_cand = 0
    for i in range(k):
        if abs(t[i]) <= param_tol:
            end[i] = edge[i]
        elif abs(t[i] - 1.0) <= param_tol:
            end[i] = nxt[edge[i]]
        if end[i] >= 0:
            n_cand += 1
    if n_cand >= 2:
        rev = np.empty(n_cand, np.int64)
        q = 0
        for i in range(k):
            if end[i] >= 0:
                rev[q] = canon[vert[i]] * n_vertices + canon[end[i]]
                q += 1
        rev = rev[_argsort(rev)]
        for i in range(k):
            if end[i] >= 0 and vbody[edge[i]] > vbody[vert[i]]:
                key = canon[end[i]] * n_vertices + canon[vert[i]]
                lo_, hi_ = 0, n_cand          # binary search: first rev >= key
                while lo_ < hi_:
                    mid = (lo_ + hi_) // 2
                    if rev[mid] < key:
                        lo_ = mid + 1
                    else:
                        hi_ = mid
                if lo_ < n_cand and rev[lo_] == key:
                    keep[i] = False
    idx = _where(keep)
    n = idx.shape[0]
    # duplicates: one canonical vertex against parallel edges of one body
    if n >= 2:
        gkey = np.empty(n, np.int64)
        for q in range(n):
            i = idx[q]
            gkey[q] = ((vbody[vert[i]] * n_vertices + canon[vert[i]]) * n_bodies
                       + vbody[edge[i]])
        o = _argsort(gkey)
        s0 = 0
        while s0 < n:
            s1 = s0 + 1
            while s1 < n and gkey[o[s1]] == gkey[o[s0]]:
                s1 += 1
            if s1 - s0 >= 2:
                # members by (gap, vertex, edge), then keep greedily
                mem = idx[o[s0:s1]].copy()
                for u in range(1, mem.shape[0]):
                    v = mem[u]
                    p = u - 1
                    while p >= 0 and (gap[mem[p]] > gap[v] or (gap[mem[p]] == gap[v] and (
                            vert[mem[p]] > vert[v] or (vert[mem[p]] == vert[v]
                                                       and edge[mem[p]] > edge[v])))):
                        mem[p + 1] = mem[p]
                        p -= 1
                    mem[p + 1] = v
                kept = np.empty(mem.shape[0], np.int64)
                nk = 0
                for u in range(mem.shape[0]):
                    ci = mem[u]
                    nx, ny = nw[edge[ci], 0], nw[edge[ci], 1]
                    dup = False
                    for z in range(nk):
                        mx, my = nw[edge[kept[z]], 0], nw[edge[kept[z]], 1]
                        if nx * mx + ny * my > 0 and abs(nx * my - ny * mx) <= angle_tol:
                            dup = True
                            break
                    if dup:
                        keep[ci] = False
                    else:
                        kept[nk] = ci
                        nk += 1
            s0 = s1
        idx = _where(keep)
        n = idx.shape[0]
    # final order
    k1 = np.empty(n, np.int64)
    k2 = np.empty(n, np.int64)
    for q in range(n):
        i = idx[q]
        ba, bb = vbody[vert[i]], vbody[edge[i]]
        k1[q] = min(ba, bb) * n_bodies + max(ba, bb)
        k2[q] = vert[i] * n_vertices + edge[i]
    o2 = _argsort(k2)
    o1 = _argsort(k1[o2])
    return idx[o2[o1]]
