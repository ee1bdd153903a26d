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


PARAM_JOB = """
import os, signal, sys
from subslope.logs import log_to_file
log_to_file("job.log", outputs=["out/a.txt"], params={"p": sys.argv[2]})
os.makedirs("out", exist_ok=True)
open("out/a.txt", "w").write("made with p = " + sys.argv[2] if sys.argv[1] == "ok" else "half")
if sys.argv[1] == "kill":
    os.kill(os.getpid(), signal.SIGKILL)
"""


def _param_job(tmp_path, how, p):
    return subprocess.run(
        [sys.executable, "-c", PARAM_JOB, how, p], cwd=tmp_path, capture_output=True
    )


def test_an_interrupted_rerun_of_the_same_parameters_keeps_the_restored_output(tmp_path):
    """Snakemake puts an update() output back after a failed job (as a fresh copy): it is
    correct, and left as it is, when a finished job of the same parameters wrote it; it
    is aged when the interrupted job had other parameters or the file is another."""
    out = tmp_path / "out" / "a.txt"
    assert _param_job(tmp_path, "ok", "1").returncode == 0
    made, made_at = out.read_text(), out.stat().st_mtime_ns

    def interrupted(p, restored):
        assert _param_job(tmp_path, "kill", p).returncode != 0
        out.write_text(restored)  # what Snakemake's restore does: a copy of the backup
        return mark_unfinished_outputs(tmp_path)

    assert interrupted("1", made) == []  # the same parameters: nothing reruns
    assert not list((tmp_path / RECORDS).glob("*.json"))
    assert out.stat().st_mtime_ns == made_at  # as made: what follows it stays up to date
    assert interrupted("2", made) == [out]  # the config changed: the job runs again
    os.utime(out)
    assert interrupted("1", "another file") == [out]  # not what the job made
