"""The lists that the CLI, the HTTP API and the engine share: one source of truth for each.

Plain constants with no heavy imports, so that the API process can derive its enums from them
without loading Mitsuba or Dr.Jit.
"""

#: Integrators a scene can be rendered with: Mitsuba's volpath (ground truth) or the graph cache.
INTEGRATORS = ("volpath", "graph")

#: Camera-stage estimators of the graph integrator (see ``cloudgraph/integrators/graph.py``).
ESTIMATORS = ("gather", "free_flight", "march", "field")

#: The estimators that render an anisotropic phase function (docs/method.md, "Anisotropic
#: scattering"): ``free_flight`` and ``march`` read the graph's radiance where the camera's ray
#: scatters, which holds single scattering isotropically, so they take the isotropic phase only.
PHASE_ESTIMATORS = ("gather", "field")

#: The largest optical depth across one voxel at a medium's densest point (density_scale x the
#: densest value x the voxel's size; scene.voxel_depth_problem): delta tracking takes steps in
#: proportion to the optical depth it crosses, and past this a render or a precompute runs for
#: hours where it should refuse (the HTTP API's default too).
MAX_VOXEL_TAU = 100.0

#: Graph quality presets (see ``cloudgraph.graph.PRESETS``).
QUALITIES = ("draft", "compact", "default", "high")
