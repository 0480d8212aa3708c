"""The ``field`` estimator's view of a radiance field (cloudgraph/field.py's file): its arrays as
Dr.Jit textures, and each sun's view terms summed toward the camera (docs/method.md, "The
radiance field"). The graph integrator marches them (integrators/graph.py)."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .field_grid import to_world, unit_points
from .phase import shape_basis
from .tracing import BLOCK, colour_texture, depth_texture, linear_texture, opaque, to_jit


@dataclass
class FieldTextures:
    """A :class:`~cloudgraph.field.RadianceField` in Dr.Jit for the ``field`` estimator.

    Attributes:
        tau: optical depth to each directional light, 1 channel each (a list, in the lights'
            order), as q = exp(-tau_power tau) (light_depth.py; tau itself where 0); sun_ms:
            per directional light its radiance after the first scattering (tracing.colour_texture:
            3 channels, or 1 where they are the same), over its
            light factor exp(-min(P tau_light, range)) (the header's ``ms_light``, ms_light's
            (P (3,), range); P 0 in a file of before it), at unit intensity where ``unit`` (a
            v1.1 field: the march multiplies the sun's irradiance in), else at its own; ms: the
            other components' (sky, maps) mixed (:meth:`mixed_ms`; None without); all
            trilinear, clamped, over the unit cube.
        shape: per directional light, how its L_ms depends on the view (an anisotropic phase;
            None without), as (the world points of its grid, a Point3f; their terms of
            phase.shape_basis, SHAPE_TERMS Floats; the grid's (nz, ny, nx)), over the light
            factor of grey power ``shape_power`` (its entry's ``light_power``; 0 in a file of
            before it); frame: the basis's frame (3, 3); view_sum: per such light, the terms'
            sum toward the camera, a one-channel texture (:meth:`look_from`).
        step: march step, world units; max_dtau: a step's optical depth at most (at its block's
            majorant); edge: within this of where the light enters the box, single scattering
            integrates sigma_t to it (world units; field.py's header, read by the page too).
        max_steps: iteration cap of the march: a ray takes each step and skips each block once.
    """

    tau: object
    tau_power: float
    sun_ms: tuple
    unit: bool
    ms_light: tuple
    ms: object
    shape: tuple
    shape_power: tuple
    frame: tuple
    step: float
    max_dtau: float
    edge: float
    max_steps: int
    forward: int = 0
    view_sum: tuple = ()

    @staticmethod
    def mixed_ms(field, lights) -> np.ndarray | None:
        """The radiance after the first scattering of a v1.1 field's components other than its
        directional lights (sky, maps), mixed by the scene's intensities (lights.py); None
        without any."""
        comps = field.meta.get("lights", ())
        rest = [c for c, e in enumerate(comps) if e["type"] != "directional"]
        if not rest:
            return None
        return sum(lights.mix[c].astype(np.float32) * field.array(comps[c]["ms"]) for c in rest)

    @classmethod
    def from_field(cls, field, lights) -> FieldTextures:
        step, max_dtau = float(field.meta["step"]), float(field.meta["max_dtau"])
        power = float(field.meta.get("tau_power", 0.0))  # (0: a file of before it, tau interpolated)
        suns = [c for c in field.meta["lights"] if "tau" in c] if "lights" in field.meta else None
        taus = [field.array(c["tau"]) for c in suns] if suns is not None else [field.tau_light]
        sun_ms = [field.array(c["ms"]) for c in suns] if suns is not None else [field.radiance_ms]
        shapes = [c.get("shape") for c in suns] if suns is not None else [field.meta.get("ms_shape")]
        u2w = np.asarray(field.meta["unit_to_world"], float)
        arrays = [field.array(sh["array"]) if sh else None for sh in shapes]
        views = [  # (in Dr.Jit: the points, and each term apart)
            None
            if a is None
            else (
                to_jit(mi.Point3f, to_world(u2w, unit_points(a.shape[2::-1]))),
                [to_jit(mi.Float, a[..., i].ravel()) for i in range(a.shape[-1])],
                a.shape[:3],
            )
            for a in arrays
        ]
        diag = float(np.linalg.norm(np.subtract(*field.meta["world_bbox"][::-1])))
        blocks = sum(-(-n // BLOCK) for n in field.sigma_t.shape)
        ml = field.meta.get("ms_light", {"power": (0.0, 0.0, 0.0), "range": 0.0})
        rest = cls.mixed_ms(field, lights)
        # the longest march: every segment at most max_dtau of the medium's majorant
        dense = float(field.majorant.max(initial=0.0)) * diag / max_dtau
        return cls(
            tau=tuple(depth_texture(t, power) for t in taus),
            tau_power=power,
            sun_ms=tuple(colour_texture(a) for a in sun_ms),
            unit=suns is not None,
            ms_light=(tuple(map(float, ml["power"])), float(ml["range"])),
            ms=None if rest is None else linear_texture(rest),
            shape=tuple(views),
            shape_power=tuple(float(sh.get("light_power", 0.0)) if sh else 0.0 for sh in shapes),
            frame=tuple(np.asarray(sh["frame"], float) if sh else None for sh in shapes),
            step=step,
            max_dtau=max_dtau,
            edge=float(field.meta["edge"]),
            max_steps=int(2 * (diag / step + dense + 3 * blocks) + 16),
            forward=int(field.meta.get("ms_forward", 0)),
        )

    def look_from(self, eye) -> None:
        """The view terms' sums toward a pinhole camera at ``eye`` (world): at each point x of a
        sun's view grid, sum_i c_i(x) B_i(d) with d = (x - eye) / |x - eye|, the direction of
        every camera ray through x, so that the march reads one channel where it read
        SHAPE_TERMS (between grid points the sum interpolates as the terms do, to the change of
        d across a texel). One small kernel per camera, the eye opaque: a new camera compiles
        nothing."""
        eye = opaque(mi.Point3f, eye)
        sums = []
        for view, frame, tex in zip(self.shape, self.frame, self.view_sum or self.shape, strict=True):
            if view is None:
                sums.append(None)
                continue
            points, terms, grid = view
            d = dr.normalize(points - eye)
            basis = shape_basis(*(dr.dot(mi.Vector3f(*map(float, e)), d) for e in frame))
            value = mi.TensorXf(sum(t * b for t, b in zip(terms, basis, strict=True)), (*grid, 1))
            if self.view_sum:  # (the same texture, new values)
                tex.set_tensor(value)
            else:
                tex = mi.Texture3f(value, filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Clamp)
            sums.append(tex)
        self.view_sum = tuple(sums)
