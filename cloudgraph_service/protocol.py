"""The queue protocol: Redis keys, job functions, meta fields, file names and time limits that the
API and the workers both use, and the few queue operations that both sides perform.

Job meta fields (``job.meta``), written by the API when it enqueues and by the worker as it runs:

| field        | who     | meaning                                                          |
|--------------|---------|------------------------------------------------------------------|
| kind         | API     | precompute, render, frames or animation                          |
| stage        | both    | the stage the job reports (``queued`` until a worker takes it)   |
| fraction     | worker  | progress in [0, 1]                                               |
| result_url   | API     | where the result is fetched once finished                        |
| error        | both    | what went wrong, for people: no paths, class names or tracebacks |
| failed       | both    | it ended failed without running (what it waited on failed)       |
| canceled     | API     | a client cancelled it                                            |
| children     | API     | an animation's frame jobs                                        |
| out_dir      | API     | an animation's folder of frames                                  |
| frames       | API     | an animation's frame count                                       |

Job arguments cross the queue by name: each job function takes one keyword argument,
``payload`` (:data:`PAYLOAD`), the JSON of its payload model (:class:`PrecomputeJob`,
:class:`RenderJob`, :class:`FramesJob`, :class:`EncodeJob`), which names the function it is
for. The sender builds the model (:func:`enqueue_payload`); the job function
validates it again (:meth:`JobPayload.received`) before it does anything.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, ClassVar, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from redis import Redis
from rq import Queue
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job, JobStatus

from .errors import PayloadError

# ---------------------------------------------------------------------------- job functions
PRECOMPUTE_JOB = "worker.jobs.precompute_job"
RENDER_JOB = "worker.jobs.render_job"
FRAMES_JOB = "worker.jobs.frames_job"
ENCODE_JOB = "worker.jobs.encode_job"

# --------------------------------------------------------------------------------- payloads
#: The one keyword argument of every job function: its payload, as JSON.
PAYLOAD = "payload"
#: A scene spec v1 (cloudgraph.scene) with ``volume.id`` in place of a path, as JSON; the API
#: has validated it, the job function parses it again.
SceneJSON = dict[str, Any]
#: What a render job writes (RenderJob.format).
IMAGE_FORMATS = ("png", "exr")


class JobPayload(BaseModel):
    """The arguments of one job function, by name (the function is ``FUNC``). Quality, integrator
    and estimator names are the engine's (``cloudgraph.options``), checked by the API against
    those lists before it enqueues; here they are names, not a second copy of the lists."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    FUNC: ClassVar[str]

    def job_kwargs(self) -> dict[str, dict]:
        """The job function's keyword arguments: ``{PAYLOAD: <this payload as JSON>}``."""
        return {PAYLOAD: self.model_dump(mode="json")}

    @classmethod
    def received(cls, data: object) -> Self:
        """The payload as a job function takes it, validated on this side of the queue.

        Raises:
            PayloadError: a field missing, unknown or of the wrong type; the message names each.
        """
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            fields = "; ".join(
                f"{'.'.join(str(p) for p in e['loc']) or 'the payload'}: {e['msg']}" for e in err.errors()
            )
            raise PayloadError(f"{cls.FUNC} refused its payload: {fields}") from None


class PrecomputeJob(JobPayload):
    """Builds (or finds) the radiance cache of a scene (its camera is not used)."""

    FUNC: ClassVar[str] = PRECOMPUTE_JOB
    scene: SceneJSON
    quality: str


class RenderJob(JobPayload):
    """Renders one image of ``scene`` to ``out``.

    ``radiance_key`` is the scene's radiance cache key where the API already knows it (read from
    the finished precompute it found): a worker that holds that cache loaded renders at once,
    without working the keys out from the volume again. None: the worker computes it.
    """

    FUNC: ClassVar[str] = RENDER_JOB
    scene: SceneJSON
    integrator: str
    estimator: str
    quality: str
    format: Literal[IMAGE_FORMATS]
    exposure: float  # PNG exposure in stops
    out: str  # the image file (render_path)
    radiance_key: str | None = None


