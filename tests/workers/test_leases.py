"""Stage leases and worker presence in the job store, on SQLite and on a fresh PostgreSQL
database: one delivery runs a stage, a lapsed lease is claimed by exactly one sweeper, a stage
that keeps losing its worker fails its job, and a job says when no worker consumes its queue."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import update

from tests.integration.services import ROOT
from workers.db import init_db, make_engine, make_sessionmaker
from workers.jobstore import JobStore
from workers.leases import Heartbeat, claim, lapsed_leases, renew_held_by, sweep_lapsed
from workers.models import Capture, Job, utcnow
from workers.presence import announce, live_queues, retire, waiting_queue, waiting_reason
from workers.settings import Settings

JOB = "j" * 32
STAGES = ["filter", "align", "enhance", "export"]


class Sent:
    """A task sender that records what it sends (the broker is not under test here)."""

    def __init__(self, fail: bool = False) -> None:
        self.tasks: list[tuple[str, list[Any], str]] = []
        self.fail = fail
        self.lock = threading.Lock()

    def __call__(self, name: str, args: list[Any], queue: str) -> str:
        if self.fail:
            raise ConnectionError("broker down")
        with self.lock:
            self.tasks.append((name, args, queue))
        return f"task-{len(self.tasks)}"


@pytest.fixture
def settings(store_settings: Settings) -> Settings:
    return store_settings.model_copy(update={"stage_lease_s": 30.0, "stage_max_tries": 3})


def _store(settings: Settings, jobs: int = 1) -> JobStore:
    engine = make_engine(settings)
    init_db(engine)
    store = JobStore(make_sessionmaker(engine))
    with store.sessions.begin() as session:
        session.add(Capture(id="c" * 32, sha256="c" * 64, size_bytes=1, storage_key="k",
                            state="ready"))
        for i in range(jobs):
            session.add(Job(id=JOB if i == 0 else f"{i:032x}", capture_id="c" * 32, options={},
                            stages=STAGES, stage_timings={}))
    return store


@pytest.fixture
def store(settings: Settings) -> JobStore:
    return _store(settings)


def _job(store: JobStore, job_id: str = JOB) -> Job:
    with store.sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None
        return job


def _later(seconds: float) -> Any:
    return utcnow() + timedelta(seconds=seconds)


def test_a_live_lease_keeps_other_deliveries_out(store: JobStore) -> None:
    assert store.start_stage(JOB, 0, "filter", "t0", "owner-a", 30)
    assert not store.start_stage(JOB, 0, "filter", "t0", "owner-b", 30)  # a redelivery
    assert store.start_stage(JOB, 0, "filter", "t0", "owner-a", 30)  # the holder itself
    job = _job(store)
    assert job.lease_owner == "owner-a" and job.lease_expires_at is not None
    # The holder queued the next stage: its delivery takes over the ending holder's lease,
    # and a late duplicate of the first stage stays out.
    assert store.start_stage(JOB, 1, "align", "t1", "owner-c", 30)
    assert not store.start_stage(JOB, 0, "filter", "t0", "owner-d", 30)
    store.finish_stage(JOB, 0, "filter", 1.0, 0.25)
    assert not store.start_stage(JOB, 0, "filter", "t0", "owner-d", 30)  # counted done


def test_a_released_lease_lets_the_next_delivery_in(store: JobStore, settings: Settings
                                                    ) -> None:
    assert store.start_stage(JOB, 0, "filter", "t0", "owner-a", 30)
    with Heartbeat(store.sessions, JOB, "owner-a", 30):
        pass  # a task that left by a retry or an error
    assert _job(store).lease_owner is None
    assert store.start_stage(JOB, 0, "filter", "t0", "owner-b", 30)


def test_a_lapsed_lease_is_the_sweeps_alone(store: JobStore, settings: Settings) -> None:
    assert store.start_stage(JOB, 0, "filter", "t0", "dead-worker", 1)
    sent = Sent()
    assert sweep_lapsed(store.sessions, sent, settings) == {}  # still live
    # Lapsed, a redelivery of the dead worker's message still does not start it...
    assert not store.start_stage(JOB, 0, "filter", "t0", "redelivery", 1)
    # ...the sweep claims it and queues it again once.
    assert sweep_lapsed(store.sessions, sent, settings, now=_later(5)) == {JOB: "requeue"}
    assert sent.tasks == [("volumesh.stage", [JOB, 0], "cpu")]
    job = _job(store)
    assert (job.state, job.lease_owner, job.lease_lapses) == ("queued", None, 1)
    assert sweep_lapsed(store.sessions, sent, settings, now=_later(10)) == {}
    assert store.start_stage(JOB, 0, "filter", "t1", "new-worker", 30)
    assert _job(store).lease_lapses == 1  # the same stage keeps its count


def test_two_sweepers_claim_each_lapsed_lease_once(settings: Settings) -> None:
    store = _store(settings, jobs=24)
    with store.sessions() as session:
        ids = [job_id for (job_id,) in session.query(Job.id)]
    for job_id in ids:
        assert store.start_stage(job_id, 1, "align", "t", f"dead-{job_id}", 1)
    now = _later(5)
    barrier = threading.Barrier(2)
    won: list[list[str]] = [[], []]

    def sweeper(slot: int) -> None:
        # Each sweeper has its own engine (as two gateway processes would) and the same view
        # of the lapsed leases; both then race to claim every one of them.
        engine = make_engine(settings)
        sessions = make_sessionmaker(engine)
        seen = lapsed_leases(sessions, now)
        barrier.wait()
        for lapsed in seen:
            if claim(sessions, lapsed, now, settings.stage_max_tries) is not None:
                won[slot].append(lapsed.job_id)
        engine.dispose()

    threads = [threading.Thread(target=sweeper, args=(slot,)) for slot in (0, 1)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert sorted(won[0] + won[1]) == sorted(ids)  # every lease claimed, none twice
    for job_id in ids:
        assert (_job(store, job_id).state, _job(store, job_id).lease_lapses) == ("queued", 1)


def test_concurrent_sweeps_queue_each_stage_once(settings: Settings) -> None:
    store = _store(settings, jobs=12)
    with store.sessions() as session:
        ids = [job_id for (job_id,) in session.query(Job.id)]
    for job_id in ids:
        assert store.start_stage(job_id, 2, "enhance", "t", f"dead-{job_id}", 1)
    sent = Sent()
    now = _later(5)
    threads = [threading.Thread(target=sweep_lapsed, args=(store.sessions, sent, settings, now))
               for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert sorted(args[0] for _, args, _ in sent.tasks) == sorted(ids)
    assert {queue for _, _, queue in sent.tasks} == {"gpu"}  # the stage's own queue


def test_a_stage_that_keeps_losing_its_worker_fails_the_job(store: JobStore,
                                                            settings: Settings) -> None:
    sent = Sent()
    for attempt in range(1, settings.stage_max_tries + 1):
        assert store.start_stage(JOB, 1, "align", "t", f"worker-{attempt}", 1)
        outcome = sweep_lapsed(store.sessions, sent, settings, now=_later(5))
        job = _job(store)
        assert job.lease_lapses == attempt
        if attempt < settings.stage_max_tries:
            assert outcome == {JOB: "requeue"} and job.state == "queued"
        else:
            assert outcome == {JOB: "failed"} and job.state == "failed"
    assert len(sent.tasks) == settings.stage_max_tries - 1
    job = _job(store)
    assert job.error is not None and job.finished_at is not None
    assert "the align stage's worker stopped answering 3 times" in job.error
    assert "killed, out of memory or its machine lost" in job.error
    assert "VOLUMESH_STAGE_MAX_TRIES" in job.error
    assert not store.start_stage(JOB, 1, "align", "t", "late", 1)  # the job is over


def test_lapses_count_per_stage(store: JobStore, settings: Settings) -> None:
    sent = Sent()
    assert store.start_stage(JOB, 0, "filter", "t", "w1", 1)
    sweep_lapsed(store.sessions, sent, settings, now=_later(5))
    assert store.start_stage(JOB, 0, "filter", "t", "w2", 30)
    assert store.finish_stage(JOB, 0, "filter", 1.0, 0.25)
    assert store.start_stage(JOB, 1, "align", "t", "w2", 30)
    assert _job(store).lease_lapses is None  # a new stage starts with a clean count


def test_an_unsent_requeue_is_retried(store: JobStore, settings: Settings) -> None:
    assert store.start_stage(JOB, 0, "filter", "t", "dead", 1)
    assert sweep_lapsed(store.sessions, Sent(fail=True), settings, now=_later(5)) == {}
    job = _job(store)
    assert (job.state, job.lease_lapses) == ("running", 0)  # put back, lapsed, uncounted
    sent = Sent()
    assert sweep_lapsed(store.sessions, sent, settings, now=_later(6)) == {JOB: "requeue"}
    assert len(sent.tasks) == 1 and _job(store).lease_lapses == 1


def test_the_heartbeat_renews_and_notices_a_lost_lease(store: JobStore, settings: Settings
                                                       ) -> None:
    lease_s = 0.6
    assert store.start_stage(JOB, 0, "filter", "t", "holder", lease_s)
    with Heartbeat(store.sessions, JOB, "holder", lease_s) as beat:
        time.sleep(3 * lease_s)  # three times the lease, with no progress callback
        assert sweep_lapsed(store.sessions, Sent(), settings) == {}  # renewed, never lapsed
        assert not beat.lost.is_set()
        with store.sessions.begin() as session:  # a sweep gave the stage to another worker
            session.execute(update(Job).where(Job.id == JOB).values(lease_owner="other"))
        deadline = time.monotonic() + 10 * lease_s
        while not beat.lost.is_set() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert beat.lost.is_set()
    assert _job(store).lease_owner == "other"  # leaving does not release another's lease


_GIL_HOG = """
import sys, time
from workers.db import make_engine, make_sessionmaker
from workers.jobstore import JobStore
from workers.leases import Heartbeat, new_owner
from workers.settings import Settings

