"""Trace chunks evaluated on worker threads, their results in chunk order (``SurfaceModel``'s
predictions and Gauss-Newton products: the chunks' sums are added in that order, so the numbers
are the same bit for bit whatever the number of threads)."""
from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor

__all__ = ["run_chunks"]


def run_chunks(fn, chunks: list, workers: int):
    """``fn(t0, t1)`` over ``chunks`` ((t0, t1) pairs), results yielded in chunk order: on
    ``workers`` threads (at most two chunks per thread submitted and not yet consumed, which
    bounds the memory of results waiting for their turn), else serially."""
    if workers == 1 or len(chunks) == 1:
        for c in chunks:
            yield fn(*c)
        return
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="surface-chunk") as ex:
        todo, running = iter(chunks), deque()
        for c in todo:
            running.append(ex.submit(fn, *c))
            if len(running) >= 2 * workers:
                break
        while running:
            out = running.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                running.append(ex.submit(fn, *nxt))
            yield out
