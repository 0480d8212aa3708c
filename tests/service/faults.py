"""Helpers of the fault tests: the service as `make run` starts it (bin/run-service), its
processes found by what they run, a job held still at a stage of its own choosing, and the
checks that nothing leaked.

A fault is set up so that it lands where it is meant to: the worker process is paused (SIGSTOP)
as soon as its job reports the stage asked for (Redis tells the test of every write to the
job's hash), the fault is done, and the worker goes on (SIGCONT) or is gone.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from redis import Redis
from rq.job import Job

from ..harness import ROOT, TERMINAL, free_port, wait_until

PRECOMPUTE_STAGES = ("trace", "reinforce", "graph", "lighting", "transport", "field")


def _children() -> dict[int, list[int]]:
    """Every process's children (from /proc)."""
    out: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        out.setdefault(ppid, []).append(int(d))
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def descendants(pid: int) -> list[int]:
    tree, out, todo = _children(), [], [pid]
    while todo:
        for c in tree.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


@dataclass
class Launched:
    """``bin/run-service`` on free ports, its data (and TMPDIR) in ``data_dir``."""

    data_dir: Path
    settings: dict = field(default_factory=dict)
    proc: subprocess.Popen | None = None
    port: int = 0
    redis_port: int = 0

    def start(self, timeout: float = 90) -> Launched:
        self.port, self.redis_port = free_port(), free_port()
        (self.data_dir / "tmp").mkdir(parents=True, exist_ok=True)
        env = {
            **{k: v for k, v in os.environ.items() if not k.startswith("CLOUDGRAPH_")},
            "CLOUDGRAPH_DATA_DIR": str(self.data_dir),
            "PORT": str(self.port),
            "REDIS_PORT": str(self.redis_port),
            "WORKERS": "1",
            "TMPDIR": str(self.data_dir / "tmp"),  # the service's own temporary files: checked too
            "PYTHONUNBUFFERED": "1",
            **{f"CLOUDGRAPH_{k}": str(v) for k, v in self.settings.items()},
        }
        self.log = open(self.data_dir / "service.log", "ab")  # noqa: SIM115 (closed in stop())
        self.proc = subprocess.Popen(  # a session of its own, as a terminal's job is
            [str(ROOT / "bin" / "run-service")],
            cwd=ROOT,
            env=env,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            # Ctrl-C reaches it as it reaches a terminal's job, even where this run ignores
            # SIGINT (started in the background of a script): bash cannot trap a signal that
            # was ignored when it started
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        self.wait_ready(timeout)
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def client(self, **kw) -> httpx.Client:
        return httpx.Client(base_url=self.url, **{"timeout": 30, **kw})

    def redis(self) -> Redis:
        return Redis(port=self.redis_port, socket_timeout=5)

    def log_text(self) -> str:
        return (self.data_dir / "service.log").read_text(errors="replace")

    # ------------------------------------------------------------------------ processes
    def pids(self) -> dict[str, int]:
        """The pid of each part: redis, api, supervisor, worker (the supervisor's worker
        process); a part that is not running is missing."""
        out = {}
        for pid in descendants(self.proc.pid):
            cmd = _cmdline(pid)
            if cmd.startswith("redis-server"):
                out["redis"] = pid
            elif "uvicorn" in cmd and "server.main:create_app" in cmd:
                out["api"] = pid
            elif cmd.endswith("-m worker "):
                out["supervisor"] = pid
                for c in _children().get(pid, []):
                    if "multiprocessing.spawn" in _cmdline(c):
                        out["worker"] = c
        return out

    def dump_stacks(self) -> None:
        """The supervisor and its worker process write every thread's stack to the log
        (SIGUSR1: worker/process.py, worker/__main__.py)."""
        for part, pid in self.pids().items():
            if part in ("supervisor", "worker"):
                os.kill(pid, signal.SIGUSR1)
        time.sleep(0.5)

    def wait_ready(self, timeout: float = 60) -> float:
        """Until Redis, the API and a live worker answer; returns the monotonic time."""

        def ready():
            try:
                r = httpx.get(f"{self.url}/readyz", timeout=2)
            except httpx.HTTPError:
                return False
            return r.status_code == 200 and "worker" in self.pids()

        wait_until(ready, timeout, "the service did not become ready", interval=0.05)
        return time.monotonic()

    def stop(self, sig: int = signal.SIGTERM, group: bool = False, timeout: float = 30) -> float:
        """Stops the launcher with ``sig``, sent to its process group when ``group`` (as a
        terminal sends Ctrl-C's SIGINT); every process it started ends. Returns seconds taken."""
        if self.proc is None or self.proc.poll() is not None:
            return 0.0
        parts = [self.proc.pid, *descendants(self.proc.pid)]
        t0 = time.monotonic()
        if group:
            os.killpg(self.proc.pid, sig)
        else:
            self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout)
            wait_until(lambda: not [p for p in parts if _running(p)], 5, "processes outlived the launcher")
        finally:
            left = [p for p in parts if _running(p)]
            for p in left:
                os.kill(p, signal.SIGKILL)
            self.log.close()
        assert not left, f"still running after the launcher ended: {[_cmdline(p) for p in left]}"
        return time.monotonic() - t0


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie has ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


