"""Progress of ensembles, regions and calibrations: a counter with the time left on a
terminal, nothing in a log (not a terminal) nor with -q."""

from __future__ import annotations

import io

import pytest

import avflow.ensemble.orchestrate as orchestrate
from avflow.ensemble.orchestrate import ProgressLine, time_left
from avflow.region.orchestrate import RegionProgress


class Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.fixture
def clock(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(orchestrate.time, "perf_counter", lambda: now[0])
    return now


def test_time_left_at_the_pace_so_far():
    assert time_left(10.0, 0, 20) == ""
    assert time_left(10.0, 20, 20) == ""
    assert time_left(10.0, 5, 20) == ", ~30 s left"        # 2 s a run, 15 to go
    assert time_left(60.0, 2, 10) == ", ~4 min 00 s left"
    assert time_left(3600.0, 1, 3) == ", ~2 h 00 min left"
    assert time_left(0.3, 3, 4) == ", <1 s left"


def test_ensemble_line_counts_members_and_says_the_time_left(clock):
    term = Terminal()
    line = ProgressLine(10, stream=term)
    line.update(4, 0)           # 4 reused from an earlier run: not in the pace
    clock[0] += 12.0
    line.update(7, 1)           # 3 run in 12 s: 3 to go, ~12 s
    text = term.getvalue().split("\r")[-1]
    assert "7/10 members, 1 failed" in text and "~12 s left" in text


@pytest.mark.parametrize("stream, quiet", [(io.StringIO(), False), (Terminal(), True)])
def test_nothing_in_a_log_nor_when_quiet(stream, quiet, clock):
    line = ProgressLine(10, stream=stream, quiet=quiet)
    for k in range(1, 11):
        clock[0] += 1.0
        line.update(k, 0)
    line.close()
    assert stream.getvalue() == ""
    region = RegionProgress(3, 100.0, stream=stream, quiet=quiet)
    region.update({"id": 1, "status": "ok", "row0": 0, "row1": 2, "col0": 0, "col1": 2})
    region.close()
    assert stream.getvalue() == ""


def test_region_line_says_the_time_left_of_the_runs_still_to_go(clock):
    term = Terminal()
    region = RegionProgress(4, 100.0, stream=term)
    region.update({"id": 9, "status": "ok", "reused": True, "row0": 0, "row1": 1, "col0": 0,
                   "col1": 1})
    clock[0] += 10.0
    region.update({"id": 1, "status": "ok", "reused": False, "row0": 0, "row1": 2, "col0": 0,
                   "col1": 2})
    text = term.getvalue().split("\r")[-1]
    assert "2/4 releases, 0 failed" in text and "~20 s left" in text  # 10 s a run, 2 to go
