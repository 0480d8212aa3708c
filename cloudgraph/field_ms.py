"""The radiance field's multiple scattering: L_ms at the points of its grid, from the graph
(docs/method.md, "The radiance field"; field.py bakes it, as ``field_ms`` chunks).

Everything after the first scattering is computed as ``gather`` computes it at its camera
collision: one more flight from the grid point to p'', where G = albedo L'_search (the
``radiance_gather`` of Eq. 4.25, on the field grid, with the isotropic phase plus each sun's
direct light where the flight is, from tau_light: field.py) stands in for the rest,

    L_ms(x) = 1/4pi int_S2 int_0^inf T_r(x, x + t w) sigma_t(x + t w) G(x + t w) dt dw,

the flight integrated over :data:`MS_DIRECTIONS` directions in closed form, not sampled
(:func:`gather_ms`). An anisotropic phase (docs/method.md, "Anisotropic scattering") takes a
sun's L_ms by the walks of ``gather`` (its first events exact) from the points instead, and keeps
how it depends on the view as coefficients of 20 functions of direction (:func:`walk_ms`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import gaussian_filter

from .phase import (
    SHAPE_DEGREES,
    SHAPE_NORMS,
    SHAPE_WEIGHTS,
    beam_phases,
    forward_light,
    hg_phase,
    light_frame,
    phase_legendre,
    phase_walk,
    sample_phase,
    shape_basis,
)
from .tracing import (
    ISOTROPIC_PDF,
    colour_texture,
    depth_at,
    envmap_nee,
    envmap_pdf,
    envmap_seen,
    exponential_segment,
    from_jit,
    jit_rng,
    opaque,
    optical_depth,
    power_heuristic,
    step_length,
    to_jit,
    uniform_sphere,
)

#: Directions per point of the multiple-scattering gather (8 and 16 measure the same on the
#: dense bench cloud: the camera march averages neighbouring points' turned sets), and its
#: shortest march step in field voxels.
MS_DIRECTIONS = 8
MS_STEP = 0.5
#: The gather's steps span at most this optical depth (at the block majorant), and at most
#: MS_STRIDE times MS_STEP (4 voxels) in thin media. Steps of at least a voxel read L_ms bright
#: where a voxel is optically thick: on the dense bench cloud at albedo 1, back-lit, ``gather``
#: with its second flight replaced by this march from the camera's collision read 1.0 % over the
#: same with the flight sampled (and 2.2 % at albedo 0.8); with steps down to half a voxel 0.3 %,
#: to a quarter 0.1 % (docs/measurements.md, "Where the medium absorbs, and the field's
#: multiple-scattering march").
MS_MAX_DTAU = 0.5
MS_STRIDE = 8.0
#: The gather stops where this much light is left, and adds the rest at the last G seen.
MS_TR_MIN = 1e-2
#: The bake's G = albedo L' (what a flight from a grid point reaches) is interpolated between
#: grid points as G^G_POWER per channel, as tau_light is as T^TAU_POWER: it rises steeply toward
#: a lit surface, and interpolating G itself read the field's multiple scattering bright back-
#: lit. thick (blender at optical depth 2 a voxel), all orders, albedo 1, field at 16 spp against
#: 1024-spp volpath, binned relMAE / mean: back-lit 5.59 % / 1.053 with G, 5.21 % / 1.049 with
#: G^0.5, 5.09 % / 1.047 with G^0.3 (gather 4.32 % / 1.037); side-lit 2.63, 2.58, 2.56 %.
G_POWER = 0.3
#: ... and as G itself where G is looked up on a grid coarser than the field's (a large medium:
#: field.lookup_grid), where interpolating its power reads low between the points (a power mean of
#: the corners is below their mean). smoke1 (G on a grid 2x coarser; field at 16 spp against
#: RR-free volpath at 4096, binned relMAE / mean; side-lit albedo 1 / 0.8, back-lit 1 / 0.8): G^0.3
#: 1.74 / 1.09 / 0.90 / 0.69 %, 0.985 / 0.991 / 0.999 / 1.000; G 1.59 / 1.00 / 0.88 / 0.72 %,
#: 0.988 / 0.993 / 1.001 / 1.001 (G^0.3 at every field point: 1.43 / 0.97 / 0.86 / 0.69 %, 0.989 /
#: 0.994 / 1.000 / 1.001; gather 1.15 / 0.96 / 1.29 / 1.23 %, 0.993 / 0.994 / 1.003 / 1.003).
G_POWER_COARSE = 1.0
#: An anisotropic phase: walks per multiple-scattering point (phase.phase_walk, its first
#: events exact, from directions half uniform and half from the phase about the light); half
#: as many on a grid of more than field.MS_MAX_POINTS points (a large cloud's, allowed up to
#: field.MS_WALK_POINTS), so that no grid takes more walks than the largest did at WALKS.
#: smoke1 at g = 0.5 (field at 16 spp against gather at 1024 on one cache, binned relMAE side-
#: lit, albedo 1 / 0.8; precompute): its grid 3x coarser than the field's, 64 walks, 2.67 /
#: 1.87 %, 7.2-8.0 s; 2x coarser, 64 walks, 1.49 / 1.26 %, 11.1-11.9 s; 2x coarser, 32 walks,
#: 1.68 / 1.31 %, 9.3-9.8 s (isotropic: 7.6-8.5 s).
WALKS = 64
#: ... and the width (standard deviation, in multiple-scattering grid points) of the Gaussian
#: that smooths the walks' estimates over the grid: 0 up to |g_eff| = 0.5, WALK_SMOOTH from
#: 0.85 on, linear between, and 0 where the beam's orders are in closed form (FORWARD_FROM). A
#: peaked phase makes the walks heavy-tailed (next-event estimation weighted by the peak): on the
#: bench sphere at g = 0.85 (64^2, field against volpath at 16,384 spp, binned relMAE / mean) 128
#: walks unsmoothed read 8.2 % / 1.040 side-lit and 512 walks 7.5 % / 1.039, 64 walks smoothed
#: over 2 points 7.9 % / 0.985 (back-lit 4.2 % / 0.984). At g = 0.5 (draft, against 4096 spp)
#: smoothing costs more than it saves: unsmoothed 3.9 %, over 1 point 5.9 %, 2 points 8.4 %
#: (gather 3.0 %). With the beam's orders in closed form the walks' view terms no longer hold
#: the peak, and smoothing only blurs: the bench's thick cloud at g = 0.85 (field at 16 spp
#: against gather at 1024, binned relMAE, side-lit albedo 1 / 0.8, back-lit 1 / 0.8) 7.6 / 10.4 /
#: 3.5 / 2.9 % unsmoothed, 7.2 / 11.5 / 4.2 / 3.0 % over 1 point, 8.4 / 14.3 / 6.9 / 4.0 % over 2.
WALK_SMOOTH = 2.0
#: The field keeps each sun's L_ms over a factor of that sun's light, f = exp(-min(P tau_light,
#: RANGE)), and its readers multiply it back where they read (field.py, :func:`light_factor`): in a
#: dense cloud L_ms falls within a fraction of a voxel below a lit surface, like the light, and
#: tau_light is read on a grid up to twice as fine. P per channel grows with absorption, as the
#: diffusion's decay sqrt(3 (1 - albedo)) does: P = P_0 + P_1 sqrt(3 (1 - albedo)). Chosen on the
#: bench's thick and dense clouds, all orders, field at 16 spp against gather at 1024 on one
#: cache (4x4-binned relMAE / mean; docs/measurements.md): first thick side-lit at albedo 0.8
#: 2.30 % / 0.985 without, 1.21 % / 1.001 with P = 0.45 (P 0.25-0.75 and RANGE 1-4 tried); at
#: albedo 1 1.69 % / 0.991 without, 1.25 % / 0.998 with P = 0.1 (P = 0.5: 2.25 % / 1.021). Chosen
#: again with the march's half-voxel steps (MS_STEP), which no longer reads L_ms bright: with
#: (0.1, 0.45) thick side-lit at albedo 0.8 read 0.987 of gather, with (0.2, 0.8) 0.998; over the
#: dense and thick clouds' 8 views, field against gather within 0.998-1.012 in mean.
MS_LIGHT_POWER = (0.2, 0.8)
MS_LIGHT_RANGE = 1.25
#: ... and P_0 where the suns' L_ms is walked (an anisotropic phase: every sun's is). At g = 0.5
#: (64^2, default, field at 16 spp against gather at 1024 on one cache, binned relMAE; side-lit
#: albedo 1 / 0.8, back-lit 1 / 0.8) P_0 = 0.2 -> 0.6: blender 2.51 / 2.01 / 2.75 / 2.55 % ->
#: 1.58 / 1.87 / 2.58 / 2.44 %, its mean 0.980-0.987 -> 0.985-0.994 of gather; smoke1, the sphere
#: and the noise cloud within 0.3 points either way; at P_0 = 1 blender 1.76 / 2.08 / 2.37 /
#: 2.47 %. At g = 0.85 blender side-lit 5.85 / 5.29 % -> 5.37 / 5.05 %.
WALK_LIGHT_POWER_0 = 0.6
#: An anisotropic phase: the sun's light of this many scattering orders that is still in its
#: beam is taken in closed form (phase.forward_light), where the camera's march reads it, and
#: the walks keep only the rest: scattered n times within the forward peak, light from the sun
#: has crossed the straight path's optical depth tau and its direction has spread as the
#: phase's n-th power (HG lobes convolve into HG lobes). It is the sharpest part of L_ms in
#: direction and in space (it falls below a lit surface as the light does), which the walks'
#: projection on SHAPE_ORDER degrees and their smoothing blurred. The bench at g = 0.85 (64^2,
#: default, field at 16 spp against gather at 1024 on one cache, binned relMAE; side-lit albedo
#: 1 / 0.8, back-lit 1 / 0.8), walks alone smoothed over 2 points -> 2 orders unsmoothed: thick
#: 9.8 / 17.6 / 9.7 / 9.0 % -> 7.6 / 10.4 / 3.5 / 2.9 %, dense 10.3 / 19.1 / 10.1 / 9.0 % ->
#: 9.1 / 14.8 / 3.1 / 2.9 %, sphere 7.5 / 12.9 / 5.6 / 8.2 % -> 9.7 / 13.7 / 5.7 / 5.9 % (gather's
#: own noise is 1-4 %). 1 and 3 orders read within a point of 2 (docs/measurements.md). At
#: g = 0.5 the peak is broad and the straight path's depth a worse guess: thick 2.4 / 2.2 / 2.5 /
#: 3.4 % -> 2.7 / 3.4 / 1.9 / 2.3 %, sphere 1.8 / 2.4 / 1.8 / 3.3 % -> 2.1 / 2.6 / 2.2 / 4.8 %, so
#: the closed form is taken from a mean cosine of FORWARD_FROM on (only 0.5 and 0.85 measured).
FORWARD_ORDERS = 2
FORWARD_FROM = 0.7


def ms_light_power(albedo, walked: bool = False) -> np.ndarray:
    """(3,) P of the light factor per channel (MS_LIGHT_POWER; ``walked``: the suns' L_ms is
    walked, P_0 is WALK_LIGHT_POWER_0)."""
    a = np.clip(np.broadcast_to(np.asarray(albedo, float), (3,)), 0.0, 1.0)
    p0 = WALK_LIGHT_POWER_0 if walked else MS_LIGHT_POWER[0]
    return p0 + MS_LIGHT_POWER[1] * np.sqrt(3.0 * (1.0 - a))


def view_light_power(albedo, walked: bool) -> float:
    """The grey P of the light factor that a sun's view terms are kept over (their one channel):
    the mean of :func:`ms_light_power`'s (the view terms are the walks'). Like c_0 they fall
    below a lit surface as the light does, and kept over the factor they interpolate between
    grid points at half the resolution (field.py)."""
    return float(ms_light_power(albedo, walked).mean())


def light_factor(tau: np.ndarray, power, limit: float) -> np.ndarray:
    """(..., 3) f = exp(-min(P tau, limit)) per channel at optical depths ``tau`` (...)."""
    return np.exp(-np.minimum(np.asarray(tau, float)[..., None] * np.asarray(power, float), limit))


def forward_orders(phase, max_depth: int = -1) -> int:
    """The orders of a sun's light in its beam that the camera's march takes in closed form
    (FORWARD_ORDERS), of those after the camera's own event; 0 below FORWARD_FROM."""
    if phase is None or phase.isotropic or abs(phase.mean_cosine()) < FORWARD_FROM:
        return 0
    return FORWARD_ORDERS if max_depth < 0 else max(0, min(FORWARD_ORDERS, max_depth - 1))


