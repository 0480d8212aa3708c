"""Shared fixtures: the Mitsuba variant (set once, as an entry point does) and the real data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("CLOUDGRAPH_TEST_DATA", ROOT.parent / "shared" / "data"))
if not DATA.is_dir():  # a checkout that carries shared/ inside it
    DATA = ROOT / "shared" / "data"


@pytest.fixture(scope="session")
def variant() -> str:
    from cloudgraph.mitsuba_scene import set_variant

    return set_variant()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not (DATA / "smoke1.vdb").is_file():
        pytest.fail(f"real test volumes not found in {DATA} (set CLOUDGRAPH_TEST_DATA)")
    return DATA
