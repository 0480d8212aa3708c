"""The lists that the CLI, the HTTP API and the engine share: one source of truth for each.

Plain constants with no heavy imports, so that the API process can derive its enums from them
without loading Mitsuba or Dr.Jit.
"""

#: Integrators a scene can be rendered with: Mitsuba's volpath (ground truth) or the graph cache.
INTEGRATORS = ("volpath", "graph")

#: Camera-stage estimators of the graph integrator (see ``cloudgraph/integrators/graph.py``).
ESTIMATORS = ("gather", "free_flight", "march", "field")

#: Graph quality presets (see ``cloudgraph.graph.PRESETS``).
QUALITIES = ("draft", "compact", "default", "high")
