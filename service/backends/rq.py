"""The RQ backend: solves run on ``acinoset worker`` processes, on any machine that reaches Redis.

Redis carries the work, the job table stays the record of truth. Each attempt chain of a job is
one RQ job whose id is the job's *run token* in the table. Its input files travel as one zip
archive in the Redis key ``acinoset:input:<token>`` (workers need no shared disk), its result files
come back in ``acinoset:result:<token>`` (each a list of 1 MB chunks, so that footage and labelled
videos are not bounded by the largest value Redis takes: :func:`service.store.jobfiles.put_archive`); the server's
collector thread copies them into the data
dir and the table, then deletes them and the RQ job from Redis. With ``shared_data_dir`` the workers
mount the data dir: a job's files stay where the API stored them, the worker writes its results beside
them (``result.<token>.tmp``) and the collector installs that folder; nothing but the job's id and
its progress goes through Redis. RQ is used with
``Retry`` (a work horse that dies is queued again by its worker), ``result_ttl=-1`` (a result
waits in Redis until the server has stored it, even across a server restart), a job timeout above
the longest solve, and the JSON serializer (nothing from a job is ever unpickled).

The collector (every ``0.5 s``) reconciles the table with Redis:

* queued rows without an RQ job are enqueued, a few at a time and fairly between users (see
  ``_dispatch``), as are rows whose RQ job was lost (the server died between the two writes, or
  Redis lost data);
* a started RQ job mirrors its progress, worker and attempt into the row; one whose worker stopped
  heartbeating for ``lease_seconds`` (the whole worker machine died) is dropped and enqueued again
  as the next attempt, or failed after ``max_attempts``;
* finished, failed and stopped RQ jobs end the row and are deleted from Redis.
"""

from __future__ import annotations

import shutil
import threading
import time
from dataclasses import dataclass

from service.backends.base import Backend, log
from service.settings import Settings, redacted
from service.store import Job, Store, StoreFull

RQ_FUNCTION = "service.run.worker.run_rq_job"


def run_token(job_id: str, attempt: int) -> str:
    """The RQ job id of a job's attempt chain from ``attempt`` on: the row's run token."""
    return f"{job_id}-{attempt}"


def job_of(token: str) -> str:
    """The job id in a run token (:func:`run_token`)."""
    return token.rsplit("-", 1)[0]


def project_worker_class():
    """RQ's ``Worker``, refusing every job whose function is not :data:`RQ_FUNCTION`.

    RQ runs whatever importable function a job in its queue names (``os.system`` with arguments of
    the enqueuer's choice), the JSON serializer notwithstanding: anyone who can write to Redis could
    run code on every worker. A job naming another function is failed without being run (its
    function never imported), and the worker says so in its log and goes on."""
    from rq import Worker

    class ProjectWorker(Worker):
        def execute_job(self, job, queue):
            name = job.func_name  # read from the job's JSON; nothing is imported to know it
            if name != RQ_FUNCTION:
                log.warning("refused RQ job %s: it names %r, not this project's %s", job.id, name, RQ_FUNCTION)
                self.handle_job_failure(job, queue, exc_string=f"refused: {name!r} is not {RQ_FUNCTION}")
                return
            super().execute_job(job, queue)

    return ProjectWorker


def _rq():
    from redis import Redis
    from rq import Queue
    from rq.serializers import JSONSerializer

    return Redis, Queue, JSONSerializer


_STATE_FIELDS = ("status", "last_heartbeat", "started_at", "worker_name", "meta", "retries_left")


@dataclass
class _RQState:
    """The few fields of an RQ job the collector reads on every pass (not its data: the input files)."""

    id: str
    status: str
    last_heartbeat: float | None
    started_at: float | None
    worker_name: str | None
    meta: dict
    retries_left: int | None


def _states(redis, serializer, tokens: list[str]) -> dict[str, _RQState | None]:
    from rq.job import Job as RQJob
    from rq.utils import str_to_date

    def text(v):
        return v.decode() if isinstance(v, bytes) else v

    def when(v):
        return str_to_date(v).timestamp() if v else None

    with redis.pipeline() as pipe:
        for t in tokens:
            pipe.hmget(RQJob.key_for(t), *_STATE_FIELDS)
        rows = pipe.execute()
    out: dict[str, _RQState | None] = {}
    for t, (status, hb, started, worker, meta, retries) in zip(tokens, rows):
        if status is None:
            out[t] = None
            continue
        try:
            meta_d = serializer.loads(meta) if meta else {}
        except ValueError:
            meta_d = {}
        out[t] = _RQState(t, text(status), when(hb), when(started), text(worker) or None, meta_d,
                          int(retries) if retries not in (None, b"") else None)
    return out


