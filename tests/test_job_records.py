"""Records of jobs that started and did not finish (subslope.logs): a failed or killed
job leaves its record, a finished one removes it, and the workflow makes the outputs of
an unfinished job older than any input so that the job runs again."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from subslope.logs import RECORDS, job_started, mark_unfinished_outputs

JOB = """
import sys
from subslope.logs import log_to_file
log_to_file("job.log", outputs=["out/a.txt", "out/b.txt"])
if sys.argv[1] == "fail":
    raise RuntimeError("the job fails")
if sys.argv[1] == "kill":
    import os, signal
    os.kill(os.getpid(), signal.SIGKILL)
"""


def _run(tmp_path, how):
    return subprocess.run([sys.executable, "-c", JOB, how], cwd=tmp_path, capture_output=True)


@pytest.mark.parametrize("how", ["fail", "kill"])
def test_a_failed_or_killed_job_leaves_its_record(tmp_path, how):
    assert _run(tmp_path, how).returncode != 0
    (record,) = (tmp_path / RECORDS).glob("*.json")
    assert "out/a.txt" in record.read_text()


def test_a_finished_job_removes_its_record(tmp_path):
    assert _run(tmp_path, "ok").returncode == 0
    assert not list((tmp_path / RECORDS).glob("*.json"))


def test_outputs_of_an_unfinished_job_become_older_than_any_input(tmp_path):
    (tmp_path / "out").mkdir()
    for name in ("a.txt", "other.txt"):
        (tmp_path / "out" / name).write_text("previous version")
    job_started(["out/a.txt", "out/b.txt"], root=tmp_path)  # this process does not exit
    marked = mark_unfinished_outputs(tmp_path)
    assert marked == [tmp_path / "out" / "a.txt"]  # b.txt does not exist: nothing to mark
    assert os.stat(tmp_path / "out" / "a.txt").st_mtime == 0
    assert os.stat(tmp_path / "out" / "other.txt").st_mtime > 0
    assert (tmp_path / "out" / "a.txt").read_text() == "previous version"
    assert mark_unfinished_outputs(tmp_path) == []  # once is enough


def test_a_job_whose_outputs_were_put_in_place_is_forgotten(tmp_path):
    from subslope.logs import forget_jobs_of

    job_started(["resources/hst/x.npy"], root=tmp_path)
    job_started(["out/a.txt", "out/b.txt"], root=tmp_path)
    assert forget_jobs_of([], root=tmp_path) == 0
    assert forget_jobs_of(["out/a.txt"], root=tmp_path) == 0  # b.txt is still the job's
    assert forget_jobs_of(["./resources/hst/x.npy"], root=tmp_path) == 1
    (record,) = (tmp_path / RECORDS).glob("*.json")
    assert "out/a.txt" in record.read_text()
