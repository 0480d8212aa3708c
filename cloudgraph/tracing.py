"""Walking the medium in Dr.Jit: the density field, free-flight sampling and ratio tracking.

Kept apart from what each stage does at the points it samples (pbrt's ``SampleT_maj`` split):
the graph build (§4.3), the direct lighting (§4.4) and the graph integrator (§4.6) all walk the
medium through this module, with the same density interpolation as Mitsuba's ``gridvolume``
(trilinear between voxel centres, clamped at the box) and the same box as ``volpath``.

A variant must be set before these functions are called.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import maximum_filter

from .light_depth import TAU_MAX, depth_floor
from .volume import Volume

#: Empty-space blocks, voxels a side.
BLOCK = 8


def linear_texture(values: np.ndarray):
    """A 3D texture over the unit cube from (nz, ny, nx[, channels]) values at texel centres:
    trilinear, clamped at the edges (as Mitsuba's ``gridvolume``)."""
    a = values if values.ndim == 4 else values[..., None]
    tensor = mi.TensorXf(to_jit(mi.Float, a.ravel()), a.shape)
    return mi.Texture3f(tensor, filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Clamp)


def new_scope() -> None:
    """Starts a new Dr.Jit scope on this thread: a thread that lives on between uses (a pool's)
    must, before it reads arrays that another thread made since (the builder's medium, a light's
    values), or Dr.Jit refuses to order the two (``jitc_assemble``)."""
    dr.detail.new_scope(dr.backend_v(mi.Float))


def opaque(kind, values):
    """A Dr.Jit vector or colour of ``values`` that kernels read as a parameter, not a literal:
    a kernel that differs only in it (a new light's direction or colour: a relight) compiles
    once."""
    return dr.opaque(kind, tuple(float(c) for c in np.ravel(values)))


def colour_texture(values: np.ndarray, transform=None):
    """:func:`linear_texture` of (nz, ny, nx, 3) RGB values (``transform``, elementwise, applied
    first), of one channel where the three are the same (a grey medium lit by white light: a
    third of the lookups, and of the transform's work; :func:`colour_at`)."""
    grey = all(np.array_equal(values[..., 0], values[..., c]) for c in (1, 2))
    values = np.ascontiguousarray(values[..., :1]) if grey else values
    return linear_texture(values if transform is None else transform(values))


def colour_at(texture, pu, active=True):
    """A :func:`colour_texture`'s Color3f at unit-cube points pu."""
    v = texture.eval(pu, active)
    return mi.Color3f(v[0]) if len(v) == 1 else mi.Color3f(v[0], v[1], v[2])


def depth_texture(tau: np.ndarray, power: float):
    """The texture of an optical-depth grid (nz, ny, nx; the field's or finer:
    light_depth.py): q = exp(-power tau), trilinear (power 0, a field file of before the
    header's ``tau_power``: tau itself)."""
    tau = np.asarray(tau, np.float64)
    return linear_texture((np.exp(-power * tau) if power else tau).astype(np.float32))


def depth_at(texture, pu, active, power: float):
    """Optical depth read from :func:`depth_texture` at unit-cube points pu (Dr.Jit)."""
    value = texture.eval(pu, active)[0]
    if not power:
        return value
    return -dr.log(dr.maximum(value, depth_floor(power))) / power


def block_majorant(grid: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(bz, by, bx) max of a (nz, ny, nx) grid over blocks of block^3 voxels, dilated by one voxel
    first, so that trilinear interpolation anywhere inside a block never exceeds it."""
    dilated = maximum_filter(grid, size=3, mode="nearest")
    d = np.pad(dilated, [(0, -s % block) for s in dilated.shape], mode="edge")
    bz, by, bx = (s // block for s in d.shape)
    return d.reshape(bz, block, by, block, bx, block).max(axis=(1, 3, 5))


@dataclass
class DensityField:
    """sigma_t(x) = scale * density(x) over the medium box, in Dr.Jit.

    Attributes:
        texture: density in the unit cube, cell-centred, trilinear, clamped (as ``gridvolume``).
        world_to_unit: affine map of world points to the unit cube; ray parameters are kept.
        scale: ``density_scale``, per world unit.
        majorant: max sigma_t over the medium, per world unit (0: nothing to track).
        blocks: max density over blocks of BLOCK^3 voxels (flat, x fastest), for skipping empty
            space; block_counts: blocks per axis (x, y, z); block_unit: a block's side in the
            unit cube, per axis; nudge: how far past a block's exit tracking resumes, world units
            (1e-5 of a block: negligible medium skipped).
        max_steps: iteration cap of a walk (null collisions and block crossings).
    """

    texture: object
    world_to_unit: object
    scale: float
    majorant: float
    blocks: object
    block_counts: tuple
    block_unit: tuple
    nudge: float
    max_steps: int

    @classmethod
    def from_volume(cls, volume: Volume, density_scale: float) -> DensityField:
        grid = np.ascontiguousarray(volume.density.transpose(2, 1, 0)[..., None], np.float32)
        texture = linear_texture(grid)
        world_to_unit = mi.Transform4f(np.linalg.inv(volume.unit_to_world).tolist())
        majorant = float(volume.density.max()) * float(density_scale)
        blocks = block_majorant(grid[..., 0])
        bz, by, bx = blocks.shape
        nz, ny, nx = grid.shape[:3]
        lo, hi = volume.world_bbox()
        expected = majorant * float(np.linalg.norm(hi - lo))
        return cls(
            texture,
            world_to_unit,
            float(density_scale),
            majorant,
            mi.Float(blocks.ravel()),
            (bx, by, bz),
            (BLOCK / nx, BLOCK / ny, BLOCK / nz),
            1e-5 * BLOCK * float(np.min(volume.voxel_size)),
            int(min(16 * expected + 4 * (bx + by + bz) + 1024, 2**31 - 1)),
        )

    def sigma_t(self, p: mi.Point3f) -> mi.Float:
        """Extinction at world points p, per world unit."""
        # mi.Point3f(...): o + t * d is typed as a vector, which a transform would not translate
        return self.texture.eval(self.world_to_unit @ mi.Point3f(p))[0] * self.scale

    def sigma_t_at(self, points: np.ndarray) -> np.ndarray:
        """(M,) float64 extinction at (M, 3) world points (numpy in and out)."""
        return np.array(self.sigma_t(to_jit(mi.Point3f, np.asarray(points, np.float32))), np.float64)

    def block(self, o: mi.Point3f, d: mi.Vector3f, t: mi.Float, active: mi.Bool) -> tuple[mi.Float, mi.Float]:
        """The block holding o + t d: its majorant (max sigma_t, 0 where empty space can be
        skipped) and the ray parameter where the ray leaves it (d need not be of unit length)."""
        ou = self.world_to_unit @ mi.Point3f(o)
        du = self.world_to_unit @ mi.Vector3f(d)
        pu = ou + t * du
        counts, side = mi.Vector3i(*self.block_counts), mi.Vector3f(*self.block_unit)
        b = dr.clip(mi.Vector3i(dr.floor(pu / side)), 0, counts - 1)
        rho = dr.gather(mi.Float, self.blocks, b.x + counts.x * (b.y + counts.y * b.z), active)
        lo = mi.Vector3f(b) * side
        # A ray parallel to an axis never leaves through that axis's faces
        moving = dr.abs(du) > 1e-12
        leave = dr.select(moving, dr.select(du > 0, lo + side - pu, lo - pu) * dr.rcp(du), dr.inf)
        return rho * self.scale, t + dr.minimum(dr.minimum(leave.x, leave.y), leave.z)

    def box_interval(self, o: mi.Point3f, d: mi.Vector3f) -> tuple[mi.Float, mi.Float]:
        """Ray parameters [t0, t1] inside the medium box (t0 >= 0; t0 >= t1 where the ray misses)."""
        ou = self.world_to_unit @ mi.Point3f(o)
        du = self.world_to_unit @ mi.Vector3f(d)
        inv = dr.rcp(du)
        a = (0.0 - ou) * inv
        b = (1.0 - ou) * inv
        lo, hi = dr.minimum(a, b), dr.maximum(a, b)
        t0 = dr.maximum(dr.maximum(dr.maximum(lo.x, lo.y), lo.z), 0.0)
        t1 = dr.minimum(dr.minimum(hi.x, hi.y), hi.z)
        return t0, t1


def majorant_step(
    field: DensityField, o: mi.Point3f, d: mi.Vector3f, t: mi.Float, t_end: mi.Float, rng: mi.PCG32
) -> tuple[mi.Float, mi.Float, mi.Bool, mi.Float]:
    """One step of tracking against the block majorants (pbrt-v4's majorant grid): a tentative
    collision at rate sigma_maj of the block holding o + t d, if it falls inside that block.

    Returns:
        (sigma_maj, t_c, inside, t_next): the block's majorant; the tentative collision t_c;
        whether it lies in the block (and before t_end); else t_next, where the next block
        begins (the exponential is memoryless, so tracking resumes there with a fresh sample).
    """
    sigma_maj, t_leave = field.block(o, d, t, mi.Bool(True))
    t_leave = dr.minimum(t_leave, t_end)
    u = rng.next_float32()
    t_c = t + dr.select(sigma_maj > 0, -dr.log(1.0 - u) / dr.maximum(sigma_maj, 1e-30), dr.inf)
    inside = t_c < t_leave
    # Past the block's exit by a hair, so that the next lookup finds the next block
    t_next = dr.maximum(t_leave + field.nudge, t * (1.0 + 2.0**-20))
    return sigma_maj, t_c, inside, t_next


@dr.syntax
def sample_collision(
    field: DensityField, o: mi.Point3f, d: mi.Vector3f, rng: mi.PCG32, active: mi.Bool
) -> tuple[mi.Float, mi.Bool]:
    """Free-flight sampling by delta tracking against the block majorants: the distance to the
    first real collision, with density sigma_t(x) T_r(o, x) along o + t d (d of unit length).
    Thin media take as many null collisions as their own density asks for, not the densest
    voxel's (a 35x difference on smoke1).

    Returns:
        (t, collided): collided is False where the ray leaves the medium first.
    """
    t, t_end = field.box_interval(o, d)
    active = mi.Bool(active) & (t < t_end) & (field.majorant > 0)
    collided = mi.Bool(False)
    steps = mi.UInt32(0)  # Iteration cap (field.max_steps)
    while dr.hint(active, label="delta_tracking"):
        # A tentative collision in this block, accepted with probability sigma_t / sigma_maj
        sigma_maj, t_c, inside, t_next = majorant_step(field, o, d, t, t_end, rng)
        real = inside & (rng.next_float32() * sigma_maj < field.sigma_t(o + t_c * d))
        collided |= active & real
        t = dr.select(inside, t_c, t_next)
        steps += 1
        active &= ~real & (t < t_end) & (steps < field.max_steps)
    return t, collided


@dr.syntax
def ratio_tracking(
    field: DensityField, o: mi.Point3f, d: mi.Vector3f, rng: mi.PCG32, active: mi.Bool
) -> mi.Float:
    """Transmittance from o along d to the box boundary, by ratio tracking against the block
    majorants (unbiased, in [0, 1])."""
    t, t_end = field.box_interval(o, d)
    Tr = mi.Float(1.0)  # Transmittance estimate
    active = mi.Bool(active) & (t < t_end) & (field.majorant > 0)
    steps = mi.UInt32(0)  # Iteration cap (field.max_steps)
    while dr.hint(active, label="ratio_tracking"):
        sigma_maj, t_c, inside, t_next = majorant_step(field, o, d, t, t_end, rng)
        Tr[active & inside] *= 1.0 - field.sigma_t(o + t_c * d) / sigma_maj
        t = dr.select(inside, t_c, t_next)
        steps += 1
        active &= (t < t_end) & (Tr > 1e-6) & (steps < field.max_steps)  # below 1e-6 the light is gone
    return Tr


def step_length(
    empty: mi.Bool, t: mi.Float, t_leave: mi.Float, t_end: mi.Float, step, overshoot: float
) -> mi.Float:
    """The next march step: ``step``, or where the block is empty (``DensityField.block``) across
    it to ``overshoot`` past its exit (a fixed length, so that a skip always moves on); never past
    t_end."""
    skip = dr.maximum(t_leave - t, 0.0) + overshoot
    return dr.minimum(dr.select(empty, skip, step), t_end - t)


def exponential_segment(dtau: mi.Float, v0, v1):
    """One segment of a march in closed form: its transmittance exp(-dtau), and
    int_0^dtau exp(-x) v(x) dx for v linear in optical depth from v0 to v1
    (= v0 (1 - e^-dtau) + (v1 - v0) (1 - e^-dtau (1 + dtau)) / dtau, exact for constant
    sigma_t and linear v)."""
    T = dr.exp(-dtau)
    w1 = dr.select(dtau > 1e-3, (1.0 - T * (1.0 + dtau)) / dr.maximum(dtau, 1e-3), 0.5 * dtau)
    return T, v0 * (1.0 - T) + (v1 - v0) * w1


def single_segment(dtau: mi.Float, tau0: mi.Float, tau1: mi.Float) -> mi.Float:
    """int_0^dtau exp(-x) exp(-tau(x)) dx for tau_light linear in optical depth x from tau0 to
    tau1 (exact in a homogeneous medium): with a = dtau + tau1 - tau0,
    = dtau (exp(-tau0) - exp(-tau1 - dtau)) / a, and dtau exp(-tau0) (1 - a / 2) as a -> 0."""
    a = dtau + tau1 - tau0
    small = dr.abs(a) < 1e-4
    ratio = (dr.exp(-tau0) - dr.exp(-tau1 - dtau)) / dr.select(small, 1.0, a)
    return dtau * dr.select(small, dr.exp(-tau0) * (1.0 - 0.5 * a), ratio)


def envmap_seen(emitter, d: mi.Vector3f) -> mi.Color3f:
    """The radiance an environment map (a Mitsuba emitter) sends along -d: what a ray of
    direction d that leaves the medium sees."""
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(d))
    si.wi = -d
    return mi.Color3f(emitter.eval(si))


#: The isotropic phase's (and a uniform direction's) density per steradian.
ISOTROPIC_PDF = 1.0 / (4.0 * np.pi)


def power_heuristic(pdf, other):
    """The power heuristic's weight of a sample drawn with ``pdf`` against one other strategy."""
    a, b = pdf * pdf, other * other
    return dr.select(a + b > 0, a / (a + b), 0.0)


def envmap_pdf(emitter, p: mi.Point3f, d: mi.Vector3f, active: mi.Bool) -> mi.Float:
    """The density (per steradian) with which an environment map's own sampling draws d at p."""
    it = dr.zeros(mi.Interaction3f, dr.width(d))
    it.p = p
    ds = dr.zeros(mi.DirectionSample3f, dr.width(d))
    ds.d = d
    return emitter.pdf_direction(it, ds, active)


def envmap_nee(medium, emitter, p: mi.Point3f, rng: mi.PCG32, active: mi.Bool) -> mi.Color3f:
    """An environment map's single scattering at p (isotropic phase) by one direction drawn
    from the map (Mitsuba's importance sampling) with ratio tracking toward it, weighted by the
    power heuristic against an isotropic direction that also sees the map where it leaves the
    medium (weighted by :func:`envmap_pdf`'s heuristic): a small bright spot, a sun in the map,
    is found by the map's samples, a wide glow by the isotropic ones."""
    it = dr.zeros(mi.Interaction3f, dr.width(p))
    it.p = p
    ds, weight = emitter.sample_direction(it, mi.Point2f(rng.next_float32(), rng.next_float32()), active)
    Tr = ratio_tracking(medium, p, ds.d, rng, active & (ds.pdf > 0))
    return mi.Color3f(weight) * Tr * (power_heuristic(ds.pdf, ISOTROPIC_PDF) * ISOTROPIC_PDF)


def uniform_sphere(rng: mi.PCG32) -> mi.Vector3f:
    """Isotropic directions."""
    return mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))


# ------------------------------------------------------------------ inputs that compile once
# Kernels are compiled for what their inputs look like: a Python number is a literal in them,
# and Dr.Jit's LLVM backend reads numpy memory where it lies and compiles for the alignment it
# finds. Chunks and renders that differ only in an offset, a seed or where numpy put an array
# would each compile a kernel of their own (0.1 s and more) without these two.


def jit_rng(size: int, initstate, initseq) -> mi.PCG32:
    """``size`` PCG32 streams, lane i adding i to both seeds; integer seeds are opaque."""

    def seed(v):
        return dr.opaque(mi.UInt64, v) if isinstance(v, int | np.integer) else v

    return mi.PCG32(size, initstate=seed(initstate), initseq=seed(initseq))


def towards_light(light_dir) -> np.ndarray:
    """(3,) unit vector towards a directional light that travels along ``light_dir``."""
    return -np.asarray(light_dir, float) / np.linalg.norm(light_dir)


def cpu_threads() -> int:
    """Threads for CPU work outside Dr.Jit (k-d tree queries): as many as Dr.Jit's pool has, so
    that a worker limited to n threads (WORKER_THREADS) uses n throughout."""
    return max(1, dr.thread_count())


def to_jit(cls, a: np.ndarray, dtype=np.float32):
    """numpy data as the Dr.Jit type ``cls``: (N,) for a flat type, (N, k) for a k-vector one,
    each column copied to 64-byte-aligned memory first."""
    a = np.asarray(a)
    if a.ndim == 1:
        return cls(_aligned(a, dtype))
    return cls(*(_aligned(a[:, i], dtype) for i in range(a.shape[1])))


def from_jit(v, dtype=np.float32) -> np.ndarray:
    """(N, 3) numpy array of a Dr.Jit 3-vector (the inverse of :func:`to_jit`); evaluate ``v``
    first, or each component runs its kernel again."""
    return np.stack([np.array(c, dtype) for c in (v.x, v.y, v.z)], axis=1)


def _aligned(a: np.ndarray, dtype) -> np.ndarray:
    buf = np.empty(a.size * np.dtype(dtype).itemsize + 64, np.uint8)
    start = -buf.ctypes.data % 64
    out = buf[start : start + a.size * np.dtype(dtype).itemsize].view(dtype)
    out[:] = a
    return out


# ------------------------------------------------------------------ walks of the graph build (§4.3)


def trace_light_paths(
    field: DensityField,
    directions: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    n_paths: int,
    max_collisions: int,
    seed: int,
    first: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Paths first .. first + n_paths - 1 from directional lights, free-flight sampled through the
    medium (Dr.Jit). Path i is the same whichever range it is traced in.

    Args:
        field: the medium's density field.
        directions: (K, 3) unit directions the light travels; path i uses directions[i % K].
        first: the index of the first path.
        bounds: world bounding box of the medium (lo, hi).

    Returns:
        positions: (n_paths, max_collisions, 3) float32 collision points (NaN where none).
        n_collisions: (n_paths,) int32 collisions per path; a path with fewer than
            max_collisions left the medium after its last one.
    """
    lo, hi = bounds
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2 * 1.001
    dirs = to_jit(mi.Vector3f, directions)
    path = dr.arange(mi.UInt32, n_paths) + dr.opaque(mi.UInt32, first)
    d = dr.gather(mi.Vector3f, dirs, path % len(directions))
    frame = mi.Frame3f(d)
    rng = jit_rng(n_paths, seed + first, first)  # lane i: first + i added to both
    # Origins uniform on a disk perpendicular to the light that covers the medium
    disk = mi.warp.square_to_uniform_disk_concentric(mi.Point2f(rng.next_float32(), rng.next_float32()))
    o = mi.Point3f(
        mi.Point3f(*(float(c) for c in centre))
        + radius * (disk.x * mi.Vector3f(frame.s) + disk.y * mi.Vector3f(frame.t) - d)
    )
    buf = dr.full(mi.Float, np.nan, n_paths * max_collisions * 3)
    n = _walk(field, o, d, rng, buf, max_collisions)
    dr.eval(buf, n)  # one kernel: read one by one, each output would run the walk again
    positions = np.array(buf, dtype=np.float32).reshape(n_paths, max_collisions, 3)
    return positions, np.array(n, dtype=np.int32)


@dr.syntax
def _walk(
    field: DensityField, o: mi.Point3f, d: mi.Vector3f, rng: mi.PCG32, buf: mi.Float, max_collisions: int
) -> mi.UInt32:
    """Random walks by free-flight sampling, writing each collision to buf[(path, k, xyz)]."""
    idx = dr.arange(mi.UInt32, dr.width(o))
    k = mi.UInt32(0)  # Collisions recorded on this path
    active = mi.Bool(True)
    while dr.hint(active, label="light_path"):
        t, collided = sample_collision(field, o, d, rng, active)
        o = dr.select(collided, o + t * d, o)
        slot = (idx * max_collisions + k) * 3
        dr.scatter(buf, o.x, slot, collided)
        dr.scatter(buf, o.y, slot + 1, collided)
        dr.scatter(buf, o.z, slot + 2, collided)
        k[collided] += 1
        d = dr.select(collided, uniform_sphere(rng), d)  # every collision continues: albedo comes later
        active &= collided & (k < max_collisions)
    return k


def trace_flights(
    field: DensityField, origins: np.ndarray, seed: int, first: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """One isotropic free flight from each origin: (collision points (M, 3), collided (M,)).
    Flight i (counted from ``first``) is the same whichever range it is traced in."""
    m = len(origins)
    rng = jit_rng(m, seed + first, first)  # lane i: first + i added to both
    o = to_jit(mi.Point3f, origins)
    d = uniform_sphere(rng)
    t, collided = sample_collision(field, o, d, rng, mi.Bool(True))
    p = o + t * d
    dr.eval(p, collided)  # one kernel: read one by one, each output would run the walk again
    return from_jit(p), np.array(collided, bool)


@dr.syntax
def optical_depth(medium, p: mi.Point3f, w: mi.Vector3f, step: float) -> mi.Float:
    """int_0^boundary sigma_t(p + s w) ds per point, midpoint rule, stopped at TAU_MAX; blocks
    without density are crossed in one step."""
    t, t_end = medium.box_interval(p, w)
    tau = mi.Float(0.0)  # Optical depth accumulator
    active = t < t_end
    while dr.hint(active, label="light_march"):
        sigma_maj, t_leave = medium.block(p, w, t, active)
        empty = sigma_maj <= 0.0
        dt = step_length(empty, t, t_leave, t_end, step, 1e-3 * step)
        tau += dr.select(empty, 0.0, medium.sigma_t(p + (t + 0.5 * dt) * w) * dt)
        t += dt
        active &= (t < t_end) & (tau < TAU_MAX)
    return dr.minimum(tau, TAU_MAX)
