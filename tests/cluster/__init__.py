"""The cluster (compose.yaml) end to end, in Docker."""
