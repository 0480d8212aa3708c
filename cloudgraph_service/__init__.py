"""What the API (server/) and the workers (worker/) share, and nothing else: the settings and the
queue protocol (Redis keys, job functions, meta fields, file names, time limits).

Light on purpose: it imports neither the renderer nor FastAPI, so both sides can use it.
"""
