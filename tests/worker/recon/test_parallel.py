import threading

import numpy as np
import pytest

from worker.recon.parallel import run_blocks


@pytest.mark.parametrize("workers", [1, 2, 4])
def test_every_block_is_processed_once(workers):
    out = np.zeros(100)
    calls = []

    def work(start):
        calls.append(start)
        out[start : start + 10] += 1

    run_blocks(work, range(0, 100, 10), workers=workers)
    assert sorted(calls) == list(range(0, 100, 10))
    assert np.all(out == 1)


def test_single_worker_runs_in_the_calling_thread_in_order():
    seen = []
    run_blocks(lambda s: seen.append((s, threading.get_ident())), [3, 1, 2], workers=1)
    assert [s for s, _ in seen] == [3, 1, 2]
    assert {t for _, t in seen} == {threading.get_ident()}


@pytest.mark.parametrize("workers", [1, 2])
def test_an_error_in_a_block_reaches_the_caller(workers):
    def work(start):
        if start == 2:
            raise ValueError("block 2")

    with pytest.raises(ValueError, match="block 2"):
        run_blocks(work, range(4), workers=workers)