class FramesJob(JobPayload):
    """Renders frames ``first``, ``first + 1``, ... of an animation (``FRAME_FILE`` in
    ``out_dir``): ``scene`` seen from each of ``cameras`` in turn. The frames share everything
    but the camera, so one radiance cache (found by one key) serves them all; ``radiance_key``
    as in :class:`RenderJob`."""

    FUNC: ClassVar[str] = FRAMES_JOB
    scene: SceneJSON
    cameras: list[dict[str, Any]] = Field(min_length=1)  # camera specs (cloudgraph.scene)
    first: int = Field(ge=0)
    integrator: str
    estimator: str
    quality: str
    exposure: float
    out_dir: str  # animation_dir
    radiance_key: str | None = None


class EncodeJob(JobPayload):
    """Encodes an animation's ``frames`` frames in ``out_dir`` into ``VIDEO_FILE``."""

    FUNC: ClassVar[str] = ENCODE_JOB
    out_dir: str
    fps: float = Field(gt=0)
    frames: int = Field(ge=1)


def enqueue_payload(queue: Queue, payload: JobPayload, **options) -> Job:
    """Enqueues ``payload``'s job function with its payload by name; ``options`` are RQ's
    (``job_id``, ``depends_on``, ``job_timeout``, ``meta``, ...)."""
    return queue.enqueue(payload.FUNC, kwargs=payload.job_kwargs(), **options)


# ----------------------------------------------------------------------------- time limits
RESULT_TTL_S = 7 * 24 * 3600  # finished and failed jobs are kept this long
CANCEL_TTL_S = 24 * 3600  # a cancel flag outlives any job it can stop
HEARTBEAT_GRACE_S = 15  # a worker is alive while its heartbeat is younger than HEARTBEAT_S + this
KILL_GRACE_S = 5  # past its budget by this much, a job's worker process is killed
CANCEL_GRACE_S = 10  # a cancelled job still running this long after is stopped by force
LOCK_S = 30  # one request at a time per cache id

# ------------------------------------------------------------------------------ ids, files
#: Job ids the service makes (``cache-``, ``render-``, ``anim-`` + hex) and RQ's own (uuid4).
JOB_ID = re.compile(r"[A-Za-z0-9_-]{1,100}")
FRAME_FILE = "frame_{:05d}.png"
FRAME_GLOB = "frame_*.png"
FRAME_FFMPEG = "frame_%05d.png"  # FRAME_FILE as ffmpeg reads a numbered sequence
VIDEO_FILE = "video.mp4"


def is_job_id(text: str) -> bool:
    """Whether ``text`` can be a job id at all (RQ refuses others with an error)."""
    return JOB_ID.fullmatch(text) is not None


def cancel_key(job_id: str) -> str:
    """Redis key of a job's cancel flag, checked by the worker at every progress report."""
    return f"cloudgraph:cancel:{job_id}"


def lock_key(job_id: str) -> str:
    """Redis key of the lock that makes enqueueing one cache's precompute happen once."""
    return f"cloudgraph:lock:{job_id}"


def render_path(outputs_dir: Path, job_id: str, fmt: str) -> Path:
    """Where a render job writes its image."""
    return outputs_dir / "renders" / f"{job_id}.{fmt}"


def animation_dir(outputs_dir: Path, anim_id: str) -> Path:
    """The folder of an animation's frames and video."""
    return outputs_dir / "animations" / anim_id


def fetch(redis: Redis, job_id: str) -> Job | None:
    """The job, or None when there is none by that id or the id is not well-formed."""
    if not is_job_id(job_id):
        return None
    try:
        return Job.fetch(job_id, connection=redis)
    except NoSuchJobError:
        return None


