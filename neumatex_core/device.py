"""Device choice, written once: CUDA when present, else CPU. All core code is device-agnostic. And how independent
pieces of work share the CPU's torch threads (`side_by_side`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import torch

T = TypeVar("T")


def default_device() -> torch.device:
    """The device new tensors go to unless a caller says otherwise."""
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def resolve_device(name: str = "auto") -> torch.device:
    """The torch device a config names: "auto" is `default_device()`, anything else ("cpu", "cuda", "cuda:1") as
    given."""
    return default_device() if name == "auto" else torch.device(name)


def side_by_side(tasks: Sequence[Callable[[], T]], device: torch.device) -> list[T]:
    """The tasks' results (in order). On the CPU with at least one torch thread per task they run side by side, each in
    its own Python thread on an equal share of torch's threads (torch releases the GIL inside its operations), and
    torch's thread count is restored afterwards; else (one thread, or a GPU) one after the other. A neural TTO
    phase's small operations leave a second torch thread idle much of the time, so two of them on 2 cores take 1.77x
    one on both instead of 2x (the demo's choice: 56 -> 50 s; docs/design-notes.md item 44). The tasks must share
    nothing they write. A task's numbers depend on the threads it runs on, as any torch computation's: the same
    settings on one machine give the same bits."""
    if not runs_side_by_side(len(tasks), device):
        return [task() for task in tasks]
    with torch_threads(torch.get_num_threads() // len(tasks)):
        with ThreadPoolExecutor(len(tasks), thread_name_prefix="side-by-side") as pool:
            futures = [pool.submit(task) for task in tasks]
            return [future.result() for future in futures]


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op thread count set to `count` inside the block and restored after it (also on an error): e.g.
    one thread where a number must come out bit for bit the same whatever the caller's count."""
    threads = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def runs_side_by_side(n_tasks: int, device: torch.device) -> bool:
    """Whether `side_by_side` runs n_tasks tasks at once: on the CPU with at least one torch thread per task."""
    return n_tasks >= 2 and device.type == "cpu" and torch.get_num_threads() >= n_tasks
