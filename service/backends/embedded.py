"""The embedded backend: solves run in child processes of the server, one process per job.

No other server is needed. A scheduler thread keeps at most ``settings.workers`` solves running:
it claims the next queued job from the table (fair between users), forks a process for it and
watches it. A process per job means a cancel kills exactly that solve (gtsam's optimiser holds the
GIL and cannot be interrupted from Python), and a solve that crashes takes nothing else with it.

Processes come from a *forkserver* that imported the solver (and, with ``warm_start``, ran it once
so numba's kernels are compiled): forking a job costs milliseconds, not an import and a JIT. The
forkserver starts with the server; until it is up no job is started (their progress says
``compiling``) and ``/healthz`` says ``starting``.

A long run's windows (:mod:`service.run.shared_windows`) use the slots no queued job takes: the run
asks for helpers on its board (:mod:`service.run.folder_windows`), and the scheduler starts helper
processes for it (:func:`service.run.worker.help_embedded`), counted among the ``workers``; a helper
leaves when another job is queued, and goes with its run.

Crash safety:

* a job process that dies without finishing (killed, out of memory) interrupts its run: the job is
  queued again, or failed once it used ``max_attempts`` runs;
* the scheduler renews the lease of every run it watches; at start-up the server holds the data
  dir's lock, so runs still marked ``running`` belong to a server that died: they are interrupted
  the same way (:meth:`service.store.Store.adopt`);
* job processes ask the kernel to kill them when the forkserver dies (which it does when the
  server dies), and a run's writes are fenced by its run token, so an orphan can never overwrite a
  newer run.
"""

from __future__ import annotations

import multiprocessing
import shutil
import socket
import threading
import time
from dataclasses import dataclass

from service.backends.base import Backend, log
from service.errors import DISK_FULL, EXIT_DISK_FULL
from service.settings import Settings
from service.store import COMPILING, Store, StoreFull
from service.store.jobfiles import job_dir, result_tmp

WAITING_FOR_SOLVER = ("starting: the solver's kernels are being compiled (once after an install or upgrade, "
                      "about 1-2 minutes); jobs wait in the queue until then")


@dataclass
class _Run:
    job_id: str
    token: str
    process: multiprocessing.process.BaseProcess
    started: float
    cancelled: bool = False


def _describe_exit(code: int | None) -> str:
    import signal

    if code is None:
        return "the solve process vanished"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"the solve process was killed ({name})"
    return f"the solve process exited with status {code} without a result"