def _attempts(rj, status, fallback: int) -> int:
    """Runs of the job started so far, counted from RQ's own retry bookkeeping: the runs before this
    RQ job, plus the retries it used, plus the current run if it has started or ended."""
    from rq.job import JobStatus

    meta = rj.meta or {}
    if "attempts_before" not in meta:
        return fallback
    retries = int(meta.get("retries", 0))
    used = retries - int(rj.retries_left if rj.retries_left is not None else retries)
    current = 0 if status in (JobStatus.QUEUED, JobStatus.SCHEDULED, JobStatus.DEFERRED) else 1
    return int(meta["attempts_before"]) + used + current


class RQBackend(Backend):
    name = "rq"
    TICK = 0.5

    def __init__(self, settings: Settings, store: Store):
        super().__init__(settings, store)
        Redis, Queue, JSONSerializer = _rq()
        self.serializer = JSONSerializer
        self.redis = Redis.from_url(settings.redis_url, socket_timeout=10, socket_connect_timeout=5,
                                    health_check_interval=30)
        self.queue = Queue(settings.queue_name, connection=self.redis, serializer=JSONSerializer,
                           default_timeout=int(settings.job_timeout_seconds))
        self._lock = threading.RLock()  # one enqueue or collector pass at a time
        self._stopping: dict[str, float] = {}  # RQ job ids told to stop -> when
        self._last_sweep = 0.0
        self._redis_error: str | None = None
        self._row_errors: dict[str, str] = {}  # job id -> the error its collection keeps meeting (logged once)

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        self._adopt()
        self._start_thread("acinoset-rq-collector")

    def stop(self) -> None:
        self._stop_thread()

    # -- the API's calls ---------------------------------------------------------------------

    def submit(self, job_id: str) -> None:
        """The collector enqueues it (rows without a run token) at once; the upload's answer does
        not wait for Redis, and a Redis that is down only delays the job."""
        self._wake.set()

    def cancel(self, job_id: str, run_token: str | None) -> None:
        if not run_token:
            return
        from rq.command import send_stop_job_command
        from rq.job import Job as RQJob
        from rq.job import JobStatus

        try:
            rj = RQJob.fetch(run_token, connection=self.redis, serializer=self.serializer)
        except Exception:
            return
        try:
            if rj.get_status(refresh=False) == JobStatus.STARTED:
                send_stop_job_command(self.redis, run_token, serializer=self.serializer)
                self._stopping[run_token] = time.time()
            else:
                self._delete(run_token)
        except Exception as e:
            log.warning("job %s: could not stop RQ job %s (%s)", job_id, run_token, e)
            self._stopping[run_token] = time.time()

    def health(self) -> dict:
        from rq import Worker

        try:
            self.redis.ping()
            workers = Worker.count(queue=self.queue)
        except Exception as e:
            return {"ok": False, "workers": 0,
                    "detail": f"Redis at {redacted(self.settings.redis_url)} unreachable: {e}"}
        alive = self._thread_alive()
        detail = None
        if not alive:
            detail = "the collector thread is not running"
        elif workers == 0:
            detail = "no worker is connected: start 'acinoset worker --redis-url URL'"
        return {"ok": alive, "workers": workers, "detail": detail}

    # -- enqueue -----------------------------------------------------------------------------

    def _enqueue(self, job: Job) -> None:
        """One RQ job for the job's remaining attempts; its id, ``<job id>-<first attempt>``, becomes
        the row's run token. If the server died after enqueueing it but before recording it, the RQ
        job is found again by that id instead of being enqueued twice. A job whose stored files
        cannot be read is failed, saying why (it would otherwise end every dispatch pass at itself
        and hold back the jobs after it); Redis' own errors propagate (the backend waits for Redis)."""
        from rq import Retry
        from rq.job import Job as RQJob

        from service.store.jobfiles import INPUT, input_archive, input_key, job_dir, put_archive

        with self._lock:
            remaining = max(1, job.max_attempts - job.attempts)
            token = run_token(job.id, job.attempts + 1)
            shared = self.settings.shared_data_dir
            if RQJob.fetch_many([token], connection=self.redis, serializer=self.serializer)[0] is None:
                if not shared:
                    try:
                        archive = input_archive(job_dir(self.settings.jobs_dir, job.id) / INPUT)
                    except Exception as e:  # noqa: BLE001 - this job's files, not the service
                        self._unsendable(job, token, e)
                        return
                    put_archive(self.redis, input_key(token), archive)
                self.queue.enqueue_call(
                    RQ_FUNCTION,
                    args=(job.id, self.settings.progress_interval_seconds, self.settings.solve_niceness),
                    kwargs={"shared": True} if shared else None,
                    job_id=token, timeout=int(self.settings.job_timeout_seconds), result_ttl=-1,
                    failure_ttl=7 * 24 * 3600, retry=Retry(max=remaining - 1) if remaining > 1 else None,
                    meta={"attempts_before": job.attempts, "retries": remaining - 1, "job": job.id},
                    description=f"acinoset job {job.id} ({job.owner})")
            if not self.store.assign_run(job.id, token):  # cancelled meanwhile
                self._delete(token)

    def _unsendable(self, job: Job, token: str, e: Exception) -> None:
        """Fail a queued job whose input files cannot be read from the data dir."""
        why = f"{type(e).__name__}: {' '.join(str(e).split())}"
        log.error("job %s: its input files cannot be sent to the workers: %s", job.id, why)
        if self.store.assign_run(job.id, token):
            self.store.mirror_finished(job.id, token, "failed", job.attempts,
                                       error=f"the job's stored input files cannot be read: {why}")

    # -- the collector -----------------------------------------------------------------------

    def _tick(self) -> None:
        try:
            with self._lock:
                self._collect()
            self._finish_stopping()
            if time.time() - self._last_sweep > 60:
                self._sweep()
                self._last_sweep = time.time()
            if self._redis_error:
                log.warning("Redis reachable again")
            self._redis_error = None
        except StoreFull:  # the disk is full: the loop says so once (Backend._guarded_tick)
            raise
        except Exception as e:
            if str(e) != self._redis_error:
                log.exception("RQ collector")
            self._redis_error = str(e)
            time.sleep(1.0)

    def _full(self, token: str):
        from rq.job import Job as RQJob

        return RQJob.fetch_many([token], connection=self.redis, serializer=self.serializer)[0]

    def _delete(self, token: str) -> None:
        """The RQ job and its files in Redis, and what a long job shared with helpers: their queued
        RQ jobs and the windows' keys (a work horse killed, by a cancel, cleans up nothing itself)."""
        from rq.job import Job as RQJob

        from service.store.jobfiles import (
            JOB_ID,
            PARTIAL,
            helpers_prefix,
            input_key,
            job_dir,
            result_key,
            result_tmp,
            windows_key,
        )

        rj = self._full(token)
        if rj is not None:
            rj.delete()
        self.redis.delete(input_key(token), result_key(token), input_key(token) + PARTIAL, result_key(token) + PARTIAL)
        job_id = job_of(token)
        if JOB_ID.match(job_id):  # results a worker on the shared data dir left (a cancel, a lost run)
            shutil.rmtree(result_tmp(job_dir(self.settings.jobs_dir, job_id), token), ignore_errors=True)
        helpers = [jid for jid in self.queue.get_job_ids() if jid.startswith(helpers_prefix(token))]
        for helper in RQJob.fetch_many(helpers, connection=self.redis, serializer=self.serializer):
            if helper is not None:
                helper.delete()
        windows = list(self.redis.scan_iter(match=windows_key(token) + ":*", count=500))
        if windows:
            self.redis.delete(*windows)

    def _collect(self) -> None:
        from redis.exceptions import RedisError

        rows = self.store.active_jobs(self.name)
        tokens = [r.run_token for r in rows if r.run_token]
        fetched = _states(self.redis, self.serializer, tokens)
        now = time.time()
        waiting: list[Job] = []  # queued rows Redis does not hold yet
        for row in rows:
            try:
                if self._collect_row(row, fetched.get(row.run_token) if row.run_token else None, now):
                    waiting.append(row)
            except RedisError:  # Redis itself: the whole pass waits for it
                raise
            except Exception as e:  # noqa: BLE001 - this row's own trouble: the rows after it go on
                self._row_trouble(row, e)
        self._row_errors = {k: v for k, v in self._row_errors.items() if any(r.id == k for r in rows)}
        self._dispatch(waiting, rows, fetched)

    def _row_trouble(self, row: Job, e: Exception) -> None:
        """A row whose collection raised (its result archive cannot be read or stored). A full disk
        may be freed: the row is tried again on the next pass. Anything else fails the row, saying
        why, instead of stopping every pass at it."""
        import errno

        why = f"{type(e).__name__}: {' '.join(str(e).split())}"
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            if self._row_errors.get(row.id) != why:
                log.error("job %s: its results cannot be stored yet: %s", row.id, why)
            self._row_errors[row.id] = why
            return
        log.error("job %s: failed while collecting its run: %s", row.id, why)
        if row.run_token and self.store.mirror_finished(row.id, row.run_token, "failed", row.attempts,
                                                        error=f"the run's result files could not be stored: {why}"):
            self._delete(row.run_token)
        self._row_errors.pop(row.id, None)

    def _collect_row(self, row: Job, rj, now: float) -> bool:
        """Mirror one active row from its RQ job ``rj`` (None: Redis holds none); True if the row
        waits to be handed to Redis."""
        from rq.job import JobStatus

        if rj is None:
            if row.status == "queued":
                return True
            status = self.store.interrupt(row.id, row.run_token, "the queue lost the job "
                                          "(Redis restarted without its data?)")
            fresh = self.store.job(row.id)
            if status == "queued" and fresh is not None:
                self._enqueue(fresh)
            return False
        token = rj.id
        status = rj.status
        attempt = _attempts(rj, status, row.attempts)
        if status == JobStatus.STARTED:
            hb = rj.last_heartbeat or rj.started_at
            if hb is not None and now - hb > self.settings.lease_seconds:
                self._lost(row, rj, attempt)
            else:
                self.store.mirror_running(row.id, token, attempt, rj.worker_name, rj.started_at,
                                          self.settings.lease_seconds, rj.meta.get("progress"))
        elif status == JobStatus.FINISHED:
            full = self._full(token)
            if full is not None:
                self._finished(row, full, attempt)
        elif status == JobStatus.FAILED:
            rj = self._full(token)
            if rj is None:
                return False
            res = rj.latest_result()
            exc = (res.exc_string if res is not None else None) or "unknown error"
            last = [ln for ln in exc.strip().splitlines() if ln.strip()][-1:] or ["unknown error"]
            reason = " ".join(last[0].split())
            if "terminated unexpectedly" in exc or "Abandoned" in exc:
                reason = f"the worker's solve process died ({reason})"
            self.store.mirror_finished(row.id, token, "failed", attempt,
                                       error=f"gave up after {max(attempt, 1)} attempts; last: {reason}"
                                       if attempt >= row.max_attempts else reason)
            self._delete(token)
        elif status in (JobStatus.STOPPED, JobStatus.CANCELED):
            self.store.cancel(row.id)
            self._delete(token)
        elif status in (JobStatus.QUEUED, JobStatus.SCHEDULED, JobStatus.DEFERRED):
            if row.status == "running":  # RQ retries it: its work horse died
                self.store.mirror_requeued(row.id, token, attempt,
                                           f"attempt {attempt} of {row.max_attempts} interrupted: "
                                           "the worker's solve process died")
        return False

    def _dispatch(self, waiting: list[Job], rows: list[Job], fetched: dict) -> None:
        """Hand queued jobs to Redis, fairly between users. RQ runs its queue in order, so one user's
        200 jobs would hold back everyone else's; instead Redis holds only about two waiting jobs
        per live worker, and each free place goes to the queued job of the user with the fewest
        jobs in Redis (running or waiting), the oldest first."""
        if not waiting:
            return
        from collections import Counter

        from rq import Worker
        from rq.job import JobStatus

        held = [r for r in rows if r.run_token and fetched.get(r.run_token) is not None]
        ready = sum(1 for r in held if fetched[r.run_token].status in (JobStatus.QUEUED, JobStatus.SCHEDULED,
                                                                          JobStatus.DEFERRED))
        room = max(2, 2 * Worker.count(queue=self.queue)) - ready
        per_owner = Counter(r.owner_id for r in held)
        while room > 0 and waiting:
            pick = min(waiting, key=lambda r: (per_owner[r.owner_id], r.seq))
            waiting.remove(pick)
            self._enqueue(pick)
            per_owner[pick.owner_id] += 1
            room -= 1

    def _lost(self, row: Job, rj, attempt: int) -> None:
        """A started job whose worker stopped heartbeating: that worker is gone."""
        self.store.mirror_running(row.id, rj.id, attempt, rj.worker_name, None, self.settings.lease_seconds, None)
        try:
            self._delete(rj.id)
        except Exception:
            pass
        status = self.store.interrupt(row.id, rj.id, f"worker {rj.worker_name or '?'} stopped responding")
        log.warning("job %s: worker %s stopped responding; now %s", row.id, rj.worker_name, status)
        fresh = self.store.job(row.id)
        if status == "queued" and fresh is not None:
            self._enqueue(fresh)

    def _finished(self, row: Job, rj, attempt: int) -> None:
        from service.store.jobfiles import (
            get_archive,
            install_result,
            is_result_name,
            job_dir,
            keep_results,
            result_key,
            result_tmp,
            unpack_files,
        )

        rv = rj.return_value()
        dest = job_dir(self.settings.jobs_dir, row.id)
        tmp = result_tmp(dest, rj.id)
        on_disk = isinstance(rv, dict) and rv.get("files") == "shared" and tmp.is_dir()  # the worker wrote them there
        archive = None if on_disk else get_archive(self.redis, result_key(rj.id))
        if not isinstance(rv, dict) or rv.get("status") not in ("succeeded", "failed"):
            self.store.mirror_finished(row.id, rj.id, "failed", attempt, error="the worker returned no result")
        elif rv["status"] == "failed":
            self.store.mirror_finished(row.id, rj.id, "failed", attempt, error=rv.get("error") or "failed",
                                       error_kind=rv.get("error_kind"), worker=rv.get("worker"))
        elif archive is None and not on_disk:
            self.store.mirror_finished(row.id, rj.id, "failed", attempt, error="the worker's result files are "
                                       "missing", worker=rv.get("worker"))
        else:
            try:
                if archive is not None:
                    shutil.rmtree(tmp, ignore_errors=True)
                    unpack_files(archive, tmp, allowed=is_result_name)
                else:
                    keep_results(tmp)
                self.store.mirror_finished(row.id, rj.id, "succeeded", attempt, summary=rv.get("report"),
                                           solve_seconds=rv.get("seconds"), worker=rv.get("worker"),
                                           commit=lambda: install_result(dest, tmp))
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        self._delete(rj.id)

    def _finish_stopping(self) -> None:
        """Delete stopped RQ jobs of cancelled rows once their work horse is gone."""
        from rq.command import send_stop_job_command
        from rq.job import Job as RQJob
        from rq.job import JobStatus

        for token, since in list(self._stopping.items()):
            rj = RQJob.fetch_many([token], connection=self.redis, serializer=self.serializer)[0]
            if rj is None:
                self._stopping.pop(token, None)
                continue
            if rj.get_status(refresh=False) != JobStatus.STARTED:
                self._delete(token)
                self._stopping.pop(token, None)
            elif time.time() - since > 10:  # the stop message was missed: say it again
                send_stop_job_command(self.redis, token, serializer=self.serializer)
                self._stopping[token] = time.time()

    def _sweep(self) -> None:
        """Delete RQ jobs that belong to no active row (left by a crash, or a run given up for lost
        whose worker came back): Redis does not keep growing."""
        from rq.job import Job as RQJob
        from rq.registry import CanceledJobRegistry, FailedJobRegistry, FinishedJobRegistry

        from service.store.jobfiles import PARTIAL, input_key, result_key

        live = {r.run_token for r in self.store.active_jobs(self.name) if r.run_token}
        for reg in (FinishedJobRegistry, FailedJobRegistry, CanceledJobRegistry):
            registry = reg(queue=self.queue)
            for jid in registry.get_job_ids():
                if jid in live:
                    continue
                rj = RQJob.fetch_many([jid], connection=self.redis, serializer=self.serializer)[0]
                if rj is not None:
                    self._delete(jid)
                else:
                    registry.remove(jid)
        # files of RQ jobs that no active row runs
        for prefix in (input_key(""), result_key("")):
            for key in self.redis.scan_iter(match=prefix + "*", count=500):
                token = key.decode().removeprefix(prefix).removesuffix(PARTIAL)  # a partial one is its token's
                if token not in live and self._full(token) is None:
                    self.redis.delete(key)