def walks_per_point(points: int, max_points: int) -> int:
    """Walks a point of a multiple-scattering grid of ``points`` points: WALKS, half as many over
    ``max_points`` (field.MS_MAX_POINTS)."""
    return WALKS if points <= max_points else WALKS // 2


def walk_smoothing(phase) -> float:
    """The Gaussian's width (grid points) that smooths the walks' estimates (WALK_SMOOTH)."""
    if forward_orders(phase):
        return 0.0
    return WALK_SMOOTH * float(np.clip((abs(phase.mean_cosine()) - 0.5) / 0.35, 0.0, 1.0))


def smooth(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """(..., C) grid values averaged with a Gaussian of ``sigma`` grid points over the points of
    ``mask`` only (normalised by the mask's own average: the medium's edge blends in no zeros),
    0 off the mask."""
    if sigma <= 0:
        return np.where(mask[..., None], values, 0.0).astype(values.dtype)
    m = mask.astype(np.float64)
    weight = gaussian_filter(m, sigma, mode="constant")
    out = np.zeros_like(values)
    for i in range(values.shape[-1]):
        blurred = gaussian_filter(values[..., i] * m, sigma, mode="constant")
        out[..., i] = np.where(mask, blurred / np.maximum(weight, 1e-12), 0.0)
    return out


def g_texture(G, power: float = G_POWER) -> tuple:
    """The texture of a grid of G = albedo L' (nz, ny, nx, 3): G^power (G_POWER, or
    G_POWER_COARSE), trilinear; of one channel where the three are the same
    (tracing.colour_texture). Returns (texture, power), what :func:`g_at` reads."""
    p = np.float32(power)
    return colour_texture(np.asarray(G, np.float32), lambda g: np.maximum(g, 0.0) ** p), float(power)


def g_at(G_tex, pu, mask=True) -> mi.Color3f:
    """G read from :func:`g_texture`'s (texture, power) at unit-cube points pu."""
    texture, power = G_tex
    g = texture.eval(pu, mask)
    if power == 1.0:
        return mi.Color3f(*g)  # (one channel: broadcast)
    return mi.Color3f(*(dr.power(c, 1.0 / power) for c in g))


def gather_ms(
    medium, G_tex, points: np.ndarray, step: float, seed: int, sky: float = 0.0, env=None, sun=None
) -> np.ndarray:
    """(M, 3) L_ms at (M, 3) world points: MS_DIRECTIONS flights each, averaged (see bake_field);
    ``sky``: the radiance of a uniform sky that flights leaving the box see (0: none); ``env``:
    an environment map's emitter that they see instead (None: none), and that as many
    directions drawn from the map see too (tracing.envmap_nee: the two weighted by the power
    heuristic, so that a small bright spot in the map is found); ``sun``: (albedo E / 4pi, the
    texture of its tau_light (tracing.depth_texture), its power), a sun's direct light that G
    is without, added as albedo E / 4pi exp(-tau_light) where the march reads G (None: none)."""
    m, k = len(points), MS_DIRECTIONS
    # Spherical Fibonacci directions, the same set for every point, in a random frame per point
    i = np.arange(k) + 0.5
    z = 1.0 - 2.0 * i / k
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    fib = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1).astype(np.float32)
    rng = jit_rng(m, seed, dr.arange(mi.UInt64, m))
    frame = mi.Frame3f(mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32())))
    ray = dr.arange(mi.UInt32, m * k)
    point, j = ray // k, ray % k
    fr = dr.gather(mi.Frame3f, frame, point)
    w = dr.gather(mi.Vector3f, to_jit(mi.Vector3f, fib), j)
    d = fr.to_world(w)
    o = dr.gather(mi.Point3f, to_jit(mi.Point3f, points), point)
    L = _march_ms(medium, G_tex, o, d, step, sky, env, sun)
    if env is not None:  # and as many directions drawn from the map (multiple importance sampling)
        L += envmap_nee(medium, env, o, jit_rng(m * k, seed + 1, dr.arange(mi.UInt64, m * k)), mi.Bool(True))
    dr.eval(L)  # one kernel: read channel by channel, each would run the march again
    out = from_jit(L, np.float64)
    return out.reshape(m, k, 3).mean(axis=1).astype(np.float32)