# -------------------------------------------------------------------- a job held at a stage
def watch_jobs(redis: Redis) -> None:
    """Redis tells of every change to a hash (the job's meta is one), from now on."""
    redis.config_set("notify-keyspace-events", "Kh")


def hold_at_stage(svc: Launched, submit, stages, timeout: float = 60) -> tuple[str, str, int]:
    """Submits a job with its worker process paused, lets it run, and pauses the worker again
    (SIGSTOP) as soon as the job reports one of ``stages``.

    Args:
        submit: () -> job id; called while the worker is paused.

    Returns:
        (job id, the stage it is held at, the paused worker process's pid).
    """
    redis = svc.redis()
    watch_jobs(redis)
    pid = svc.pids()["worker"]
    os.kill(pid, signal.SIGSTOP)
    try:
        job_id = submit()
        pubsub = redis.pubsub(ignore_subscribe_messages=True)
        pubsub.subscribe(f"__keyspace@0__:rq:job:{job_id}")
        job = Job.fetch(job_id, connection=redis)
    except BaseException:
        os.kill(pid, signal.SIGCONT)
        raise
    os.kill(pid, signal.SIGCONT)
    end = time.monotonic() + timeout
    try:
        while time.monotonic() < end:
            if pubsub.get_message(timeout=0.5) is None:
                continue
            stage = job.get_meta(refresh=True).get("stage")
            if stage in stages:
                os.kill(pid, signal.SIGSTOP)
                now = job.get_meta(refresh=True).get("stage")
                assert job.get_status() == "started", job.get_status()
                return job_id, now, pid
            status = job.get_status()  # (a render's "done" may be its cache's, found)
            assert status not in ("finished", "failed", "stopped", "canceled"), (job_id, status, stage)
    finally:
        pubsub.close()
    raise TimeoutError(f"job {job_id} did not reach {stages} in {timeout} s")


def wait_status(
    client, job_id: str, timeout: float, statuses=TERMINAL, svc: Launched | None = None
) -> tuple[dict, float]:
    """(the job once its status is one of ``statuses``, the monotonic time it was seen);
    requests that fail meanwhile (the API or Redis away) are tried again. A job that does not
    end has the stacks of ``svc``'s supervisor and worker process written to its log."""

    def ended():
        try:
            r = client.get(f"/v1/jobs/{job_id}")
        except httpx.HTTPError:
            return None
        if r.status_code != 200:
            return None
        return r.json() if r.json()["status"] in statuses else None

    try:
        job = wait_until(ended, timeout, f"job {job_id} did not end in {timeout} s", interval=0.05)
    except TimeoutError as err:
        if svc is None:
            raise
        svc.dump_stacks()
        raise TimeoutError(f"{err}; the stacks of its worker are in {svc.data_dir / 'service.log'}") from None
    return job, time.monotonic()


# --------------------------------------------------------------------------------- leaks
def assert_no_leaks(svc: Launched) -> None:
    """No temporary file or folder under the data folder (nor in the service's TMPDIR) and no
    key of the service in Redis without an expiry (``cloudgraph:run:*`` included)."""
    leftover = []
    for p in svc.data_dir.rglob("*"):
        rel = p.relative_to(svc.data_dir)
        if rel.parts[0] == "redis" or rel == Path("service.log") or rel == Path("tmp"):
            continue
        if rel.parts[0] == "tmp" or p.name.endswith(".tmp") or p.name.startswith(".") or "runs" in rel.parts:
            leftover.append(str(rel))
    assert not leftover, f"temporary files left: {leftover}"
    redis = svc.redis()
    forever = [k.decode() for k in redis.scan_iter("cloudgraph:*") if redis.ttl(k) < 0]
    assert not forever, f"keys without an expiry: {forever}"


def cache_files(svc: Launched, keys: dict) -> dict[str, Path]:
    root = svc.data_dir / "cache"
    return {
        "graph": root / "graphs" / f"{keys['graph_key']}.npz",
        "radiance": root / "radiance" / f"{keys['radiance_key']}.npz",
        "field": root / "fields" / f"{keys['radiance_key']}.cgf.gz",
    }
