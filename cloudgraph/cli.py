"""The ``cloudgraph`` command line. Bad input exits with status 2 and one line on stderr.

Each subcommand imports what it needs when it runs: ``schema`` and ``info`` start without
loading Mitsuba or Dr.Jit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from .errors import CloudgraphError
from .heap import keep_freed_memory
from .options import ESTIMATORS, INTEGRATORS, QUALITIES


def _cmd_render(args: argparse.Namespace) -> None:
    from .image import write_exr, write_png
    from .mitsuba_scene import set_variant
    from .render import render_volpath
    from .scene import load_scene

    _writable(args.out, ".exr", "--out")  # fail before rendering, not after
    if args.png:
        _writable(args.png, ".png", "--png")
    if not -20.0 <= args.exposure <= 20.0:  # (NaN too)
        raise CloudgraphError(f"--exposure must be within -20..20 stops, got {args.exposure}")
    scene = load_scene(args.scene)
    if args.spp is not None:
        if not 1 <= args.spp <= 65536:
            raise CloudgraphError(f"--spp must be in 1..65536, got {args.spp}")
        scene = scene.model_copy(update={"render": scene.render.model_copy(update={"spp": args.spp})})
    volume = _checked_volume(scene)
    set_variant()
    t0 = time.perf_counter()
    if args.integrator == "volpath":
        image = render_volpath(scene, volume, rr=args.rr)
    else:
        from .render import render_graph

        image = render_graph(
            scene, volume, args.quality, _store(args), args.estimator, progress=_progress_bar()
        )
    seconds = time.perf_counter() - t0
    write_exr(image, args.out)
    if args.png:
        write_png(image, args.png, args.exposure)
    print(
        f"{args.integrator}: {scene.camera.width}x{scene.camera.height} at {scene.render.spp} spp "
        f"in {seconds:.2f} s -> {args.out}"
    )


def _writable(out: str, suffix: str, flag: str) -> None:
    """A file of ``suffix`` that can be written at ``out``: one already there is opened for
    appending (and left as it was), one that is not is made and removed again."""
    path = Path(out)
    if path.suffix.lower() != suffix:
        raise CloudgraphError(f"{flag} must name a {suffix} file, got {out!r}")
    if path.is_dir():
        raise CloudgraphError(f"{flag} {out} is a folder")
    folder = path.resolve().parent
    if not folder.is_dir():
        raise CloudgraphError(f"output folder does not exist: {folder}")
    if os.path.lexists(path):  # (an OSError names the file and why: main() prints it)
        with open(path, "ab"):  # (appends nothing: the file stays as it was)
            pass
        return
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))  # made here ...
    path.unlink()  # ... and removed: the render writes it


def _checked_volume(scene):
    """The scene's volume, refused where one voxel at its densest point is optically deeper
    than options.MAX_VOXEL_TAU (as the HTTP API refuses it): delta tracking takes as many steps
    as the optical depth it crosses, and would run for hours."""
    from .errors import SceneError
    from .options import MAX_VOXEL_TAU
    from .render import scene_volume
    from .scene import voxel_depth_problem

    volume = scene_volume(scene)
    densest = float(volume.density.max(initial=0.0))
    problem = voxel_depth_problem(scene.medium.density_scale, densest, max(volume.voxel_size), MAX_VOXEL_TAU)
    if problem:
        raise SceneError(f"medium.density_scale: {problem}")
    return volume


def _store(args: argparse.Namespace):
    from .cache import CacheStore

    if args.cache_dir and Path(args.cache_dir).exists() and not Path(args.cache_dir).is_dir():
        raise CloudgraphError(f"--cache-dir {args.cache_dir} is a file, not a folder")
    return CacheStore(args.cache_dir)


#: Whether a progress bar's line on stderr is still open (an error then starts a line of its own)
_BAR = {"open": False}


def _progress_bar():
    """A one-line progress bar on stderr: ``[#####.....] 50% lighting``."""

    def show(stage: str, fraction: float) -> None:
        n = int(round(30 * fraction))
        end = "\n" if fraction >= 1.0 else ""
        _BAR["open"] = not end
        print(
            f"\r[{'#' * n}{'.' * (30 - n)}] {100 * fraction:3.0f}% {stage:<10}",
            end=end,
            file=sys.stderr,
            flush=True,
        )

    return show


def _cmd_precompute(args: argparse.Namespace) -> None:
    from .mitsuba_scene import set_variant
    from .precompute import precompute
    from .scene import load_scene

    scene = load_scene(args.scene)
    volume = _checked_volume(scene)
    set_variant()
    if address := os.environ.get("CLOUDGRAPH_DASK_SCHEDULER"):  # its chunks on that Dask cluster
        from cloudgraph_service.dask_chunks import precompute_chunks

        with precompute_chunks(address) as chunks:
            cache = precompute(scene, volume, args.quality, _store(args), _progress_bar(), chunks)
    else:
        cache = precompute(scene, volume, args.quality, _store(args), _progress_bar())
    for k, v in cache.keys.items():
        print(f"{k}: {v}")
    s = cache.stats
    print(f"nodes {s['nodes']}  edges {s['edges']}  collisions {s['collisions']}  radius {s['radius']:.4g}")
    if not s["graph_reused"]:
        print(
            f"build {s['build_s']:.2f} s (trace {s['trace_s']:.2f}, group {s['group_s']:.2f}, "
            f"reinforce {s['reinforce_s']:.2f})"
        )
    if not s["radiance_reused"]:
        print(
            f"lighting {s['lighting_s']:.2f} s  transport {s['transport_s']:.2f} s "
            f"({s['transport_iterations']} products)"
        )
    print(
        f"bytes: graph {s['graph_bytes']}  radiance {s['radiance_bytes']}  "
        f"(graph {'reused' if s['graph_reused'] else 'built'}, "
        f"radiance {'reused' if s['radiance_reused'] else 'computed'})"
    )


def _cmd_bench(args: argparse.Namespace) -> None:
    from .mitsuba_scene import set_variant

    try:  # the harness lives beside the engine, in the checkout's bench/
        from bench.harness import run_bench, run_converged
        from bench.parts import run_parts
    except ImportError:
        raise CloudgraphError("cloudgraph bench runs from a source checkout (its bench/ folder)") from None

    set_variant()
    if args.parts:
        run_parts(scenes=args.scene, out_dir=args.out_dir, ref_spp=args.ref_spp, parts=args.part)
    elif args.converged:
        run_converged(scenes=args.scene, out_dir=args.out_dir)
    else:
        run_bench(quick=args.quick, scenes=args.scene, out_dir=args.out_dir)


def _cmd_info(args: argparse.Namespace) -> None:
    from .volume import volume_info

    info = volume_info(args.volume)
    if args.json:
        print(json.dumps(info, indent=2))
        return
    print(f"{info['path']}")
    for g in info["grids"]:
        print(f"  grid {g['name']!r}: {g['type']}")
    if info["grid"] is None:  # (several float grids, none named density: the boxes are the first's)
        first = next(g["name"] for g in info["grids"] if g["type"] in ("float", "half"))
        print(f"  density grid: none named (name one with volume.grid); the figures below are of {first!r}")
    else:
        print(f"  density grid: {info['grid']!r}")
    print(f"  active bbox (index): {info['index_bbox'][0]} .. {info['index_bbox'][1]}")
    lo, hi = info["world_bbox"]
    print(f"  medium bbox (world): {[round(v, 4) for v in lo]} .. {[round(v, 4) for v in hi]}")
    print(f"  voxel size: {[round(v, 6) for v in info['voxel_size']]}")
    print(
        f"  values: {info['value_range'][0]:.6g} .. {info['value_range'][1]:.6g}, "
        f"{100 * info['active_fraction']:.1f} % of the box non-zero"
    )


def _cmd_compare(args: argparse.Namespace) -> None:
    from .image import read_exr
    from .metrics import compare
    from .mitsuba_scene import set_variant

    set_variant()
    m = compare(read_exr(args.image), read_exr(args.reference))
    if args.json:
        print(json.dumps(m))
    else:
        print("  ".join(f"{k} {v:.6g}" for k, v in m.items()))


def _cmd_schema(args: argparse.Namespace) -> None:
    from .scene import json_schema

    print(json.dumps(json_schema(), indent=2))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cloudgraph", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a scene spec to EXR (and PNG)")
    r.add_argument("scene", help="scene spec v1 JSON file")
    r.add_argument("--integrator", choices=INTEGRATORS, default="volpath")
    r.add_argument("--out", required=True, help="output EXR (linear radiance)")
    r.add_argument("--png", help="also write an sRGB PNG here")
    r.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    r.add_argument("--spp", type=int, help="override render.spp")
    r.add_argument(
        "--quality",
        choices=QUALITIES,
        default="default",
        help="graph cache preset (graph integrator)",
    )
    r.add_argument(
        "--estimator",
        choices=ESTIMATORS,
        default="gather",
        help="graph: camera-stage estimator (free_flight is the thesis's; see integrators/graph.py)",
    )
    r.add_argument("--cache-dir", help="cache folder (default $CLOUDGRAPH_CACHE_DIR or ~/.cache/cloudgraph)")
    r.add_argument("--rr", action="store_true", help="volpath: keep Mitsuba's Russian roulette on")
    r.set_defaults(func=_cmd_render)

    pc = sub.add_parser("precompute", help="build (or find) the graph radiance cache of a scene")
    pc.add_argument("scene")
    pc.add_argument("--quality", choices=QUALITIES, default="default")
    pc.add_argument("--cache-dir", help="cache folder (default $CLOUDGRAPH_CACHE_DIR or ~/.cache/cloudgraph)")
    pc.set_defaults(func=_cmd_precompute)

    b = sub.add_parser("bench", help="graph vs volpath: speed and accuracy (docs/benchmark.md)")
    b.add_argument("--quick", action="store_true", help="a small subset, minutes on two cores")
    b.add_argument(
        "--converged",
        action="store_true",
        help="accuracy only: converged gather and field, 4096-spp references",
    )
    b.add_argument(
        "--parts",
        action="store_true",
        help="the field's error by part (single scattering, all orders) beside gather and volpath",
    )
    b.add_argument(
        "--ref-spp",
        type=int,
        default=4096,
        help="--parts: volpath reference samples (0: field against gather only)",
    )
    b.add_argument(
        "--part",
        action="append",
        choices=["single", "all"],
        help="--parts: only this part (repeatable; default both)",
    )
    b.add_argument(
        "--scene",
        action="append",
        help="only these scenes (repeatable; the held-out and thick ones are never default)",
    )
    b.add_argument("--out-dir", default="bench/results")
    b.set_defaults(func=_cmd_bench)

    i = sub.add_parser("info", help="describe a .vdb or .vol volume")
    i.add_argument("volume")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=_cmd_info)

    c = sub.add_parser("compare", help="errors of an image against a reference (Eq. 5.1)")
    c.add_argument("image")
    c.add_argument("reference")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=_cmd_compare)

    s = sub.add_parser("schema", help="print the JSON schema of scene spec v1")
    s.set_defaults(func=_cmd_schema)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    keep_freed_memory()  # (a precompute's arrays reuse each other's pages: heap.py)
    try:
        args.func(args)
    except CloudgraphError as err:
        _fail(f"cloudgraph: error: {err}")
        return 2
    except OSError as err:
        _fail(f"cloudgraph: error: {err.strerror or err}: {err.filename or ''}".rstrip(": "))
        return 2
    except KeyboardInterrupt:
        _fail("cloudgraph: interrupted")
        return 130
    return 0


def _fail(line: str) -> None:
    """One line on stderr, on a line of its own after an open progress bar."""
    print(("\n" if _BAR["open"] else "") + line, file=sys.stderr)
    _BAR["open"] = False


if __name__ == "__main__":
    sys.exit(main())