@dr.syntax
def _march_ms(
    medium, G_tex, o: mi.Point3f, d: mi.Vector3f, step: float, sky: float, env, sun=None
) -> mi.Color3f:
    """int T_r sigma_t G dt along each ray to the box boundary (trapezoid in optical depth, as the
    field estimator marches; G with ``sun``'s direct light: :func:`gather_ms`), plus T_r to the
    boundary times ``sky`` or the environment map ``env`` seen along the ray; blocks without
    density are crossed in one step. A segment's end where sigma_t is 0, past the medium's edge,
    takes the other end's G: a flight reads nothing there, and the sun's light just outside a
    cloud is the unshadowed sky's (read as if the medium reached it, the bench sphere back-lit
    at albedo 0.8 read 1.048 of ``gather``, 1.026 now; docs/measurements.md)."""
    t, t_end = medium.box_interval(o, d)

    def at(t):
        x = o + t * d
        pu = medium.world_to_unit @ mi.Point3f(x)
        G = g_at(G_tex, pu)
        if sun is not None:
            G += sun[0] * dr.exp(-depth_at(sun[1], pu, True, sun[2]))
        return medium.sigma_t(x), G

    L = mi.Color3f(0.0)  # Gathered radiance
    Tr = mi.Float(1.0)  # Transmittance from the point
    s0, G0 = at(t)
    active = t < t_end
    while dr.hint(active, label="ms_gather"):
        # Steps of at most MS_MAX_DTAU optical depth at the block's majorant, between one and
        # MS_STRIDE voxels; empty blocks in one step
        sigma_maj, t_leave = medium.block(o, d, t, active)
        empty = sigma_maj <= 0.0
        dt = dr.clip(MS_MAX_DTAU / dr.maximum(sigma_maj, 1e-12), step, MS_STRIDE * step)
        dt = step_length(empty, t, t_leave, t_end, dt, 1e-3 * step)
        s1, G1 = at(t + dt)
        g0, g1 = dr.select(s0 > 0.0, G0, G1), dr.select(s1 > 0.0, G1, G0)  # (each where the medium is)
        seg_Tr, seg_G = exponential_segment(dr.select(empty, 0.0, 0.5 * (s0 + s1) * dt), g0, g1)
        L += Tr * seg_G
        Tr *= seg_Tr
        t += dt
        s0, G0 = s1, G1
        active &= (t < t_end) & (Tr > MS_TR_MIN)
    # What is left past the cut-off, at the last value seen (0 where the ray left the medium)
    L += dr.select(t < t_end, Tr, 0.0) * G0
    if dr.hint(sky > 0.0, mode="scalar"):  # the sky's component only
        L += dr.select(t < t_end, 0.0, Tr) * sky
    if dr.hint(env is not None, mode="scalar"):  # an environment map's, against its own samples
        seen = t >= t_end
        weight = power_heuristic(ISOTROPIC_PDF, envmap_pdf(env, o, d, seen))
        L += dr.select(seen, Tr, 0.0) * envmap_seen(env, d) * weight
    return L


