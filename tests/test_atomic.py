"""Atomic writes (subslope.io.atomic): complete or absent, umask permissions, and the
temporaries of killed writers removed by the next write."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from subslope.io.atomic import atomic_write, remove_stale_temporaries, write_text


def test_a_failed_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    out = write_text(tmp_path / "r.csv", "good\n")
    with pytest.raises(RuntimeError), atomic_write(out) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full")
    assert out.read_text() == "good\n"
    assert [p.name for p in tmp_path.iterdir()] == ["r.csv"]
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask


def test_the_temporary_of_a_killed_writer_is_removed_by_the_next_write(tmp_path):
    out = tmp_path / "shard_0.h5"
    code = (
        "import os, sys, time\n"
        "from subslope.io.atomic import atomic_write\n"
        "with atomic_write(sys.argv[1]) as tmp:\n"
        "    tmp.write_bytes(b'partial')\n"
        "    print(tmp, flush=True)\n"
        "    time.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True
    )
    left = proc.stdout.readline().strip()
    assert os.path.exists(left)
    # a live writer's temporary is kept
    assert remove_stale_temporaries(out) == []
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert os.path.exists(left) and not out.exists()
    other_host = tmp_path / ".shard_0.h5.otherhost.1.abc.tmp"
    other_host.write_bytes(b"")
    write_text(out, "complete")
    assert out.read_text() == "complete"
    assert not os.path.exists(left)
    assert other_host.exists()  # another host's writer may still be running


def test_stale_temporaries_anywhere_under_a_folder_go_at_the_start_of_a_run(tmp_path):
    """A shard-sized temporary of a killed job is removed when the workflow starts, not
    only when that shard is written again; a live writer's stays."""
    from subslope.io.atomic import remove_stale_temporaries_under, temporary_path

    deep = tmp_path / "results" / "simulate_shard" / "train"
    code = (
        "import sys; from subslope.io.atomic import temporary_path; "
        "print(temporary_path(sys.argv[1]))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(deep / "shard_0.h5")], capture_output=True, text=True
    )
    dead = Path(out.stdout.strip())
    assert dead.exists()
    live = temporary_path(deep / "shard_1.h5")
    assert remove_stale_temporaries_under(tmp_path / "results") == [dead]
    assert not dead.exists() and live.exists()
