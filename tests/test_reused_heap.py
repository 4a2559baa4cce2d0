"""nimbus.utils.memory.reused_heap: freed large blocks stay in malloc's heap while training, and go back after."""

import sys

import pytest
import torch

from nimbus.utils import memory
from nimbus.utils.memory import REUSED_HEAP_ENV, reused_heap, status_kb

needs_glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or memory._glibc() is None
                                 or status_kb("VmRSS") is None, reason="glibc on Linux with /proc")

MB = 2**20
BLOCK = 96 * MB  # far above glibc's largest mmap threshold (32 MiB)


def _rss_after_free() -> int:
    """VmRSS (kB) gained by allocating and touching BLOCK bytes, then freeing them."""
    before = status_kb("VmRSS")
    t = torch.empty(BLOCK // 4, dtype=torch.float32)
    t.fill_(1.0)  # touch every page
    del t
    return status_kb("VmRSS") - before


@needs_glibc
def test_freed_blocks_stay_while_the_block_runs_and_go_back_after(monkeypatch):
    monkeypatch.delenv(REUSED_HEAP_ENV, raising=False)
    assert _rss_after_free() < BLOCK // 1024 // 4  # outside: the block is unmapped when freed
    with reused_heap() as active:
        assert active
        gains = [_rss_after_free() for _ in range(16)]
        assert gains[0] > BLOCK // 1024 * 3 // 4  # inside: kept for reuse
        # ... and reused: an aligned request (torch's) may not fit the freed block exactly until free blocks
        # coalesce, which took up to 6 rounds here; then no new pages
        assert min(gains) < BLOCK // 1024 // 4, gains
        before_exit = status_kb("VmRSS")
    assert status_kb("VmRSS") < before_exit - BLOCK // 1024 * 3 // 4  # given back on leaving
    assert memory._heap_users == 0


@needs_glibc
def test_nested_blocks_keep_the_setting_until_the_outer_one_ends(monkeypatch):
    monkeypatch.delenv(REUSED_HEAP_ENV, raising=False)
    with reused_heap():
        with reused_heap() as inner:
            assert inner
        assert memory._heap_users == 1
        before = status_kb("VmRSS")
        _rss_after_free()
        assert status_kb("VmRSS") - before > BLOCK // 1024 * 3 // 4  # still in force after the inner block left
    assert memory._heap_users == 0


def test_off_by_argument_or_environment(monkeypatch):
    with reused_heap(False) as active:
        assert not active
    monkeypatch.setenv(REUSED_HEAP_ENV, "0")
    with reused_heap() as active:
        assert not active
    assert memory._heap_users == 0


@needs_glibc
def test_an_exception_inside_restores_the_defaults(monkeypatch):
    monkeypatch.delenv(REUSED_HEAP_ENV, raising=False)
    with pytest.raises(RuntimeError):
        with reused_heap():
            raise RuntimeError("boom")
    assert memory._heap_users == 0


@needs_glibc
def test_a_cpu_training_loop_runs_inside_it_and_leaves_it(make_scene, tmp_path, monkeypatch):
    from nimbus.train.config import TrainConfig
    from nimbus.train.runner import Runner

    monkeypatch.delenv(REUSED_HEAP_ENV, raising=False)
    cfg = TrainConfig(iterations=3, sh_degree=0, densify_from=100, densify_until=100, log_interval=1,
                      opacity_reset_interval=1000)
    runner = Runner("3dgs", make_scene(), cfg, tmp_path / "run", seed=0, progress=False,
                    device=torch.device("cpu"))
    seen = []
    step = runner.method.train_iteration
    monkeypatch.setattr(runner.method, "train_iteration", lambda it: (seen.append(memory._heap_users), step(it))[1])
    runner.train()
    assert seen == [1, 1, 1]
    assert memory._heap_users == 0