#: The share of a point's walks kept where the medium is empty at the point itself (the grid's
#: points just outside a cloud, which the camera reads only in the cells at its edge), and where
#: it lies deeper than DEEP_TAU optical depths from the medium's box along each of the six axes
#: (a camera outside sees it through about exp(-DEEP_TAU)). At g = 0.85 (64^2, default, field at
#: 16 spp against gather at 1024 on one cache, binned relMAE, two bakes each of 9 rows) all
#: walks everywhere 5.10 % on average, half outside 5.13 %; a quarter outside read the sphere
#: side-lit 5.48 / 5.63 -> 6.31 / 5.99 %. A quarter deep: thick, the sphere and the dense cloud
#: within 0.2 points (docs/measurements.md, "The walks where the camera looks").
OUTSIDE_SHARE = 0.5
DEEP_SHARE = 0.25
DEEP_TAU = 3.0
_AXES = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))


def _walks_kept(medium, points: mi.Point3f, k: int, n: int, step: float) -> mi.Bool:
    """Which of the ``n`` walks (``k`` a point of ``points``, consecutive) run: all of a point
    inside the medium, OUTSIDE_SHARE of them at one where it is empty, DEEP_SHARE at one deep
    inside (the first ones of the point's)."""
    depth = optical_depth(medium, points, mi.Vector3f(*_AXES[0]), step)
    for axis in _AXES[1:]:
        depth = dr.minimum(depth, optical_depth(medium, points, mi.Vector3f(*axis), step))
    inside = medium.sigma_t(points) > 0.0
    share = dr.select(depth >= DEEP_TAU, DEEP_SHARE, dr.select(inside, 1.0, OUTSIDE_SHARE))
    limit = dr.maximum(mi.UInt32(dr.round(share * k)), 1)
    j = dr.arange(mi.UInt32, n)
    return j % k < dr.gather(mi.UInt32, limit, j // k)


def walk_ms(medium, G_tex, tau, points: np.ndarray, inputs: dict, seed: int) -> np.ndarray:
    """(M, 3 + len(SHAPE_DEGREES)) a sun's L_ms at (M, 3) world points in an anisotropic
    medium: what reaches each point after its first scattering, as a function of the camera
    ray's direction d, projected on orthogonal functions B_i of direction (phase.shape_basis, in
    the light's frame) and convolved with the phase (Funk-Hecke: degree l scales by g_l,
    phase.phase_legendre):

        L_ms(x, d) = int p(w . d) L(x, w) dw  ~  c_0(x) + sum_i c_i(x) B_i(d),
        c_i = W_i g_l(i) int B_i(w) L(x, w) dw / int B_i^2,

    W_i the term's weight (phase.SHAPE_WEIGHTS), with L(x, w) the radiance that a walk from x
    along w brings back (phase.phase_walk: the medium's next events exact, the graph's ``G``
    after them; x's own event is the camera's), less the sun's light still in its beam where
    ``inputs["forward"]`` orders of it are the camera march's, in closed form (FORWARD_ORDERS).
    ``inputs["walks"]`` walks a point (:func:`walks_per_point`; a share of them outside the
    medium and deep inside, :func:`_walks_kept`), their first directions half
    uniform and half from the phase about the light (one-sample mixture pdf). ``G_tex``:
    :func:`g_texture` of ``inputs["G"]``; ``tau``: the sun's tau_light texture
    (tracing.depth_texture of ``inputs["tau"]``). Returns c_0 (RGB) and the c_i at unit
    intensity (the channels' mean over the irradiance's), so that the scene's mix scales them."""
    m, k = len(points), int(inputs["walks"][0])
    lobes = tuple((float(w), float(g)) for w, g in np.asarray(inputs["lobes"], float))
    to_light = tuple(float(c) for c in inputs["to_light"])
    E = np.asarray(inputs["irradiance"], float)
    albedo = mi.Color3f(*(float(c) for c in inputs["albedo"]))
    n = m * k
    rng = jit_rng(n, seed, dr.arange(mi.UInt64, n))
    o = dr.gather(mi.Point3f, to_jit(mi.Point3f, points), dr.arange(mi.UInt32, n) // k)
    s = opaque(mi.Vector3f, to_light)  # (the light's direction and colour: a relight compiles nothing)
    uniform = rng.next_float32() < 0.5
    w = dr.select(uniform, uniform_sphere(rng), sample_phase(lobes, s, rng))
    pdf = 0.5 / (4.0 * dr.pi) + 0.5 * hg_phase(lobes, dr.dot(w, s))

    def tail(q, mask):
        return g_at(G_tex, medium.world_to_unit @ mi.Point3f(q), mask)

    def nothing(mask, w):  # a sun's component: nothing behind the medium
        return mi.Color3f(0.0)

    power = float(inputs["tau_power"][0])  # (tau: its texture, tracing.depth_texture)

    def sun_tr(i, p, mask):  # the bake's own light march, interpolated as the camera's march does
        return dr.exp(-depth_at(tau, medium.world_to_unit @ mi.Point3f(p), mask, power))

    suns = [(s, opaque(mi.Color3f, E))]
    bounces = int(inputs["bounces"][0])
    tail = tail if inputs["tail"][0] else None
    kept = _walks_kept(medium, to_jit(mi.Point3f, points), k, n, float(inputs["step"][0]))
    L = phase_walk(medium, lobes, suns, albedo, nothing, tail, o, w, rng, kept, bounces, sun_tr)
    orders = int(inputs["forward"][0])
    if orders > 0:  # the beam's part is the camera march's, in closed form (FORWARD_ORDERS)
        tau_o = depth_at(tau, medium.world_to_unit @ mi.Point3f(o), True, power)
        L -= suns[0][1] * forward_light(albedo, tau_o, beam_phases(lobes, orders, dr.dot(w, s), 0))
    weight = dr.select(kept, L / pdf, 0.0)
    dr.eval(weight, w)  # the walks once: each sum below reads them
    # Projected per point: the sums over a point's k consecutive walks
    frame = light_frame(to_light)
    local = [dr.dot(w, opaque(mi.Vector3f, e)) for e in frame]
    inv = opaque(mi.Color3f, np.where(E > 0, 1.0 / np.where(E > 0, E, 1.0), 0.0) / 3.0)
    unit = weight.x * inv[0] + weight.y * inv[1] + weight.z * inv[2]
    sums = [dr.block_sum(v, k) for v in (weight.x, weight.y, weight.z)]
    sums += [dr.block_sum(unit * b, k) for b in shape_basis(*local)]
    dr.eval(sums)
    taken = np.array(dr.block_sum(mi.Float(kept), k), np.float64)  # (walks a point)
    S = np.stack([np.array(v, np.float64) for v in sums], axis=1) / np.maximum(taken, 1)[:, None]
    degrees = np.array((0, 0, 0, *SHAPE_DEGREES))
    scale = phase_legendre(lobes, max(degrees))[degrees] / np.array((4 * np.pi,) * 3 + SHAPE_NORMS)
    scale *= np.array((1.0,) * 3 + SHAPE_WEIGHTS)  # (the series' terms each at its weight)
    return (S * scale[None, :]).astype(np.float32)
