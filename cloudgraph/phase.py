"""Anisotropic phase functions in Dr.Jit, and the walk that takes their first scattering events
exactly (docs/method.md, "Anisotropic scattering").

The graph of an anisotropic medium is isotropic (the similarity-scaled medium's), so what depends
on the phase is taken exactly where it matters most: :func:`phase_walk` follows a path through
its first scattering events as volpath does, then the graph's radiance stands in for the rest.
``gather`` starts it at the camera's first collision (integrators/graph.py); the field's bake
starts it at grid points and keeps the result's dependence on direction as coefficients of
:func:`shape_basis` (field_ms.py). Both read :func:`hg_phase`, :func:`sample_phase` and
:func:`phase_bounces` (``gather``) or :func:`memory_bounces` (the field).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .tracing import ratio_tracking, sample_collision

#: ``gather``'s exact scattering events with an anisotropic phase: until the direction's mean
#: cosine with the camera's, |g_eff|^k, is at most this (at most MAX_PHASE_BOUNCES events).
#: Measured on the bench sphere back-lit at g = 0.85 (24^2, draft, gather 2048 spp against
#: volpath at 16384, mean ratio): k = 20 (|g|^k = 0.04) 0.975, 25 (0.017) 0.991, 32 0.995.
PHASE_MEMORY = 0.02
MAX_PHASE_BOUNCES = 64
#: ``gather``'s least exact events with an anisotropic phase. The similarity-scaled graph reads
#: low as a tail on a cloud a few transport paths across. The bench sphere back-lit at g = 0.5
#: (64^2, default, gather 8192 spp against volpath 16384, mean ratio at albedo 1 / 0.8): the
#: tail after 6 events (g's memory) 0.982 / 0.993, after 12 0.993 / 0.998, after 16 0.995 /
#: 0.999, after 64 (no tail) 1.001 / 1.000; the noise cloud within 0.5 % at 6, 16 and 64.
#: ``gather`` at 16 events costs 1.4-1.8x its time at 6 on smoke1 and blender. The field's
#: walks keep :func:`memory_bounces` (16 would cost its bake about 1.5x).
GATHER_MIN_BOUNCES = 16
#: The functions of direction in which the field keeps how a sun's L_ms depends on the view
#: (field.py, ``ms_shape``), in a frame whose z is towards the light (:func:`light_frame`): the
#: real spherical harmonics of degrees 1..SHAPE_FULL (light that turned: a cloud's diffuse
#: flux), and the zonal ones (Legendre polynomials of z, symmetric about the light) on up to
#: SHAPE_ORDER (the forward peak), then the non-zonal harmonics of degree SHAPE_FULL + 1 at
#: SHAPE_HALF of their weight. Unnormalised: Q_l^m(z) Re, Im (x + iy)^m, Q_l^m the m-th
#: derivative of P_l. On the bench sphere at g = 0.85 side-lit, the Legendre polynomials alone
#: read 0.63 of volpath's mean; with every harmonic of degree <= 2, 0.99. Near a surface that
#: faces the camera the light is a step in direction (none from outside), which the sums to
#: degree 2 and to degree 3 overshoot on either side: at the tests' dense cloud's points within
#: one optical depth of that surface (second order, 4096 walks a point, no grid) 1.165 and 0.824
#: of L_ms estimated exactly, 1 to 3 optical depths in 0.878 and 1.068 (docs/measurements.md,
#: "The view terms' series"). Between the two sums: for a step of light across the light's
#: direction seen from 0-45 degrees off it (HG 0.85; test_phase_field), the degree-3 terms at
#: half weight (Cesaro's mean) read 1.046 of the exact mean, at 3/4 1.009 (worst 5.4 -> 4.6 %),
#: at full 0.971. Rendered at g = 0.85 side-lit (field at 16 spp against gather at 1024 on one
#: cache, 12 renders of the held-out cloud, the sphere and the dense cloud, albedo 1 and 0.8,
#: two bakes each), 1/2 -> 3/4: the field's mean 1.005-1.035 (average 1.021) -> 0.993-1.022
#: (1.003), binned relMAE 4.95 -> 4.77 % on average; back-lit views and g = 0.5 as before,
#: within noise (docs/measurements.md, "The degree-3 view terms at three quarters").
SHAPE_FULL = 2
SHAPE_ORDER = 8
SHAPE_HALF = 0.75
SHAPE_TERMS = (
    tuple((n, m) for n in range(1, SHAPE_FULL + 1) for m in range(-n, n + 1))
    + tuple((n, 0) for n in range(SHAPE_FULL + 1, SHAPE_ORDER + 1))
    + tuple((SHAPE_FULL + 1, m) for m in range(-SHAPE_FULL - 1, SHAPE_FULL + 2) if m != 0)
)
#: Each term's weight in the sum (1, or SHAPE_HALF for the degree SHAPE_FULL + 1 harmonics).
SHAPE_WEIGHTS = tuple(SHAPE_HALF if n > SHAPE_FULL and m != 0 else 1.0 for n, m in SHAPE_TERMS)
SHAPE_DEGREES = tuple(n for n, _ in SHAPE_TERMS)
_Q = {
    (n, m): np.polynomial.legendre.Legendre.basis(n).convert(kind=np.polynomial.Polynomial).deriv(m).coef
    for n, m in {(n, abs(m)) for n, m in SHAPE_TERMS}
}


def shape_basis(x, y, z) -> list:
    """The :data:`SHAPE_TERMS` functions at unit directions (x, y, z) of the light's frame
    (numpy arrays or Dr.Jit floats)."""
    re, im = [x * 0.0 + 1.0], [x * 0.0]  # Re, Im (x + iy)^m (P_l's by its polynomial: Horner)
    for _ in range(max(abs(m) for _, m in SHAPE_TERMS)):
        re, im = re + [re[-1] * x - im[-1] * y], im + [re[-1] * y + im[-1] * x]
    out = []
    for n, m in SHAPE_TERMS:
        q = x * 0.0 + float(_Q[n, abs(m)][-1])
        for c in _Q[n, abs(m)][-2::-1]:  # Horner
            q = q * z + float(c)
        out.append(q * (re[m] if m >= 0 else im[-m]))
    return out


def _norms() -> tuple:
    """The integrals of the squares of :func:`shape_basis` over the sphere (they are
    orthogonal): Gauss-Legendre in z times the trapezoid in azimuth, exact for these degrees."""
    z, wz = np.polynomial.legendre.leggauss(SHAPE_ORDER + 2)
    phi = np.linspace(0, 2 * np.pi, 4 * SHAPE_ORDER + 4, endpoint=False)
    Z, PHI = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - Z * Z)
    W = wz[:, None] * (2 * np.pi / len(phi))
    return tuple(float((W * b * b).sum()) for b in shape_basis(r * np.cos(PHI), r * np.sin(PHI), Z))


SHAPE_NORMS = _norms()


def light_frame(to_light) -> np.ndarray:
    """(3, 3) rows e_x, e_y, e_z: an orthonormal frame with e_z = to_light (unit), the one the
    bake, the server's march and the page's all take (written into the field's header)."""
    ez = np.asarray(to_light, float) / np.linalg.norm(to_light)
    a = np.array([0.0, 0.0, 1.0]) if abs(ez[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    ex = np.cross(a, ez)
    ex /= np.linalg.norm(ex)
    return np.stack([ex, np.cross(ez, ex), ez])


def hg_phase(lobes: tuple, mu: mi.Float) -> mi.Float:
    """p(mu) of a blend of Henyey-Greenstein lobes ((weight, g), ...), per steradian, mu the
    cosine between the light's travel before and after scattering (Mitsuba's ``hg``: g > 0
    forward):  p = sum_i w_i (1 - g_i^2) / (4pi (1 + g_i^2 - 2 g_i mu)^1.5)."""
    p = mi.Float(0.0)
    for w, g in lobes:  # the scene's lobes, unrolled into the kernel
        denom = 1.0 + g * g - 2.0 * g * mu
        p += w * (1.0 - g * g) / (4.0 * dr.pi * denom * dr.sqrt(denom))
    return p


def phase_legendre(lobes: tuple, order: int) -> np.ndarray:
    """(order + 1,) the phase's Legendre coefficients g_l = sum_i w_i g_i^l: a function of
    direction whose Legendre moments about an axis are a_l, convolved with the phase, has
    moments g_l a_l (Funk-Hecke; a Henyey-Greenstein lobe's are exactly g^l)."""
    return sum(w * float(g) ** np.arange(order + 1) for w, g in lobes)


def lobe_power(lobes: tuple, n: int) -> tuple:
    """The lobes ((weight, g), ...) of the phase convolved with itself ``n`` times (n >= 1):
    HG lobes convolve into one lobe of the product of their g (their Legendre moments g^l
    multiply), so a blend's n-th power is a blend of lobes of every product, equal g merged."""
    out = {1.0: 1.0}  # (a delta: g = 1)
    for _ in range(n):
        nxt: dict = {}
        for g0, w0 in out.items():
            for w, g in lobes:
                key = round(g0 * float(g), 12)
                nxt[key] = nxt.get(key, 0.0) + w0 * float(w)
        out = nxt
    return tuple((w, g) for g, w in out.items())


def beam_phases(lobes: tuple, orders: int, mu: mi.Float, more: int) -> list:
    """The phase's powers p^{*(n + more)}(mu), n = 1..``orders``, that :func:`forward_light`
    weights (constant along a camera ray: computed once per ray, not per step)."""
    return [hg_phase(lobe_power(lobes, n + more), mu) for n in range(1, orders + 1)]


def forward_light(albedo: mi.Color3f, tau: mi.Float, phases: list) -> mi.Color3f:
    """The sun's light of the first ``len(phases)`` scattering orders that is still in its beam,
    per unit irradiance (field_ms.FORWARD_ORDERS): light scattered n times within a forward peak
    has crossed the optical depth tau of the straight path from the sun, and its direction
    spread as the phase's n-th power,  sum_n exp(-tau) (albedo tau)^n / n! phases[n - 1], with
    ``phases`` :func:`beam_phases` at mu = to_light . w (``more`` convolutions with the phase
    more: 0 for the radiance arriving at a point, 1 for what it scatters into a camera ray)."""
    T = dr.exp(-tau)
    term = mi.Color3f(1.0)
    L = mi.Color3f(0.0)
    for n, p in enumerate(phases, start=1):  # unrolled
        term = term * albedo * (tau / n)
        L += T * term * p
    return L


def memory_bounces(phase) -> int:
    """Scattering events a path remembers its direction over: 1 for the isotropic phase, else
    the least k with |g_eff|^k <= PHASE_MEMORY (g = 0.5: 6, g = 0.85: 25), at most
    MAX_PHASE_BOUNCES. After k events a path's direction keeps a mean cosine of g_eff^k with the
    one it started in (each event multiplies it by g_eff, whatever the phase's shape). The
    field's walks take as many (field.py)."""
    g = 0.0 if phase is None or phase.isotropic else abs(phase.mean_cosine())
    if g <= PHASE_MEMORY:
        return 1
    return int(min(MAX_PHASE_BOUNCES, np.ceil(np.log(PHASE_MEMORY) / np.log(g) - 1e-9)))


def phase_bounces(phase) -> int:
    """Exact scattering events of ``gather`` before the graph takes over: :func:`memory_bounces`,
    and at least GATHER_MIN_BOUNCES for an anisotropic phase (g = 0.5: 16, g = 0.85: 25)."""
    k = memory_bounces(phase)
    return k if k == 1 else max(k, GATHER_MIN_BOUNCES)


def sample_phase(lobes: tuple, d: mi.Vector3f, rng: mi.PCG32) -> mi.Vector3f:
    """Directions w toward where light comes from, for light scattered into -d (d the ray's
    direction), with density p(dot(w, d)): a lobe by its weight, then the HG inverse CDF
    mu = (1 + g^2 - ((1 - g^2) / (1 - g + 2 g u))^2) / 2g (uniform where g = 0). The estimate's
    weight p / pdf is 1."""
    u_lobe, u, phi = rng.next_float32(), rng.next_float32(), 2.0 * dr.pi * rng.next_float32()
    (w1, g1), *rest = lobes
    g = mi.Float(g1) if not rest else dr.select(u_lobe < w1, g1, rest[0][1])
    small = dr.abs(g) < 1e-4
    gs = dr.select(small, 1.0, g)
    sq = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * u)
    mu = dr.clip(dr.select(small, 2.0 * u - 1.0, (1.0 + gs * gs - sq * sq) / (2.0 * gs)), -1.0, 1.0)
    s = dr.safe_sqrt(1.0 - mu * mu)
    return mi.Frame3f(d).to_world(mi.Vector3f(s * dr.cos(phi), s * dr.sin(phi), mu))


#: Next-event estimation at each scattering event after the first by two strategies, weighted
#: by the balance heuristic (docs/method.md, "Anisotropic scattering"): the sun's light at the
#: event the path's own flight reaches, and at the end of one more flight drawn from the phase
#: about the light. Either alone reads p(w . w_in) p(to_light . w) over the flight's direction
#: w; with a peaked phase the path's own draws rarely turn toward a sun to its side, whose light
#: then arrives in rare large samples. On the bench at g = 0.85 (64^2, ``gather`` at 256 spp,
#: binned noise, side-lit albedo 1 / 0.8): sphere 6.8 % -> 3.4 %, dense 4.1 / 6.1 % -> 2.7 /
#: 3.1 %, thick 4.9 / 6.4 % -> 3.1 / 3.6 %, for 1.7x the time; back-lit 3.1-5.7 % -> 3.3-4.4 %.
#: The field's walks (field_ms.walk_ms) read 8.7 % -> 5.4 % from gather side-lit (6 rows). Taken
#: where a lobe's |g| is SUN_LOBE_FROM or more: at g = 0.5 the lobes are broad and meet, and the
#: noise stayed as it was (512 spp: side-lit 0.8-0.9 %, back-lit 1.4-2.4 %) for 1.5x the time.
SUN_LOBE_NEE = True
SUN_LOBE_FROM = 0.7
#: At each exact event after a peaked phase's (|g| >= SUN_LOBE_FROM) next direction w is drawn,
#: the sun's light of the beam's orders 2..BEAM_CV_ORDERS (light that stayed in the sun's forward
#: peak, in closed form: :func:`forward_light`) is added as a control variate: its integral over
#: the phase at the event, less its value at the drawn w, zero in expectation. A walk that turns
#: into the beam then reads the peak at every event after (up to 6.5 sr^-1 at g = 0.85 against
#: 0.08 for isotropic light): its walks' estimates are heavy-tailed, and the variate takes the
#: closed form's share of that spike out where it is drawn. Measured on the bench at g = 0.85,
#: side-lit (64^2, default; field at 16 spp against gather at 2116 on one cache, two seeds of the
#: bake each, binned relMAE; albedo 1 / 0.8): sphere 5.93, 8.95 / 4.99, 7.12 % -> 5.10, 6.26 /
#: 5.01, 6.60 %, dense 3.66, 4.57 / 5.11, 5.50 % -> 4.17, 4.07 / 4.49, 4.49 %; gather's noise at
#: 256 spp the same on the sphere and 2.70 / 3.14 % -> 2.44 / 2.30 % on the dense cloud; 4
#: orders took less (the sphere at albedo 1: the two bakes' difference 7.9 -> 5.7 % with 4, 5.2 %
#: with 8). The beam's first order is left out: the flights drawn about the light take it.
BEAM_CV_ORDERS = 8


def beam_variate(lobes: tuple, albedo, tau, mu_in, mu_drawn) -> mi.Color3f:
    """The sun's light of the beam's orders 2..BEAM_CV_ORDERS (per unit irradiance) scattered
    at an event into -w_in, in closed form (:func:`forward_light` one convolution on), less the
    same read at the direction w drawn from the phase there: zero in expectation over w."""
    exact = beam_phases(lobes, BEAM_CV_ORDERS, mu_in, 1)
    drawn = beam_phases(lobes, BEAM_CV_ORDERS, mu_drawn, 0)
    return forward_light(albedo, tau, [0.0] + [a - b for a, b in zip(exact[1:], drawn[1:], strict=True)])


def _peaked(lobes: tuple) -> bool:
    return any(w > 0 and abs(g) >= SUN_LOBE_FROM for w, g in lobes)


@dr.syntax
def phase_walk(medium, lobes, suns, albedo, background, tail, o, d, rng, active, bounces: int, sun_tr=None):
    """The radiance that reaches o along -d through scattering in the medium (d of unit length),
    its first ``bounces`` scattering events taken exactly, as volpath takes them: delta tracking;
    next-event estimation by ratio tracking to each sun, weighted by the phase at
    (to_light . w_in); the next direction sampled from the phase about w_in (weight p / pdf = 1).
    Then ``tail(q, mask)``, albedo L'_search(q) of an isotropic graph, stands in for everything
    after, at the point q one more flight on (Eq. 4.25; None: nothing after).

    With a peaked phase (:data:`SUN_LOBE_NEE`, :data:`SUN_LOBE_FROM`) the sun's light at
    every event after the first has a second estimate, made at the event before (at p, arrived
    along w_in): a flight along w drawn from the phase about the light, density p_l(w) =
    p(to_light . w), to its collision q. The sun's light scattered at q back toward p is
    Tr(q) E p_l(w), and at p into the path p_a(w) = p(w_in . w) of it: over the draw's density,
    Tr(q) E p_a(w). The path's own flight reads Tr E p_l over the density p_a. Weighted by the
    balance heuristic, p_a / (p_a + p_l) and p_l / (p_a + p_l), each reads
    Tr E p_a p_l / (p_a + p_l): at most the lesser phase. After each next direction is drawn,
    the beam's orders 2.. enter as a control variate (:data:`BEAM_CV_ORDERS`).

    Args:
        suns: [(to_light (3,), E mi.Color3f), ...] the directional lights, unrolled.
        albedo: mi.Color3f; background(mask, w): what a flight of direction w that leaves the
            medium sees (where mask).
        sun_tr: sun_tr(i, p, mask), the transmittance from points p to sun i (None: ratio
            tracking).
    """
    lobe_nee = SUN_LOBE_NEE and _peaked(lobes) and bounces > 1  # (no second event: no flight)
    beam_cv = BEAM_CV_ORDERS > 1 and _peaked(lobes) and bounces > 1
    t, alive = sample_collision(medium, o, d, rng, active & (bounces > 0))
    L = background(active & ~alive, d)  # Radiance accumulator
    p = mi.Point3f(o + t * d)  # Scattering point
    w_in = mi.Vector3f(d)  # Direction the path (from o) arrived at p in
    w_from = mi.Vector3f(d)  # ... and the one it was drawn about (after the first event)
    beta = mi.Color3f(1.0)  # Path throughput: albedo per scattering event
    k = mi.UInt32(0)  # Scattering events taken
    while dr.hint(alive, label="phase_walk"):
        beta *= albedo
        trs = []  # (each sun's transmittance at p)
        for i, (to_light, E) in enumerate(suns):  # unrolled
            tl = mi.Vector3f(*to_light)
            Tr = sun_tr(i, p, alive) if sun_tr else ratio_tracking(medium, p, tl, rng, alive)
            trs.append(Tr)
            p_l = hg_phase(lobes, dr.dot(tl, w_in))
            if dr.hint(lobe_nee, mode="scalar"):
                # this event's share (its first event's direction was not drawn: all of it) ...
                p_a = hg_phase(lobes, dr.dot(w_from, w_in))
                L += beta * Tr * E * dr.select(k == 0, p_l, p_a * p_l / (p_a + p_l))
                # ... and the next event's by a flight drawn about the light (if it has one)
                w_l = sample_phase(lobes, tl, rng)
                t_l, hit_l = sample_collision(medium, p, w_l, rng, alive & (k + 1 < bounces))
                q_l = mi.Point3f(p + t_l * w_l)
                Tr_l = sun_tr(i, q_l, hit_l) if sun_tr else ratio_tracking(medium, q_l, tl, rng, hit_l)
                p_a, p_l = hg_phase(lobes, dr.dot(w_in, w_l)), hg_phase(lobes, dr.dot(tl, w_l))
                L += dr.select(hit_l, beta * albedo * Tr_l * E * (p_a * p_l / (p_a + p_l)), 0.0)
            else:
                L += beta * Tr * E * p_l
        w = sample_phase(lobes, w_in, rng)
        if dr.hint(beam_cv, mode="scalar"):
            # the beam's orders 2.. as a control variate (BEAM_CV_ORDERS): their closed form
            # integrated over this event's phase, less the same at the drawn direction w (only
            # where the walk goes on to take that light itself)
            for i, (to_light, E) in enumerate(suns):  # unrolled
                tl = mi.Vector3f(*to_light)
                tau_b = -dr.log(dr.maximum(trs[i], 1e-30))
                cv = beam_variate(lobes, albedo, tau_b, dr.dot(tl, w_in), dr.dot(tl, w))
                L += dr.select(alive & (k + 1 < bounces), beta * E * cv, 0.0)
        t2, hit = sample_collision(medium, p, w, rng, alive)
        L += beta * background(alive & ~hit, w)
        k += 1
        q = mi.Point3f(p + t2 * w)
        if dr.hint(tail is not None, mode="scalar"):  # unbounded depth: the graph takes over at q
            last = hit & (k >= bounces)
            L += dr.select(last, beta * tail(q, last), 0.0)
        p, w_from, w_in = q, mi.Vector3f(w_in), mi.Vector3f(w)
        alive &= hit & (k < bounces)
    return L
