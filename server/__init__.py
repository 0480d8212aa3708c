"""cloudgraph's HTTP API (FastAPI). Routes validate and enqueue; workers call the engine."""
