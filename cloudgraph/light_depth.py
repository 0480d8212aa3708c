"""The field's single-scattering grid: optical depth to the light, fitted so that trilinear
interpolation between grid points reads it right where the medium changes fast.

At grid points the light march (light_march.py) gives tau_light exactly. Between them the field
interpolates it trilinearly, and where a voxel's optical depth changes fast tau_light bends
within the voxel: it grows faster than linearly where the density ramps up toward the light, so
interpolating exact point values reads it too high there, and the field's single scattering
too low (a dense cloud lit from the side read 5 % dark, the rim of a back-lit sphere 8 %).
Where a voxel's optical depth changes by THICK or more from a neighbour's, the march also
samples :data:`SUB_OFFSETS` points around each grid point, and the grid values are fitted to
all samples by weighted least squares, weighted by what each sample scatters toward a camera
(sigma_t T^2: a change of tau changes T by T). Elsewhere the grid keeps its exact values.

Between grid points the textures interpolate q = T^TAU_POWER = exp(-TAU_POWER tau), not tau:
where a cloud's shadow edge runs between grid points (the rim a back-lit camera sees: the light
grazes a thin fringe) tau rises steeply across the light, and interpolating tau there reads
the light far too low, interpolating T too high. The fit works in q too.

Where the grid allows (:func:`fine_shape`: at most MAX_FINE_POINTS tau texels over all suns),
tau_light is kept at twice the field's resolution instead (:func:`fine_depth`), unfitted: the
sub-voxel samples are the fine grid's points in optically thick voxels, exact, and elsewhere
the field's points are interpolated onto it. A back-lit camera sees the light graze a fringe
thinner than a voxel, and no fit of the field's grid reads it there: camera-weighted, the
fine grid halves the error per point (bench's thick cloud back-lit: mean |dT| 0.103 -> 0.042 of
the light seen). Interpolated as T^FINE_POWER, the light's mean is right (0.987-1.002 of the
exact march on the bench's dense and thick clouds, either view; T^0.3 reads it 0.975-0.994).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
from scipy.ndimage import maximum_filter, minimum_filter

#: Change of a voxel's optical depth across a grid step from which the grid is fitted to
#: sub-voxel samples (the back-lit bench sphere's rim, voxels of optical depth 0.44 stepping to
#: 0, reads 0.92 of the reference unfitted and 0.985 fitted).
THICK = 0.2
#: Sub-voxel samples around a grid point, in grid steps: the centres of its eight octants.
SUB_OFFSETS = np.array([[x, y, z] for z in (-0.25, 0.25) for y in (-0.25, 0.25) for x in (-0.25, 0.25)])
#: LSQR iterations of the fit (from the exact point values: a few sweeps take out most of the
#: interpolation's bias; measured on the dense bench cloud, more fit the samples closer and the
#: light seen by a camera no better).
ITERATIONS = 10
#: Optical depth where the light march stops: exp(-16) ~ 1e-7 of the light is left.
TAU_MAX = 16.0
#: The power of the transmittance the grid's textures interpolate (module docstring). Camera-
#: weighted single scattering against exact optical depth at 400 k points of the bench's dense
#: and thick clouds and its sphere, fitted: tau 0.981-0.988 side-lit and 0.946-0.972 back-lit;
#: T^0.3 0.981-0.990 and 0.984-0.986; T^0.2 and T^0.5 a little worse.
TAU_POWER = 0.3


#: The fine grid's power of the transmittance (module docstring).
FINE_POWER = 0.5
#: At most this many tau_light texels over all suns for the fine grid (2^24: a density grid of
#: 126 x 86 x 154, a sixteenth of the Disney cloud's, has 13.3 M with one sun).
MAX_FINE_POINTS = 1 << 24


def fine_shape(shape, suns: int) -> tuple | None:
    """(nz, ny, nx) of the fine tau grid of an (nz, ny, nx) field grid lit by ``suns``
    directional lights, or None where they would hold over MAX_FINE_POINTS texels."""
    fine = tuple(2 * int(n) for n in shape)
    return fine if suns * int(np.prod(fine)) <= MAX_FINE_POINTS else None


def depth_floor(power: float = TAU_POWER) -> float:
    """The least q = exp(-power tau) a grid holds: the light march stops at TAU_MAX."""
    return float(np.exp(-power * TAU_MAX))


def sub_centres(sigma_t: np.ndarray, voxel: float) -> np.ndarray:
    """(K, 3) grid coordinates (x, y, z; int) of the grid points of (nz, ny, nx) ``sigma_t``
    whose neighbourhood holds a voxel of optical depth THICK or more (``voxel``: the grid's
    step, world units): the sub-voxel samples sit around them (:func:`sub_coords`)."""
    od = sigma_t * voxel
    # where optical depth changes by THICK or more across a grid step: tau_light bends there
    # (inside a homogeneous block it is linear and the grid's values interpolate exactly)
    bends = maximum_filter(od, size=3, mode="constant") - minimum_filter(od, size=3, mode="constant")
    thick = maximum_filter(bends >= THICK, size=3, mode="constant")
    z, y, x = np.nonzero(thick)
    return np.stack([x, y, z], axis=1)


def sub_coords(centres: np.ndarray) -> np.ndarray:
    """(8K, 3) grid coordinates of the sub-voxel samples around (K, 3) ``centres``: each
    centre's :data:`SUB_OFFSETS` in turn."""
    return (centres[:, None, :] + SUB_OFFSETS[None, :, :]).reshape(-1, 3)