# ---------------------------------------------------------------------- ending jobs for good
def end_dependents(job: Job, why: str, failed: bool) -> None:
    """Ends the jobs that wait on ``job`` (and those that wait on them) with ``why`` as their
    error, as failed or canceled. Once ``job`` has failed or been cancelled, RQ would leave them
    deferred for ever: waiting, to clients, and taking room in the queue."""
    todo, seen = list(job.dependent_ids), set()
    while todo:
        jid = todo.pop()
        if jid in seen:
            continue
        seen.add(jid)
        dep = fetch(job.connection, jid)
        if dep is None or dep.get_status() != JobStatus.DEFERRED:
            continue
        dep.meta.update({"error": why, "failed" if failed else "canceled": True})
        dep.save_meta()
        dep.cancel()
        todo.extend(dep.dependent_ids)


def ended_dependency(job: Job) -> tuple[Job, bool] | None:
    """(dependency, failed) for the first job that ``job`` waits on and that has ended without
    finishing (failed, cancelled or gone); None while all of them may still finish."""
    for jid in job.dependency_ids:
        dep = fetch(job.connection, jid)
        if dep is None:
            return Job(jid, connection=job.connection), True
        st = dep.get_status()
        if st == JobStatus.FAILED or dep.meta.get("failed"):
            return dep, True
        if st in (JobStatus.CANCELED, JobStatus.STOPPED) or dep.meta.get("canceled"):
            return dep, False
    return None


def end_if_orphaned(job: Job) -> bool:
    """Ends ``job`` (and its dependents) when something it waits on has already ended without
    finishing: the case of a job enqueued after its dependency failed, which RQ never wakes."""
    if job.get_status() != JobStatus.DEFERRED:
        return False
    found = ended_dependency(job)
    if found is None:
        return False
    dep, failed = found
    why = f"it waited on job {dep.id}, which {'failed' if failed else 'was cancelled'}"
    if dep.meta.get("error") and failed:
        why += f": {dep.meta['error']}"
    job.meta.update({"error": why, "failed" if failed else "canceled": True})
    job.save_meta()
    try:
        job.cancel()
    except InvalidJobOperation:  # ended meanwhile by another process (a sweep, a request): done
        return True
    end_dependents(job, why, failed)
    return True


def sweep_deferred(queue: Queue) -> int:
    """Ends every waiting job of ``queue`` whose dependency ended without finishing; returns how
    many. Run by the workers' supervisors now and then, so no route to failure leaves one."""
    n = 0
    for jid in queue.deferred_job_registry.get_job_ids():
        job = fetch(queue.connection, jid)
        if job is not None and end_if_orphaned(job):
            n += 1
    return n


def fail_for_good(job: Job, message: str, cancelled: bool = False) -> None:
    """Ends a started job whose worker process was killed: failed with ``message`` (or stopped,
    when a client had cancelled it), never retried, so no restart brings it back. It leaves the
    started registry, and the jobs that wait on it end too."""
    from rq.job_lifecycle import record_job_failure
    from rq.utils import now

    job.meta.update({"error": message, "stage": "canceled" if cancelled else "failed"})
    job.save_meta()
    job.retries_left = 0
    with job.connection.pipeline() as pipe:
        job.started_job_registry.remove_executions(job, pipeline=pipe)
        job.ended_at = job.ended_at or now()
        record_job_failure(job, message, pipe)
        if cancelled:
            job.set_status(JobStatus.STOPPED, pipeline=pipe)
        job.save(pipeline=pipe, include_meta=False)
        pipe.execute()
    why = "was cancelled" if cancelled else f"failed: {message}"
    end_dependents(job, f"it waited on job {job.id}, which {why}", failed=not cancelled)


def requeue_after_death(job: Job) -> bool:
    """Puts back a started job whose worker died under it, if it has retries left (True), else
    fails it for good. The one kind of failure that is retried: it may not happen again."""
    if not job.retries_left:
        fail_for_good(job, "its worker died while running it, on every try; see the worker log")
        return False
    job.retries_left -= 1
    queue = Queue(job.origin, connection=job.connection)
    with job.connection.pipeline() as pipe:
        job.started_job_registry.remove_executions(job, pipeline=pipe)
        job.meta.update({"stage": "queued"})
        job.started_at = None
        queue._enqueue_job(job, pipeline=pipe, at_front=True)
        pipe.execute()
    return True