class EmbeddedBackend(Backend):
    name = "embedded"
    TICK = 0.25

    def __init__(self, settings: Settings, store: Store):
        super().__init__(settings, store)
        self._ctx = multiprocessing.get_context("forkserver")
        self._runs: dict[str, _Run] = {}
        self._helpers: dict[str, list[multiprocessing.process.BaseProcess]] = {}  # a run's helper processes
        self._helper_failed: set[str] = set()  # runs (tokens) a helper of which failed: none started again
        self._lock = threading.Lock()
        self._host = socket.gethostname()
        self._last_renew = 0.0
        self._ready = threading.Event()  # the forkserver is up, with the solver compiled if warm_start

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        self._adopt()
        threading.Thread(target=self._start_forkserver, name="acinoset-forkserver-start", daemon=True).start()
        self._start_thread("acinoset-scheduler")

    def _start_forkserver(self) -> None:
        """Start the forkserver (importing and warming the solver) now rather than at the first job."""
        from service.run.worker import noop

        t0 = time.time()
        try:
            p = self._ctx.Process(target=noop, name="acinoset-forkserver-start", daemon=True)
            p.start()
            p.join()
        except Exception:
            log.exception("could not start the forkserver")
        finally:
            self._ready.set()
            self._wake.set()
        if time.time() - t0 > 5:
            log.warning("the solver is ready (it compiled its kernels in %.0f s)", time.time() - t0)

    def stop(self) -> None:
        self._stop_thread()
        with self._lock:
            runs = list(self._runs.values())
            self._runs.clear()
        self._end_helpers(*(r.job_id for r in runs))
        for run in runs:
            run.process.kill()
            run.process.join(timeout=5)
            self.store.release(run.job_id, run.token, "the service was stopped while it ran; it runs again")

    # -- the API's calls ---------------------------------------------------------------------

    def submit(self, job_id: str) -> None:
        self._wake.set()

    def cancel(self, job_id: str, run_token: str | None) -> None:
        with self._lock:
            run = self._runs.get(job_id)
            if run is not None:
                run.cancelled = True
                run.process.kill()
        if run is not None:
            run.process.join(timeout=5)
        self._end_helpers(job_id)
        self._wake.set()

    def health(self) -> dict:
        alive = self._thread_alive()
        ready = self._ready.is_set()
        detail = None if alive else "the scheduler thread is not running"
        if alive and not ready:
            detail = WAITING_FOR_SOLVER if self.settings.warm_start else "starting the solve processes"
        return {"ok": alive, "ready": ready, "workers": self.settings.workers, "detail": detail}

    # -- the scheduler -----------------------------------------------------------------------

    def _tick(self) -> None:
        try:
            self._reap()
            self._enforce()
            self._renew()
            self._fill()
        except StoreFull:  # the disk is full: the loop says so once (Backend._guarded_tick)
            raise
        except Exception:  # keep scheduling whatever one tick hit (e.g. a locked database)
            log.exception("scheduler tick failed")
            time.sleep(0.5)

    def _reap(self) -> None:
        """Ended processes: a run that did not record its end was interrupted, but for one that
        exited with :data:`EXIT_DISK_FULL` (the disk full, it could not record its failure): that
        one is failed, naming the disk, not run again. A run is forgotten only once the table says
        so: if recording its end fails (a full disk, a locked table), the run stays watched and the
        next tick tries again; dropping it first had left its job ``running`` with no process until
        a restart."""
        with self._lock:
            ended = [r for r in self._runs.values() if r.process.exitcode is not None]
            left = [h for helpers in self._helpers.values() for h in helpers if h.exitcode is not None]
            for helpers in self._helpers.values():
                helpers[:] = [h for h in helpers if h.exitcode is None]
        for h in left:  # a helper that left (its windows done, another job queued) or failed, or was killed
            h.join(timeout=1)
            if h.exitcode != 0:
                self._helper_failed.add(h.name.rpartition("-")[2])
            h.close()
        self._end_helpers(*(r.job_id for r in ended))
        for r in ended:
            code = r.process.exitcode
            r.process.join(timeout=1)
            if not r.cancelled and code == EXIT_DISK_FULL:  # it could not record its own end
                if self.store.finish(r.job_id, r.token, "failed", error=DISK_FULL, error_kind="limit"):  # may raise
                    log.warning("job %s: failed: %s", r.job_id, DISK_FULL)
            elif not r.cancelled:
                status = self.store.interrupt(r.job_id, r.token, _describe_exit(code))  # may raise: kept
                if status is not None:
                    log.warning("job %s: %s; now %s", r.job_id, _describe_exit(code), status)
            with self._lock:
                self._runs.pop(r.job_id, None)
                self._helper_failed.discard(r.token)
            # what a killed run (cancelled, timed out, lost) had written: its staged inputs can be a GB
            shutil.rmtree(result_tmp(job_dir(self.settings.jobs_dir, r.job_id), r.token), ignore_errors=True)
            try:
                r.process.close()
            except ValueError:
                pass

    def _enforce(self) -> None:
        """Kill runs whose job is no longer theirs (cancelled, deleted, or cancelled from the CLI)
        and runs over the time limit."""
        with self._lock:
            runs = list(self._runs.values())
        now = time.time()
        for r in runs:
            job = self.store.job(r.job_id)
            if job is None or job.status != "running" or job.run_token != r.token:
                if r.process.is_alive() and job is not None and job.status in ("succeeded", "failed"):
                    continue  # finished a moment ago; the process is on its way out
                if r.process.is_alive():
                    r.cancelled = True
                    r.process.kill()
            elif now - r.started > self.settings.job_timeout_seconds:
                r.cancelled = True
                r.process.kill()
                r.process.join(timeout=5)
                self.store.finish(r.job_id, r.token, "failed", error_kind="limit",
                                  error=f"the solve ran longer than the time limit of "
                                        f"{self.settings.job_timeout_seconds:g} s")

    def _renew(self) -> None:
        now = time.time()
        if now - self._last_renew < self.settings.heartbeat_seconds:
            return
        self._last_renew = now
        with self._lock:
            tokens = [r.token for r in self._runs.values()]
        self.store.renew_leases(tokens, self.settings.lease_seconds)

    def _busy(self) -> int:
        """Slots taken: runs and their helpers (call with the lock held)."""
        return len(self._runs) + sum(len(h) for h in self._helpers.values())

    def _end_helpers(self, *job_ids: str) -> None:
        """The helper processes of these jobs' runs killed (their runs ended)."""
        with self._lock:
            helpers = [h for j in job_ids for h in self._helpers.pop(j, [])]
        for h in helpers:
            h.kill()
            h.join(timeout=5)

    def _fill(self) -> None:
        from service.run.worker import run_embedded

        if not self._ready.is_set():  # a fork now would block this thread until the forkserver is up
            self.store.mark_queued(self.name, COMPILING)
            return
        while True:
            with self._lock:
                if self._busy() >= self.settings.workers:
                    return
            job = self.store.claim_next(f"{self._host}:starting", self.settings.lease_seconds, self.name)
            if job is None:
                break
            assert job.run_token is not None
            p = self._ctx.Process(
                target=run_embedded, name=f"acinoset-job-{job.id[:8]}", daemon=True,
                args=(str(self.settings.db_path), str(self.settings.jobs_dir), job.id, job.run_token,
                      self.settings.progress_interval_seconds, self.settings.solve_niceness,
                      self.settings.workers - 1))
            try:
                p.start()
            except Exception as e:  # cannot fork: give the attempt back and retry later
                self.store.interrupt(job.id, job.run_token, f"could not start a solve process ({e})")
                raise
            with self._lock:
                self._runs[job.id] = _Run(job.id, job.run_token, p, time.time())
            self.store.set_worker(job.id, job.run_token, f"{self._host}:{p.pid}")
        self._help()

    def _help(self) -> None:
        """Slots no queued job took go to long runs that ask for helpers (their boards say how many)."""
        from service.run.folder_windows import FolderBoard
        from service.run.worker import help_embedded
        from service.store.jobfiles import windows_board

        with self._lock:
            runs = [r for r in self._runs.values() if not r.cancelled and r.process.exitcode is None
                    and r.token not in self._helper_failed]
        for r in runs:
            wanted = FolderBoard(windows_board(job_dir(self.settings.jobs_dir, r.job_id), r.token)).wanted()
            while True:
                with self._lock:
                    helpers = self._helpers.setdefault(r.job_id, [])
                    if len(helpers) >= wanted or self._busy() >= self.settings.workers:
                        break
                h = self._ctx.Process(
                    target=help_embedded, name=f"acinoset-helper-{r.token}", daemon=True,
                    args=(str(self.settings.db_path), str(self.settings.jobs_dir), r.job_id, r.token,
                          self.settings.solve_niceness, self.name))
                h.start()
                with self._lock:
                    kept = self._helpers.get(r.job_id) is helpers  # not ended meanwhile (a cancel)
                    if kept:
                        helpers.append(h)
                if not kept:
                    h.kill()
                    h.join(timeout=5)
                    break
                log.info("job %s: a helper process (%s) solves windows of its run", r.job_id, h.pid)