#: Trilinear weights of the sub-voxel samples around a centre along one axis (rows: the sample
#: 1/4 below the centre, 1/4 above) on the grid points there (columns: below, the centre, above):
#: a sample 1/4 below its centre reads the point below with 1/4 and the centre with 3/4. Over the
#: three axes (z, y, x; x fastest, as SUB_OFFSETS and the 27 neighbours are ordered) it is the
#: (8, 27) matrix _SAMPLE_WEIGHTS: each sample's weight on each of its centre's neighbours.
_AXIS_WEIGHTS = np.array([[0.25, 0.75, 0.0], [0.0, 0.75, 0.25]])
_SAMPLE_WEIGHTS = np.kron(_AXIS_WEIGHTS, np.kron(_AXIS_WEIGHTS, _AXIS_WEIGHTS))


def _neighbours(centres: np.ndarray, shape) -> np.ndarray:
    """Flat indices (K, 27) of the grid points around (K, 3) ``centres`` (x, y, z; offsets -1, 0,
    +1 per axis, z outermost and x fastest), clamped as the texture clamps."""
    nx, ny, _ = shape
    axes = []
    for a, n in enumerate(shape):
        c = centres[:, a].astype(np.int64)
        axes.append(np.stack([np.maximum(c - 1, 0), c, np.minimum(c + 1, n - 1)], axis=1))
    x, y, z = axes
    index = (z[:, :, None, None] * ny + y[:, None, :, None]) * nx + x[:, None, None, :]
    return index.reshape(-1, 27)