data_dir, database_url, job_id, hold_s = sys.argv[1:5]
store = JobStore(make_sessionmaker(make_engine(Settings(data_dir=data_dir,
                                                        database_url=database_url or None))))
owner = new_owner()
assert store.start_stage(job_id, 0, "mesh", "t", owner, 1.0)
with Heartbeat(store.sessions, job_id, owner, 1.0):
    sys.setswitchinterval(1000)  # as native code holding the GIL: the beat thread cannot run
    print("holding", flush=True)
    end = time.monotonic() + float(hold_s)
    while time.monotonic() < end:
        pass
"""


@pytest.mark.parametrize("main_renews", [True, False])
def test_a_stage_holding_the_gil_keeps_its_lease_through_the_worker(
        store: JobStore, settings: Settings, main_renews: bool) -> None:
    # A real process takes a 1 s lease and then starves its own heartbeat thread for 4 s;
    # this test plays its worker's main process, renewing the leases of its busy pool process.
    child = subprocess.Popen(
        [sys.executable, "-c", _GIL_HOG, str(settings.data_dir), settings.database_url or "",
         JOB, "4"], cwd=ROOT, stdout=subprocess.PIPE, text=True,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "holding"
        lapsed = False
        deadline = time.monotonic() + 3.5
        while child.poll() is None and time.monotonic() < deadline:
            if main_renews:
                renew_held_by(store.sessions, [child.pid], 1.0)
            lapsed = lapsed or bool(lapsed_leases(store.sessions, utcnow()))
            time.sleep(0.2)
        assert lapsed is not main_renews  # without the main process's beat, it would lapse
    finally:
        child.kill()
        child.wait(10)


def test_a_job_says_when_no_worker_consumes_its_queue(store: JobStore, settings: Settings
                                                      ) -> None:
    heartbeat_s = settings.worker_heartbeat_s
    sessions = store.sessions
    announce(sessions, "w-validate", "validate.1@host", 1, ["validate"])
    announce(sessions, "w-old", "cpu.2@host", 2, ["cpu", "gpu"], now=_later(-60))  # went quiet
    assert live_queues(sessions, heartbeat_s) == frozenset({"validate"})

    job = _job(store)
    assert job.state == "queued" and waiting_queue(job) == "cpu"
    reason = waiting_reason(job, lambda: live_queues(sessions, heartbeat_s))
    assert reason == ("no worker consumes the 'cpu' queue; start one with "
                      "`volumesh worker --queues cpu`")

    announce(sessions, "w-cpu", "cpu.3@host", 3, ["cpu"])
    assert waiting_reason(_job(store), lambda: live_queues(sessions, heartbeat_s)) is None

    # Between stages a job waits on its next stage's queue: the enhance stage's is gpu.
    assert store.start_stage(JOB, 0, "filter", "t", "w-cpu", 30)
    assert store.finish_stage(JOB, 0, "filter", 1.0, 0.25)
    assert store.start_stage(JOB, 1, "align", "t", "w-cpu", 30)
    asked: list[bool] = []

    def consumed() -> frozenset[str]:
        asked.append(True)
        return live_queues(sessions, heartbeat_s)

    assert waiting_reason(_job(store), consumed) is None and not asked  # a stage runs
    assert store.finish_stage(JOB, 1, "align", 1.0, 0.5)
    with Heartbeat(sessions, JOB, "w-cpu", 30):
        pass
    assert waiting_queue(_job(store)) == "gpu"
    assert "'gpu' queue" in (waiting_reason(_job(store), consumed) or "")
    retire(sessions, "w-validate")
    assert live_queues(sessions, heartbeat_s) == frozenset({"cpu"})
