"""The scheduler: one loop's failure or hang never holds up the others; housekeeping;
a new installation analyses the history it holds."""

import math
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import pytest
from sqlalchemy import func, select

from service.analysis import analyse_window
from service.store.models import AnalysisRun, Sample, Ticket
from tests.service.test_api import T0, simulated_batch


class SabotagingExecutor(ThreadPoolExecutor):
    """A real thread pool that makes the analysis of one loop fail or hang.

    The other loops' analyses are run once in the caller before they are submitted, so
    their JIT is compiled before the limit's clock starts (a cold cache takes ~30 s) and
    a short limit still leaves them ample time."""

    def __init__(self, loop_id: str, mode: str) -> None:
        super().__init__(3)  # a hung job and its retry hold two threads till the test ends
        self.loop_id, self.mode = loop_id, mode
        self.release = threading.Event()  # ends the hang when the test is over

    def submit(self, fn, /, *args, **kwargs) -> Future:
        if fn is analyse_window and args[0]["id"] != self.loop_id:
            fn(*args, **kwargs)
        if fn is analyse_window and args[0]["id"] == self.loop_id:
            if self.mode == "fail":
                def fail(*_a, **_k):
                    raise RuntimeError("worker crashed")
                return super().submit(fail)
            return super().submit(self.release.wait, 120.0)
        return super().submit(fn, *args, **kwargs)


@pytest.mark.parametrize(("mode", "status", "error", "retries"), [
    ("fail", "failed", "RuntimeError: worker crashed", 0),  # an analysis error: no retry
    ("hang", "timeout", "analysis took longer than 4 s, on its retry too", 1),
])
def test_one_loop_failing_or_hanging_does_not_stop_the_others(make_service, mode, status,
                                                              error, retries):
    # The limit leaves the healthy loop (its JIT warm) ample time on a busy machine; the
    # hanging one waits until the test ends, so only the limit can end its wait (a thread
    # cannot be killed: the retry runs in the pool's other thread).
    svc = make_service(SabotagingExecutor("FIC-2", mode), analysis_timeout_s=4.0)
    svc.state.ingest(simulated_batch())
    runs = {r.loop_id: r for r in svc.scheduler.run_once(T0)}
    assert runs["FIC-1"].status == "ok" and runs["FIC-1"].verdict == "stiction"
    assert runs["FIC-2"].status == status
    with svc.state.store.session() as session:
        stored = session.scalars(select(AnalysisRun).where(AnalysisRun.loop_id == "FIC-2")).one()
        assert stored.error == error and stored.result is None
    assert svc.state.metrics.value("loopwatch_analyses_total", status=status) == 1
    assert svc.state.metrics.value("loopwatch_analysis_retries_total", cause="timeout") == retries
    assert svc.state.metrics.value("loopwatch_executor_replacements_total") == 0


def test_samples_past_the_retention_period_are_purged(make_service):
    svc = make_service(sample_retention_days=600 / 86400)
    svc.state.ingest(simulated_batch())
    with svc.state.store.session() as session:
        before = session.scalar(select(func.count()).select_from(Sample))
    svc.scheduler.maintain(T0)
    with svc.state.store.session() as session:
        after = session.scalar(select(func.count()).select_from(Sample))
        oldest = session.scalar(select(func.min(Sample.time)))
    assert before == 6 * 3600
    assert oldest >= T0 - 600
    assert after == 6 * 601  # T0 - 600 s to T0 inclusive
    assert svc.state.metrics.value("loopwatch_samples_purged_total") == before - after


@pytest.mark.parametrize(("confirmations", "tickets"), [(2, ["FV-1"]), (3, [])])
def test_a_new_installation_confirms_on_the_history_it_holds(make_service, confirmations,
                                                             tickets):
    # Tickets need stiction on windows that do not overlap, and on every window between
    # them (service.tickets).  With an hour of history and half-hour windows a new
    # installation analyses four windows (8 min apart) before the newest: the oldest ends
    # before the newest starts, enough for a ticket when two confirmations are needed, not
    # for three.
    svc = make_service(window_s=1800, analysis_interval_s=60,
                       ticket_confirmations=confirmations)
    newest = math.floor(T0 / 60) * 60
    assert svc.scheduler.due_rounds(T0) == [newest]  # nothing held yet: no history round
    svc.state.ingest(simulated_batch())  # the hour before T0: FIC-1 sticks, FIC-2 does not
    assert svc.scheduler.due_rounds(T0) == [newest - k * 480 for k in (4, 3, 2, 1, 0)]
    svc.scheduler.election = None  # the only scheduler: it leads
    done = svc.scheduler.run_due()
    # FIC-2's healthy valve hardly moves: too little travel to judge (issue 17).
    assert [(s.loop_id, s.verdict) for s in done] == [
        ("FIC-1", "stiction"), ("FIC-2", "undecided")] * 5
    with svc.state.store.session() as session:
        opened = session.scalars(select(Ticket)).all()
        assert [t.valve_asset for t in opened] == tickets
        if tickets:
            assert opened[0].malfunction_start == newest - 4 * 480 - 1800
            assert opened[0].evidence["confirmations"] == 2
    assert svc.scheduler.run_due() == []  # the history is not run again


def test_samples_not_yet_arrived_at_the_round_end_are_not_bad_data(make_service):
    """Issue 19: a round at T0 + 2 s whose last two samples the plant has not delivered yet
    analyses the window ending at the newest sample, with no NaN/inf finding; a silence
    longer than the analysis interval is still a gap the data-quality screen reports."""
    svc = make_service(window_s=1800, analysis_interval_s=60)
    svc.state.ingest(simulated_batch())
    (run,) = [r for r in svc.scheduler.run_once(T0 + 2) if r.loop_id == "FIC-1"]
    late = svc.scheduler.run_once(T0 + 120)
    with svc.state.store.session() as session:
        stored = session.get(AnalysisRun, run.run_id)
        assert stored.status == "ok" and stored.verdict == "stiction"
        assert stored.result["first_sample_at"] == T0 - 1800 + 1
        assert [i["message"] for i in stored.result["quality"]["issues"]
                if "NaN/inf" in i["message"]] == []
        gap = session.get(AnalysisRun, next(r.run_id for r in late if r.loop_id == "FIC-1"))
        assert any("NaN/inf" in i["message"] for i in gap.result["quality"]["issues"])
