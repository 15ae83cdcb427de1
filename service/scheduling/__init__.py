"""The parts of :class:`service.scheduler.AnalysisScheduler`: the round grid and buffer
sync (:mod:`.rounds`), executor jobs and retries (:mod:`.jobs`), and storing results
with alarms and tickets (:mod:`.results`)."""
