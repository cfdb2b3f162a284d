"""Each thread's CPU and wake-ups in a running process, from /proc (Linux): where a process's CPU goes
that py-spy does not see (libzmq's I/O threads, native threads, the kernel) and how often each thread wakes.

``snapshot(pid)`` reads every thread's time on a CPU (``schedstat``, ns), its share in the kernel
(``stat``'s stime over utime + stime, in clock ticks), its time waiting for a CPU while runnable
(``schedstat``: py-spy counts that as busy too) and its voluntary context switches (``status``: each
is a sleep, so a wake-up); the difference of two snapshots, per thread name (``comm``: libzmq names its
threads ``ZMQbg/IO/0``, ``ZMQbg/Reaper``; Python 3.11's threads are all named after the process), is
what the process did between them.
"""
from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import NamedTuple


class Sample(NamedTuple):
    name: str
    run_ns: int  # on a CPU
    wait_ns: int  # runnable, waiting for a CPU
    user_ticks: int
    system_ticks: int
    switches: int  # voluntary context switches: sleeps


def snapshot(pid: int) -> dict[int, Sample]:
    """Per thread id; threads gone meanwhile are left out."""
    threads = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            run_ns, wait_ns = (int(v) for v in (task / "schedstat").read_text().split()[:2])
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            status = (task / "status").read_text()
        except (OSError, ValueError):
            continue
        switches = next((int(line.split()[1]) for line in status.splitlines()
                         if line.startswith("voluntary_ctxt_switches")), 0)
        threads[int(task.name)] = Sample(name, run_ns, wait_ns, int(fields[11]), int(fields[12]), switches)
    return threads


def difference(before: dict[int, Sample], after: dict[int, Sample], main_pid: int) -> dict[str, Sample]:
    """What each thread did between two snapshots, by name; the main thread is named ``main``."""
    totals: dict[str, Counter[str]] = {}
    for tid, now in after.items():
        then = before.get(tid, Sample(now.name, 0, 0, 0, 0, 0))
        label = "main" if tid == main_pid else now.name
        total = totals.setdefault(label, Counter())
        for field in Sample._fields[1:]:
            total[field] += getattr(now, field) - getattr(then, field)
    return {label: Sample(label, **t) for label, t in totals.items()}


def describe(threads: dict[str, Sample], seconds: float, chunks: float) -> str:
    """One line: per thread, CPU-s per hour, its kernel share, waiting for a CPU, and wake-ups per chunk."""
    def line(t: Sample) -> str:
        system = t.system_ticks / max(1, t.user_ticks + t.system_ticks)
        return (f"{t.name} {t.run_ns / 1e9 * 3600 / seconds:.0f} CPU-s/h ({system:.0%} kernel, "
                f"{t.wait_ns / 1e9 * 3600 / seconds:.0f} s/h waiting) {t.switches / chunks:.2f} wake-ups/chunk")
    return ", ".join(line(t) for t in sorted(threads.values(), key=lambda t: -t.run_ns))


def alive(pid: int) -> bool:
    return os.path.exists(f"/proc/{pid}/task")
