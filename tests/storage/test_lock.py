"""One process at a time on a data directory (storage.lock, docs/design/service.md §4.1)."""

from __future__ import annotations

import os
import threading

import pytest

from storage.lock import DataDirInUse, DataDirLock


def test_a_second_holder_is_refused_naming_the_first_and_takes_it_once_let_go(tmp_path):
    first = DataDirLock(tmp_path / ".lock").acquire()
    with pytest.raises(DataDirInUse, match=f"pid {os.getpid()}"):
        DataDirLock(tmp_path / ".lock").acquire()
    first.release()
    DataDirLock(tmp_path / ".lock").acquire().release()


def test_deleting_the_lock_file_does_not_let_a_second_process_in(tmp_path):
    # an outside test: with the lock on a file, `rm .lock` let a second server in, which deleted the
    # first's live map; the lock is the directory's
    first = DataDirLock(tmp_path / ".lock").acquire()
    (tmp_path / ".lock").unlink()
    with pytest.raises(DataDirInUse):
        DataDirLock(tmp_path / ".lock").acquire()
    first.release()


def test_the_pid_is_never_written_through_a_link(tmp_path):
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep me")
    (tmp_path / ".lock").symlink_to(target)
    DataDirLock(tmp_path / ".lock").acquire().release()
    assert target.read_text() == "keep me"


def test_a_waiting_holder_takes_the_lock_when_the_first_lets_go(tmp_path):
    first = DataDirLock(tmp_path / ".lock").acquire()
    letting_go = threading.Timer(0.3, first.release)
    letting_go.start()
    try:
        DataDirLock(tmp_path / ".lock").acquire(wait_s=30).release()
    finally:
        letting_go.join()
