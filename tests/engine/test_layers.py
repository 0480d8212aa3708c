"""The engine is layered one way: every import inside ``cloudgraph/`` points down a layer.

The layers, from the bottom (docs/method.md's order of the method, then its entry points): a
module may import only modules of lower layers, so no import goes up and none closes a circle.
Imports inside functions count like any other.
"""

from __future__ import annotations

import ast
from pathlib import Path

ENGINE = Path(__file__).resolve().parents[2] / "cloudgraph"

LAYERS: list[set[str]] = [
    # foundations: errors, shared lists, atomic writes, the package (format version), the heap
    {"cloudgraph", "integrators", "errors", "options", "files", "chunks", "graph", "transport", "heap"},
    # the scene spec, images, their metrics and edges, the VDB header, the graph file's format
    {"vdb", "scene", "image", "metrics", "edges", "graph_file", "light_depth"},
    {"volume", "sunsky"},  # volumes; a sunsky light's sun and sky map (from Mitsuba's model)
    # walks of the medium, Mitsuba scenes, parameters, the volume store, test volumes, lights
    {"tracing", "mitsuba_scene", "params", "store", "procedural", "lights"},
    # nodes, direct light, the spatial index, the field's file, cache keys and store, phase walks
    {"nodes", "lighting", "spatial", "field_file", "field_grid", "cache", "phase"},
    # the field's multiple scattering, from the graph; its light march; its textures for a march
    {"field_ms", "light_march", "field_textures"},
    # the graph build, the field bake, the integrator plugin (reads caches only)
    {"build", "field", "integrators.graph"},
    {"stages"},  # stage name -> chunk function
    {"precompute"},
    {"render"},  # GraphRenderer, render_graph, render_volpath
    {"cli"},
]


def _module(path: Path) -> str:
    """The engine module of a file: ``build``, ``integrators.graph``; the package is ``cloudgraph``."""
    parts = [p for p in path.relative_to(ENGINE).with_suffix("").parts if p != "__init__"]
    return ".".join(parts) or "cloudgraph"


def _is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (ENGINE / rel.with_suffix(".py")).is_file() or (ENGINE / rel / "__init__.py").is_file()


def _layer(module: str) -> int:
    for i, layer in enumerate(LAYERS):
        if module in layer:
            return i
    raise AssertionError(f"engine module {module!r} is in no layer of this test: place it")


def _engine_imports(path: Path) -> set[str]:
    """The engine modules that a file imports, anywhere in it (inside functions too)."""
    here = _module(path)
    parts = [] if here == "cloudgraph" else here.split(".")
    package = parts if path.name == "__init__.py" else parts[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(
                a.name.removeprefix("cloudgraph").lstrip(".") or "cloudgraph"
                for a in node.names
                if a.name.split(".")[0] == "cloudgraph"
            )
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                module = ".".join([*base, *([node.module] if node.module else [])])
            elif (node.module or "").split(".")[0] == "cloudgraph":
                module = node.module.removeprefix("cloudgraph").lstrip(".")
            else:
                continue
            # ``from .pkg import mod`` imports the module pkg.mod
            subs = [f"{module}.{a.name}".lstrip(".") for a in node.names]
            found.update([m for m in subs if _is_module(m)] or [module or "cloudgraph"])
    return found


def test_every_engine_import_points_down_a_layer():
    files = sorted(ENGINE.rglob("*.py"))
    assert len(files) > 20
    upward = []
    for path in files:
        module = _module(path)
        for target in _engine_imports(path):
            if _layer(target) >= _layer(module):
                upward.append(f"cloudgraph/{module.replace('.', '/')}.py imports {target}")
    assert not upward, "imports that do not point down a layer:\n" + "\n".join(upward)


def test_every_engine_module_has_a_layer():
    for path in ENGINE.rglob("*.py"):
        _layer(_module(path))