def fit_depth(
    tau: np.ndarray, sigma_t: np.ndarray, centres: np.ndarray, tau_samples: np.ndarray
) -> np.ndarray:
    """The grid values (nz, ny, nx) of optical depth whose interpolation (of q = T^TAU_POWER)
    best matches tau_light at the grid points (``tau``, exact) and at the sub-voxel samples
    around ``centres`` ((K, 3) grid coordinates; ``tau_samples`` (8K,) exact, in
    :func:`sub_coords`' order), by weighted least squares in q (module docstring; LSQR from the
    exact point values). Grid points no sample touches keep their value."""
    if not len(centres):
        return tau
    flat_tau, flat_sigma = tau.ravel().astype(np.float64), sigma_t.ravel().astype(np.float64)
    flat_q = np.exp(-TAU_POWER * flat_tau)
    q_samples = np.exp(-TAU_POWER * np.asarray(tau_samples, np.float64)).reshape(-1, 8)
    near = _neighbours(centres, tau.shape[::-1])  # (K, 27): every sample reads its centre's
    # The unknowns: the grid points the samples read (a mask: no sort of the samples' corners)
    touched = np.zeros(flat_tau.size, bool)
    touched[near.ravel()] = True
    free = np.flatnonzero(touched)
    column = (np.cumsum(touched) - 1)[near]  # (K, 27): each neighbour's unknown
    sigma_samples = flat_sigma[near] @ _SAMPLE_WEIGHTS.T  # (K, 8)
    # Each equation weighted as a change of tau is by what its point scatters, sigma_t T^2:
    # dq = -TAU_POWER q dtau, so sqrt(sigma_t) T / q (a constant factor left out)
    w_samples = np.sqrt(sigma_samples) * q_samples ** (1.0 / TAU_POWER - 1.0)
    w_points = np.sqrt(flat_sigma[free]) * flat_q[free] ** (1.0 / TAU_POWER - 1.0)
    m, k = w_samples.size, len(free)

    # A: the samples' rows (their 27 neighbours' unknowns by _SAMPLE_WEIGHTS), then the grid
    # points' own rows, each weighted; applied without being made (a third of the entries)
    def matvec(x):
        x = np.ravel(x)
        return np.concatenate([(w_samples * (x[column] @ _SAMPLE_WEIGHTS.T)).ravel(), w_points * x])

    def rmatvec(y):
        y = np.ravel(y)
        spread = (w_samples * y[:m].reshape(-1, 8)) @ _SAMPLE_WEIGHTS  # (K, 27)
        return np.bincount(column.ravel(), spread.ravel(), minlength=k) + w_points * y[m:]

    A = spla.LinearOperator((m + k, k), matvec=matvec, rmatvec=rmatvec, dtype=np.float64)
    b = np.concatenate([(w_samples * q_samples).ravel(), w_points * flat_q[free]])
    x0 = flat_q[free]
    dx = spla.lsqr(A, b - matvec(x0), atol=1e-6, btol=1e-6, iter_lim=ITERATIONS)[0]
    q = flat_q.copy()
    q[free] = np.clip(x0 + dx, depth_floor(), 1.0)
    return (-np.log(q) / TAU_POWER).reshape(tau.shape).astype(np.float32)


def fine_depth(tau: np.ndarray, near: np.ndarray, coords: np.ndarray, tau_samples: np.ndarray) -> np.ndarray:
    """tau_light (2nz, 2ny, 2nx) at twice the resolution of the field grid's ``tau`` (nz, ny,
    nx; exact at the grid points ``near``, (nz, ny, nx) bool, the rest unset): the sub-voxel
    samples (``coords`` (M, 3) grid coordinates, the fine grid's points by SUB_OFFSETS;
    ``tau_samples`` their exact values) where they are, elsewhere the field grid's q =
    T^FINE_POWER interpolated from the points ``near`` alone (points where none is near hold
    0). The fine grid's point 2i + (0, 1) sits at i -/+ 1/4 of the field grid's."""
    q = np.where(near, np.exp(-FINE_POWER * np.asarray(tau, np.float32)), np.float32(0.0))
    weight = near.astype(np.float32)  # (float32: the fine grid of a large field is 2^24 points)
    for axis in range(3):  # linear 2x on each axis: weights 3/4, 1/4 of the two nearest points
        q, weight = _doubled(q, axis), _doubled(weight, axis)
    fine = np.divide(q, weight, out=np.ones_like(q), where=weight > 0)
    del q, weight
    if len(coords):
        j = np.rint(2.0 * np.asarray(coords) + 0.5).astype(np.int64)
        fine[j[:, 2], j[:, 1], j[:, 0]] = np.exp(-FINE_POWER * np.asarray(tau_samples, np.float32))
    np.clip(fine, np.float32(depth_floor(FINE_POWER)), np.float32(1.0), out=fine)
    np.log(fine, out=fine)
    fine *= np.float32(-1.0 / FINE_POWER)
    return fine


def _doubled(a: np.ndarray, axis: int) -> np.ndarray:
    """``a`` at twice its resolution along ``axis``, linearly, clamped at the ends as a
    texture is: point 2i + (0, 1) at i -/+ 1/4."""
    a = np.moveaxis(a, axis, 0)
    lower = np.concatenate([a[:1], a[:-1]])  # a[i - 1], clamped
    upper = np.concatenate([a[1:], a[-1:]])  # a[i + 1]
    three = np.float32(0.75) * a
    out = np.stack([three + np.float32(0.25) * lower, three + np.float32(0.25) * upper], axis=1)
    return np.moveaxis(out.reshape(-1, *a.shape[1:]), 0, axis)
