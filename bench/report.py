"""The bench's tables and the machine they ran on."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path


def fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def row_md(row: dict, columns: list[str]) -> str:
    return "| " + " | ".join(fmt(row.get(c)) for c in columns) + " |"


def table(rows: list[dict], columns: list[str]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "\n".join(row_md(r, columns) for r in rows) + "\n"


def machine() -> dict:
    import mitsuba as mi

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_GB": round(mem, 1),
        "system": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "variant": mi.variant(),
        "mitsuba": mi.__version__,
    }


CONVERGED_COLUMNS = [
    "scene",
    "camera",
    "albedo",
    "nodes",
    "graph_MB",
    "gather_mean_ratio",
    "gather_binned_relMAE_pct",
    "field_mean_ratio",
    "field_binned_relMAE_pct",
    "ref_spp",
    "ref_binned_noise_pct",
]


COLUMNS = [
    "scene",
    "camera",
    "albedo",
    "precompute_s",
    "relight_s",
    "nodes",
    "edges",
    "cache_MB",
    "build_s",
    "lighting_s",
    "transport_s",
    "peak_rss_MB",
    "graph_frame_s",
    "MAE",
    "MAE_pct_of_mean",
    "mean_ratio",
    "ref_noise_pct",
    "MPE",
    "MNE",
    "relMSE",
    "volpath_equal_error_s",
    "speedup",
    "break_even_frames",
    "converged_binned_relMAE",
    "converged_mean_ratio",
]


#: The field estimator's table.
FIELD_COLUMNS = [
    "scene",
    "camera",
    "albedo",
    "field_s",
    "field_MB",
    "field_frame_64_s",
    "field_frame_256_s",
    "volpath_1spp_256_s",
    "field_vs_volpath_1spp",
    "field_aa_frame_64_s",
    "field_MAE_pct",
    "field_binned_relMAE",
    "field_mean_ratio",
    "field_volpath_equal_error_s",
    "field_speedup",
]


def markdown(result: dict) -> str:
    m = result["machine"]
    head = (
        f"# cloudgraph bench ({'quick' if result['quick'] else 'full'})\n\n"
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['memory_GB']} GB, {m['system']}; "
        f"variant {m['variant']}; quality {result['quality']}; reference volpath "
        f"{result['reference_spp']} spp, RR off.\n\n"
    )
    field = "\n## field estimator\n\n" + table(result["rows"], FIELD_COLUMNS)
    return head + table(result["rows"], COLUMNS) + field


def write_results(out_dir: Path, mode: str, result: dict, text: str) -> None:
    """``bench-<mode>-<date>-<time>`` as .json (``result``) and .md (``text``) under ``out_dir``,
    and ``text`` printed."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"bench-{mode}-{time.strftime('%Y%m%d-%H%M%S')}"
    (out_dir / f"{stem}.json").write_text(json.dumps(result, indent=2))
    (out_dir / f"{stem}.md").write_text(text)
    print(text)


def add_accuracy_args(p, scenes=None) -> None:
    """The options the accuracy benches (phase.py, lights.py) share."""
    p.add_argument("--scenes", nargs="*", default=scenes)
    p.add_argument("--albedo", nargs="*", type=float, default=[1.0, 0.8])
    p.add_argument("--ref-spp", type=int, default=4096)
    p.add_argument("--gather-spp", type=int, default=1024)
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--quality", default="default")
    p.add_argument("--out", default="bench/results")


def write_accuracy_rows(
    stem: Path, title: str, reference: str, legend: str, rows, columns, settings: dict
) -> None:
    """An accuracy bench's rows so far (phase.py, lights.py): ``stem``.json (the machine,
    ``settings``: quality, size, gather_spp, ref_spp; the rows) and ``stem``.md (``title``, the
    machine and settings with ``reference``, what volpath renders with, ``legend`` and the
    table), written again after each row, so that a cut run keeps what it measured."""
    m = machine()
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps({"machine": m, **settings, "rows": rows}, indent=2))
    size = settings["size"]
    about = (
        f"Machine: {m['cpu']}, {m['cores']} cores; variant {m['variant']}; quality {settings['quality']}; "
        f"{size}x{size}; gather {settings['gather_spp']} spp, field 16 spp; reference volpath with "
        f"{reference}, {settings['ref_spp']} spp, RR off. {legend}"
    )
    stem.with_suffix(".md").write_text(f"# {title}\n\n{about}\n\n" + table(rows, columns))
