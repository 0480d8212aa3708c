"""The graph integrator (thesis §4.6, Eq. 4.24-4.25), registered with Mitsuba as ``graph``.

    L(p, w) = int T_r(p, p') sigma_s(p') L'_search(p') dt                       (Eq. 4.24)
    L'_search(p') = sum_a w_a L'(a) / sum_a w_a,  w_a = 1 / |p' - x_a|^2,
                    over the nodes a whose search range R_a holds p'             (Eq. 4.25)

The camera-stage estimator of Eq. 4.24 is a replaceable part (``estimator``):

| estimator     | what it does                                                              |
|---------------|---------------------------------------------------------------------------|
| ``gather``      | default: p' by delta tracking, single scattering at p' exact (ratio      |
|                 | tracking to the light), then one free flight to p'', the light there     |
|                 | exact too, and L'_search(p'') of the rest                                |
| ``free_flight`` | the thesis's: sample p' by delta tracking, weight albedo(p') L'_search(p') |
| ``march``       | jittered ray march: sum T_r sigma_s L'_search dt along the ray (less noise) |
| ``field``       | deterministic march of the baked radiance field (``cloudgraph/field.py``): |
|                 | single scattering exact to the grid, the rest from the graph, no noise   |

Looking L' up where the camera's collision falls biases thick media upwards: node centres sit
deeper than the camera's first collision, and radiance grows with depth below a free surface
(§4.7). ``gather`` moves the lookup one flight further and computes what escapes on the way
exactly, as final gathering does for photon maps; its node radiance must then cover one
scattering event fewer (``radiance_gather`` in the cache). At that second event p'' it takes the
suns' direct light exactly too (ratio tracking), and the graph's node radiance without it.

Plugin parameters (set through :meth:`GraphIntegrator.set_cache`, not the scene dict):

| name      | type   | default       | meaning                                  |
|-----------|--------|---------------|------------------------------------------|
| estimator | string | ``gather``      | the camera-stage estimator above         |
| step      | float  | node radius / 2 | ``march`` step, world units (``field``: half a field voxel) |
| phase     | PhaseSpec | isotropic   | the medium's phase function (below)      |
| bounces   | int    | phase_bounces | ``gather``'s exact scattering events with an anisotropic phase |

Anisotropic phase functions (Henyey-Greenstein, one or two lobes; docs/method.md, "Anisotropic
scattering"): what the graph holds stays isotropic (the similarity-scaled medium's,
precompute.py), so the estimators take the phase exactly where it matters most. ``gather``
follows the path from the camera through its first :func:`phase_bounces` scattering events as
volpath does (next-event estimation weighted by the phase, directions sampled from it) before
the graph takes over; ``field`` multiplies single scattering by 4pi p(to_light . d), constant
along a ray for a directional light. ``free_flight`` and ``march`` take the isotropic phase
only (options.PHASE_ESTIMATORS).

Node radiance is gathered through a uniform grid of node lists that lives in Dr.Jit, so the
whole camera stage is one kernel; per-frame values come from the sensor, and nothing is
recompiled when only the camera moves. The ``field`` estimator needs no node grid at all: one
sample per pixel is a converged image (more only antialias), and empty space is skipped block by
block with the field's majorant grid.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..edges import spread_lanes
from ..errors import SceneError
from ..field_textures import FieldTextures
from ..mitsuba_scene import envmap_emitter
from ..options import ESTIMATORS, PHASE_ESTIMATORS
from ..phase import beam_phases, forward_light, hg_phase, phase_bounces, phase_walk
from ..spatial import NodeGrid
from ..tracing import (
    ISOTROPIC_PDF,
    DensityField,
    colour_at,
    depth_at,
    envmap_nee,
    envmap_pdf,
    envmap_seen,
    exponential_segment,
    jit_rng,
    power_heuristic,
    ratio_tracking,
    sample_collision,
    single_segment,
    step_length,
    to_jit,
    uniform_sphere,
)

#: The field march stops where the transmittance from the camera falls below this.
FIELD_TR_MIN = 1e-3
#: Midpoints of the field march's integral of sigma_t to the box where the light enters it
#: (_tau_light; the page's shader takes as many).
FIELD_EDGE_SAMPLES = 3


# ------------------------------------------------------------------ integrator


class GraphIntegrator(mi.SamplingIntegrator):
    """Renders from a radiance cache; see the module docstring."""

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.estimator = props.get("estimator", "gather")
        self.medium = self.grid = self.field = None

    def set_cache(
        self,
        medium: DensityField,
        albedo,
        lights,
        estimator: str = "gather",
        grid: NodeGrid | None = None,
        field: FieldTextures | None = None,
        node_radius: float = 1.0,
        step: float | None = None,
        phase=None,
        max_depth: int = -1,
        bounces: int | None = None,
    ) -> None:
        """Hands the integrator its medium, its lights (a :class:`~cloudgraph.lights.Lights`:
        directional lights and a uniform sky), the phase function (a
        :class:`~cloudgraph.scene.PhaseSpec`; None: isotropic), and a node grid (Monte Carlo
        estimators) or a baked field (``field``), each holding the lights' radiance mixed.

        ``gather`` with an anisotropic phase takes ``bounces`` scattering events exactly
        (default :func:`phase_bounces`) before the graph's radiance (which must then hold every
        later event: ``max_depth`` -1); with a bounded ``max_depth`` it takes every event
        exactly, as volpath does, and reads no graph.

        Raises:
            SceneError: an anisotropic phase with an estimator that cannot render it.
        """
        if estimator not in ESTIMATORS:
            raise ValueError(f"unknown estimator {estimator!r}; choose one of {', '.join(ESTIMATORS)}")
        # The lobes ((weight, g), ...) of an anisotropic phase, None for the isotropic one (whose
        # kernels stay as they were)
        self.lobes = None if phase is None or phase.isotropic else phase.lobes()
        if self.lobes is not None and estimator not in PHASE_ESTIMATORS:
            raise SceneError(
                f"estimator {estimator!r} renders the isotropic phase only; medium.phase is "
                f"{phase.type!r}: use {' or '.join(PHASE_ESTIMATORS)}"
            )
        self.bounces = int(bounces) if bounces else phase_bounces(phase)
        self.tail = max_depth < 0  # whether the graph takes over after the exact events
        self.sun_at_p2 = max_depth < 0 or max_depth >= 2  # gather: the suns' light at p'' exact
        if not self.tail:
            self.bounces = max(int(max_depth), 0)
        if (field is None) == (estimator == "field"):
            raise ValueError("the field estimator takes a field, the others a node grid")
        self.medium, self.grid, self.field, self.estimator = medium, grid, field, estimator
        self.albedo = tuple(float(a) for a in albedo)
        # Per directional light: toward it, in world units and in the unit cube (per world unit)
        self.to_light = [tuple(-float(c) for c in d) for d in lights.directions]
        self.light_unit = [
            tuple(float(c[0]) for c in medium.world_to_unit @ mi.Vector3f(*t)) for t in self.to_light
        ]
        self.has_sky = bool(lights.sky)
        self.envs = [envmap_emitter(path) for path in lights.envmaps]  # Mitsuba's envmap emitters
        self.set_intensities(lights)
        self.eps2 = (0.05 * node_radius) ** 2  # keeps w_a finite at a node's centre
        self.step = float(step) if step else 0.5 * node_radius

    def set_intensities(self, lights) -> None:
        """The lights' intensities (the same lights as :meth:`set_cache`'s, new intensities or
        colours), opaque: a new mix compiles nothing."""
        self.irradiance = [
            dr.opaque(mi.Color3f, tuple(e)) for e in lights.intensity[: len(lights.directions)]
        ]
        self.sky = dr.opaque(mi.Color3f, tuple(lights.sky_radiance))
        self.env_scale = [dr.opaque(mi.Color3f, tuple(e)) for e in lights.envmap_scale]

    def _background(self, seen: mi.Bool, d: mi.Vector3f, p=None) -> mi.Color3f:
        """What a ray of direction d sees where ``seen`` (rays that leave the medium): the sky's
        radiance and the environment maps'; 0 elsewhere, and without them. ``p``: the ray is an
        isotropic flight from there, and each map's radiance takes its multiple importance
        sampling weight against the map's own sampling (tracing.envmap_nee)."""
        L = mi.Color3f(0.0)
        if self.has_sky:  # (Python-level switches: no sky or map, no term in the kernel)
            L += self.sky
        for env, scale in zip(self.envs, self.env_scale, strict=True):
            seen_env = scale * envmap_seen(env, d)
            if p is not None:
                seen_env *= power_heuristic(ISOTROPIC_PDF, envmap_pdf(env, p, d, seen))
            L += seen_env
        if not self.has_sky and not self.envs:
            return L
        return dr.select(seen, L, 0.0)

    def field_at_film(self, sensor, positions: np.ndarray, seed: int, lanes: int) -> np.ndarray:
        """(n, 3) the ``field`` estimator's radiance along the sensor's rays through n film
        positions ((n, 2) in [0, 1]², edges.strata_positions): render.py's edge refinement.
        The kernel is launched on ``lanes`` >= n rays, the rest idle: Dr.Jit's kernels here
        hash their width, so a fixed width per image size (and the positions and the seed as
        inputs that compile once, tracing.py) compiles one kernel whatever the camera; the n
        rays are dealt out over the width (edges.spread_lanes)."""
        n = len(positions)
        lane = spread_lanes(n, lanes)
        padded = np.full((lanes, 2), -1.0, np.float32)  # (x < 0: an idle lane)
        padded[lane] = positions
        pos = to_jit(mi.Point2f, padded)
        ray, _ = sensor.sample_ray(0.0, 0.5, dr.maximum(pos, 0.0), mi.Point2f(0.5))
        rng = jit_rng(lanes, seed, 0)
        L = self._field(mi.Point3f(ray.o), mi.Vector3f(ray.d), rng, pos.x >= 0.0)
        return np.array(L, dtype=np.float32).reshape(3, lanes).T[lane]

    def sample(self, scene, sampler, ray, medium=None, active=True):
        n = dr.width(ray.o)
        seed = mi.UInt64(mi.UInt32(sampler.next_1d() * 4294967295.0))
        rng = mi.PCG32(n, initstate=seed, initseq=dr.arange(mi.UInt64, n))
        o, d = mi.Point3f(ray.o), mi.Vector3f(ray.d)
        L = getattr(self, "_" + self.estimator)(o, d, rng, mi.Bool(active))
        return mi.Spectrum(L), mi.Bool(active), []

    def _gather(self, o, d, rng, active):
        # Final gather: sample p' by delta tracking; at p', single scattering exactly (next-event
        # estimation by ratio tracking to the light, Eq. 4.22 at a point) plus one more free
        # flight to p'', where the graph's L' stands in for everything after (Eq. 4.25).
        # An anisotropic phase has its own walk (_gather_phase)
        if self.lobes is not None:  # (a Python-level switch: never in a kernel)
            return self._gather_phase(o, d, rng, active)
        # Several lights: one ratio-tracking estimate per directional light; a sky is seen where
        # the flight to p'' leaves the medium (its single scattering, weight p / pdf = 1) and
        # behind it where the camera's ray does; an environment map both there and by a
        # direction drawn from the map, the two weighted by the power heuristic
        t, collided = sample_collision(self.medium, o, d, rng, active)
        p = mi.Point3f(o + t * d)
        L_ss = self._sun_light(p, rng, collided)
        for env, scale in zip(self.envs, self.env_scale, strict=True):  # maps: their own samples too
            L_ss += scale * envmap_nee(self.medium, env, p, rng, collided)
        w = uniform_sphere(rng)
        t2, collided2 = sample_collision(self.medium, p, w, rng, collided)
        p2 = mi.Point3f(p + t2 * w)
        # at p'' the suns' direct light is exact too (the graph's node radiance is without it:
        # precompute.without_sun), the rest from the graph
        L_p2 = self.grid.lookup(p2, self.eps2, collided2)
        if self.sun_at_p2:  # (a Python-level switch: max_depth 1 has no second event)
            L_p2 += self._sun_light(p2, rng, collided2)
        L_in = L_ss + dr.select(collided2, mi.Color3f(*self.albedo) * L_p2, self._background(collided, w, p))
        return dr.select(collided, mi.Color3f(*self.albedo) * L_in, self._background(active, d))

    def _sun_light(self, p, rng, active) -> mi.Color3f:
        # The directional lights' in-scattered radiance at p: ratio tracking to each, unrolled
        L = mi.Color3f(0.0)
        for to_light, E in zip(self.to_light, self.irradiance, strict=True):
            L += ratio_tracking(self.medium, p, mi.Vector3f(*to_light), rng, active) * E / (4.0 * dr.pi)
        return L

    def _gather_phase(self, o, d, rng, active):
        # gather with an anisotropic phase: the first ``bounces`` scattering events exactly
        # (phase.phase_walk), then albedo L'_search of the similarity-scaled graph. The graph is
        # isotropic: its error is in where light goes next, which the phase remembers for
        # log(PHASE_MEMORY) / log|g_eff| events, so those are taken exactly, and at least
        # GATHER_MIN_BOUNCES (phase_bounces): the scaled graph reads low on thin clouds.
        # A sky: seen behind the medium, and where a flight leaves it (weight p / pdf = 1).
        albedo = mi.Color3f(*self.albedo)
        tail = (lambda q, m: albedo * self.grid.lookup(q, self.eps2, m)) if self.tail else None
        suns = list(zip(self.to_light, self.irradiance, strict=True))
        return phase_walk(
            self.medium, self.lobes, suns, albedo, self._background, tail, o, d, rng, active, self.bounces
        )

    def _light_phase(self, k: int, d: mi.Vector3f) -> mi.Color3f:
        """E p: directional light k's irradiance times the phase of its light scattered into -d,
        1/4pi isotropic, else p(mu) with mu = to_light . d (1 where the camera looks into the
        light: forward scattering)."""
        E = self.irradiance[k]
        if self.lobes is None:
            return E / (4.0 * dr.pi)
        return E * hg_phase(self.lobes, dr.dot(mi.Vector3f(*self.to_light[k]), d))

    def _free_flight(self, o, d, rng, active):
        # Sample p' with pdf sigma_t T_r; the estimate of Eq. 4.24 is albedo L'_search(p')
        t, collided = sample_collision(self.medium, o, d, rng, active)
        L = self.grid.lookup(o + t * d, self.eps2, collided)
        return dr.select(collided, mi.Color3f(*self.albedo) * L, self._background(active, d))

    @dr.syntax
    def _march(self, o, d, rng, active):
        t, t_end = self.medium.box_interval(o, d)
        u = rng.next_float32()  # one jitter per ray, shared by its segments
        L = mi.Color3f(0.0)  # Radiance accumulator
        Tr = mi.Float(1.0)  # Transmittance from the camera
        active = active & (t < t_end)
        while dr.hint(active, label="march"):
            dt = dr.minimum(self.step, t_end - t)
            p = o + (t + u * dt) * d
            sigma_t = self.medium.sigma_t(p)
            # Eq. 4.24 over one segment with sigma_t and L' held at the sample point:
            # int T_r sigma_s L' dt = T_r(t) (1 - exp(-sigma_t dt)) albedo L'
            seg_Tr = dr.exp(-sigma_t * dt)
            L_node = self.grid.lookup(p, self.eps2, active & (sigma_t > 0))
            L += Tr * (1.0 - seg_Tr) * mi.Color3f(*self.albedo) * L_node
            Tr *= seg_Tr
            t += dt
            active &= (t < t_end) & (Tr > 1e-4)
        return L + Tr * self._background(mi.Bool(True), d)

    def _field_at(self, p, active, views):
        """(sigma_t, [tau_light per directional light], L_ms) at world points p (field.py);
        ``views``: per directional light, E and its beam's phase powers at the ray's direction
        (:meth:`_views`) where the field keeps how its L_ms depends on the view (its sum toward
        the camera: :meth:`FieldTextures.look_from`), else None."""
        f = self.field
        pu = self.medium.world_to_unit @ mi.Point3f(p)
        taus = [self._tau_light(k, pu, active) for k in range(len(self.to_light))]
        L_ms = mi.Color3f(0.0)
        if f.ms is not None:  # the sky's and the maps'
            L_ms += colour_at(f.ms, pu, active)
        power, limit = f.ms_light
        for k, tex in enumerate(f.sun_ms):  # each sun's, times its light factor (unrolled)
            sun = colour_at(tex, pu, active) * (self.irradiance[k] if f.unit else 1.0)
            if any(power):
                sun *= dr.exp(-dr.minimum(mi.Color3f(*power) * taus[k], limit))
            L_ms += sun
        for k, view in enumerate(views):  # the suns, unrolled
            if view is not None:
                terms = f.view_sum[k].eval(pu, active)[0]
                if f.shape_power[k]:  # (kept over the sun's light factor, of grey power)
                    terms = terms * dr.exp(-dr.minimum(f.shape_power[k] * taus[k], limit))
                L_ms += view[0] * terms
                if view[1]:  # the sun's light still in its beam, in closed form (field_ms.py)
                    L_ms += view[0] * forward_light(mi.Color3f(*self.albedo), taus[k], view[1])
        if any(view is not None for view in views):  # (the series can ring below 0)
            L_ms = dr.maximum(L_ms, 0.0)
        sigma_t = self.medium.texture.eval(pu, active)[0] * self.medium.scale
        return sigma_t, taus, L_ms

    def _views(self, d):
        """Per directional light: (E, the phase's powers of its beam's light at to_light . d
        (phase.beam_phases; [] where the field has none)), constant along a ray, where the field
        holds the light's ``ms_shape`` (else None)."""
        return [
            None
            if frame is None
            else (E, beam_phases(self.lobes, self.field.forward, dr.dot(mi.Vector3f(*to_light), d), 1))
            for frame, E, to_light in zip(self.field.frame, self.irradiance, self.to_light, strict=True)
        ]

    @dr.syntax
    def _tau_light(self, k, pu, active):
        """Optical depth from points pu (in the unit cube) to directional light k: the grid's
        tau_light, or within the field's ``edge`` of where the light enters the medium box the
        integral of sigma_t itself (FIELD_EDGE_SAMPLES midpoints): the grid's values are at
        texel centres, and half a voxel in from the box's faces its texture clamps. A point on
        the box's surface (a camera ray's entry) counts as inside."""
        lu = mi.Vector3f(*self.light_unit[k])
        pc = dr.clip(pu, 0.0, 1.0)
        # (the light never leaves through the faces it runs parallel to)
        te = dr.select(dr.abs(lu) < 1e-9, 1e30, dr.maximum(-pc / lu, (1.0 - pc) / lu))
        t_exit = dr.maximum(dr.minimum(dr.minimum(te.x, te.y), te.z), 0.0)  # world units
        edge = t_exit <= self.field.edge
        near = active & edge
        tau = mi.Float(0.0)  # Optical depth to the box's face
        # A symbolic branch: on the CPU a packet of lanes none of which is near the face skips
        # the quadrature (masked lookups alone cost as much as live ones: smoke1 under two suns,
        # 64² at 16 spp, spent a quarter of its frame here)
        if near:
            for j in range(FIELD_EDGE_SAMPLES):  # a fixed quadrature, unrolled into the kernel
                q = pc + ((j + 0.5) / FIELD_EDGE_SAMPLES) * t_exit * lu
                tau += self.medium.texture.eval(q, near)[0]
        grid = depth_at(self.field.tau[k], pu, active & ~edge, self.field.tau_power)
        return dr.select(edge, tau * self.medium.scale * t_exit / FIELD_EDGE_SAMPLES, grid)

    @dr.syntax
    def _field(self, o, d, rng, active):
        # Eq. 4.24 through the baked field, segment by segment in closed form (an exponential
        # integrator), with sigma_t the mean of its end values over a segment:
        #   int_seg T_r sigma_s L_in dt = T_r(t) albedo int_0^dtau e^-x L_in(x) dx,
        #   L_in = E p exp(-tau_light) + L_ms,  p = 1/4pi, or the phase at (to_light . d).
        # Single scattering with tau_light linear in optical depth between the segment's ends
        # (single_segment: exact in a homogeneous medium, where exp(-tau_light) changes many
        # times over in one step of a dense cloud), L_ms linear (tracing.exponential_segment).
        # Each step evaluates one new end point; one jitter per ray shifts the step grid against
        # banding.
        f = self.field
        t, t_end = self.medium.box_interval(o, d)
        albedo = mi.Color3f(*self.albedo)
        # E p per directional light: constant along the ray
        E = [self._light_phase(k, d) for k in range(len(self.to_light))]
        first = (1.0 - rng.next_float32()) * f.step  # one jitter per ray: the first segment's length
        L = mi.Color3f(0.0)  # Radiance accumulator
        Tr = mi.Float(1.0)  # Transmittance from the camera
        active = active & (t < t_end)
        t = dr.select(active, t, 0.0)  # rays that miss may have no finite entry point
        views = self._views(d)
        sigma0, taus0, ms0 = self._field_at(o + t * d, active, views)  # values at the segment's start
        steps = mi.UInt32(0)  # Iteration cap: a ray takes each step and skips each block once
        started = mi.Bool(False)  # Whether the ray has reached a block with medium (and jittered)
        while dr.hint(active, label="field_march"):
            # Empty-space skipping: a block without density is crossed in one step
            sigma_maj, t_leave = self.medium.block(o, d, t, active)
            empty = sigma_maj <= 0.0
            # the jitter applies where the medium begins; in optically thick blocks steps of at
            # most max_dtau at the block's majorant
            step = dr.minimum(f.step, f.max_dtau / dr.maximum(sigma_maj, 1e-12))
            jittered = dr.select(started, step, first * step / f.step)
            dt = step_length(empty, t, t_leave, t_end, jittered, 1e-3 * f.step)
            sigma1, taus1, ms1 = self._field_at(o + (t + dt) * d, active, views)
            # One segment (nothing to add across an empty block)
            dtau = dr.select(empty, 0.0, 0.5 * (sigma0 + sigma1) * dt)
            seg_Tr, seg_ms = exponential_segment(dtau, ms0, ms1)
            seg_ss = mi.Color3f(0.0)
            for k in range(len(E)):  # the directional lights, unrolled
                seg_ss += E[k] * single_segment(dtau, taus0[k], taus1[k])
            L += Tr * albedo * (seg_ss + seg_ms)
            Tr *= seg_Tr
            t += dt
            sigma0, taus0, ms0 = sigma1, taus1, ms1
            steps += 1
            started |= ~empty
            active &= (t < t_end) & (Tr > FIELD_TR_MIN) & (steps < f.max_steps)
        return L + Tr * self._background(mi.Bool(True), d)

    def aov_names(self):
        return []

    def to_string(self):
        return f"GraphIntegrator[estimator={self.estimator}]"


mi.register_integrator("graph", lambda props: GraphIntegrator(props))
