"""cloudgraph's RQ workers: thin job functions over the engine, warm caches, heartbeats."""
