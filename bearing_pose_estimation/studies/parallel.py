"""Independent batch runs on a process pool, for the studies (``montecarlo``, ``noise-study``);
no rclpy."""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

R = TypeVar('R')


def run_all(func: Callable[..., R], calls: Sequence[tuple[Any, ...]], jobs: int | None = None,
            progress: Callable[[int, int, R], None] | None = None) -> list[R]:
    """``func(*args)`` for every ``args`` in ``calls`` on ``jobs`` processes (default: all
    cores), in order, ``progress(done, total, result)`` each; error or Ctrl-C: queue dropped."""
    jobs = min(jobs or os.cpu_count() or 1, len(calls))
    results: list[R | None] = [None] * len(calls)
    done = 0

    def finished(k: int, result: R) -> None:
        nonlocal done
        results[k], done = result, done + 1
        if progress is not None:
            progress(done, len(calls), result)

    if jobs <= 1:
        for k, args in enumerate(calls):
            finished(k, func(*args))
        return results  # type: ignore[return-value]
    pool = ProcessPoolExecutor(max_workers=jobs)
    try:
        futures = {pool.submit(func, *args): k for k, args in enumerate(calls)}
        for fut in as_completed(futures):
            finished(futures[fut], fut.result())
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return results  # type: ignore[return-value]
