"""The run's read-ahead: each frame read, preprocessed and given to the method's `ahead` on a
worker at the lowest priority while the frame before is processed, in order, with what the frame
waited for accounted by stage; and the run's malloc setting (freed memory kept for reuse)."""
import os
import subprocess
import sys
from pathlib import Path
import threading

import pytest

from conftest import write_sequence
from surfelwarp.errors import InputError
from surfelwarp.io.sequence import open_sequence
from surfelwarp.preprocess import PreprocessParams
from surfelwarp.run import _read_ahead


class Recorder:
    """A method's `ahead` that notes the frame, its thread and that thread's nice value, and
    can be held until the frame before says go."""

    def __init__(self, hold_at: int | None = None):
        self.calls, self.hold_at, self.go = [], hold_at, threading.Event()

    def ahead(self, obs):
        native = threading.get_native_id()
        nice = os.getpriority(os.PRIO_PROCESS, native) if sys.platform.startswith("linux") else None
        self.calls.append((obs.frame_index, threading.current_thread() is threading.main_thread(), nice))
        if obs.frame_index == self.hold_at:
            assert self.go.wait(10.0), "the frame before never ran beside this one"


def test_every_frame_in_order_read_ahead_on_a_low_priority_worker(tmp_path):
    seq = open_sequence(write_sequence(tmp_path / "seq", frames=range(4)))
    method = Recorder()
    got = list(_read_ahead(seq, 1, PreprocessParams(), method))
    assert [(g[0], g[1].index, g[4].frame_index) for g in got] == [(1, 1, 1), (2, 2, 2), (3, 3, 3)]
    assert [c[:2] for c in method.calls] == [(1, False), (2, False), (3, False)]
    if sys.platform.startswith("linux"):
        assert {c[2] for c in method.calls} == {19}
    assert os.getpriority(os.PRIO_PROCESS, 0) < 19              # the frame's own thread keeps its priority
    for *_, waited, took in got:      # the tail of the job, its last stages first
        assert list(waited) == list(took) == ["read", "preprocess", "ahead"]
        assert min(waited.values()) >= 0.0
        assert waited["ahead"] <= took["ahead"] and waited["preprocess"] <= took["preprocess"]
        assert waited["preprocess"] == 0.0 or waited["ahead"] == took["ahead"]
        assert waited["read"] == 0.0 or waited["preprocess"] == took["preprocess"]
    # the first frame waited for its whole job: nothing ran before it
    first_waited, first_took = got[0][5], got[0][6]
    assert sum(first_waited.values()) >= sum(first_took.values())


def test_the_next_frame_is_read_ahead_while_this_one_is_processed(tmp_path):
    seq = open_sequence(write_sequence(tmp_path / "seq", frames=range(3)))
    method = Recorder(hold_at=1)
    frames = _read_ahead(seq, 0, PreprocessParams(), method)
    next(frames)                    # frame 0 in hand: frame 1's `ahead` is under way
    method.go.set()                 # ... and finishes only now, during frame 0 (else it times out)
    rest = [g[0] for g in frames]
    assert rest == [1, 2] and [c[0] for c in method.calls] == [0, 1, 2]


def test_a_bad_frame_is_reported_at_its_turn(tmp_path):
    root = write_sequence(tmp_path / "seq", frames=range(3))
    seq = open_sequence(root)
    (root / seq.files[2].depth.name).write_bytes(b"not a png")
    frames = _read_ahead(seq, 0, PreprocessParams(), Recorder())
    assert [next(frames)[0], next(frames)[0]] == [0, 1]         # frame 2 was read during frame 1
    with pytest.raises(InputError, match=seq.files[2].depth.name):
        next(frames)


FAULTS_OF_CYCLES = """
import resource
import numba
import numpy as np
from surfelwarp.run import keep_freed_memory

@numba.njit
def block():        # a compiled kernel's array: malloc'd, not madvised to huge pages as numpy's
    return np.ones(1 << 22)

def faults_of_cycles():
    block()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(2):      # two 32 MB blocks written and freed
        block()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

default = faults_of_cycles()
took = keep_freed_memory()
print(default, took, faults_of_cycles())
"""


def _faults_of_cycles(env: dict) -> tuple[int, bool, int]:
    out = subprocess.run([sys.executable, "-c", FAULTS_OF_CYCLES], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    return int(out[0]), out[1] == "True", int(out[2])


THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
@pytest.mark.skipif(THP.is_file() and "[always]" in THP.read_text(), reason="every large block on huge pages")
def test_freed_memory_is_reused_without_page_faults():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    default, took, kept = _faults_of_cycles(env)
    if not took:
        pytest.skip("the C library has no glibc mallopt")
    pages = 2 * (1 << 25) // os.sysconf("SC_PAGE_SIZE")
    assert default > 0.9 * pages                # each block mapped afresh: every page faults
    assert kept < 0.05 * pages                  # the freed block reused


def test_a_malloc_setting_of_the_user_is_kept():
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    env["MALLOC_TRIM_THRESHOLD_"] = str(128 * 1024)
    _, took, _ = _faults_of_cycles(env)
    assert not took
