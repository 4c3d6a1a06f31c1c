"""The test runs' pytest-xdist scheduler (tests/conftest.py registers it).

A worker that crashes (a segfault in native code: JAX's persistent-cache writer,
`executable.serialize()`, took one down in a CI run) must neither hang the run nor fail
it for good. pytest-xdist 3.8's file-grouped scheduling does both: a crashed worker's
whole workload goes back on the queue, finished files included, and a replacement given
such an empty unit (or a single test) waits for work forever (pytest-xdist issues #1323,
#1327, #1378); and it cannot put the crashed test back for pytest-rerunfailures. This
scheduler keeps the grouping by file (each file's tests share their compilations) and:
re-queues only unfinished tests, gives a worker at least two tests or a shutdown (a
worker runs a test only once it knows the next), and re-queues the crashed test when
pytest-rerunfailures asks (`--reruns` with `--only-rerun 'crashed while running'` in
pyproject.toml: a crash is re-run, at most twice; an ordinary failure is not).
"""

import pytest

try:
    from xdist.scheduler import LoadFileScheduling
except ImportError:  # the suite run without pytest-xdist (`-p no:xdist`)
    LoadFileScheduling = None


if LoadFileScheduling is not None:

    class CrashTolerantFileScheduling(LoadFileScheduling):
        def remove_node(self, node):
            workload = self.assigned_work.pop(node)
            if not self._pending_of(workload):
                return None
            crashitem = next(
                nodeid for unit in workload.values() for nodeid, done in unit.items() if not done
            )
            scope = self._split_scope(crashitem)
            workload[scope][crashitem] = True  # reported failed; re-queued only for a rerun
            for unit_scope, unit in workload.items():
                if not all(unit.values()):
                    self.workqueue[unit_scope] = unit
                    self.workqueue.move_to_end(unit_scope, last=False)
            for other in self.assigned_work:
                self._reschedule(other)
            return crashitem

        def mark_test_pending(self, item):
            scope = self._split_scope(item)
            unit = self.workqueue.setdefault(scope, {})
            unit[item] = False
            self.workqueue.move_to_end(scope, last=False)
            for other in self.assigned_work:
                self._reschedule(other)

        def _reschedule(self, node):
            if node.shutting_down or node not in self.registered_collections:
                return
            while self.workqueue and self._pending_of(self.assigned_work[node]) < 2:
                self._assign_work_unit(node)
            if not self.workqueue:
                node.shutdown()


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    if LoadFileScheduling is not None and config.getvalue("dist") == "loadfile":
        return CrashTolerantFileScheduling(config, log)
    return None
