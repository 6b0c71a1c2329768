"""A first compile you can watch: kernels compiled against the plan, time spent, time left.

numba compiles a stepping method's kernels in one call tree that may take minutes on a cold
cache, printing nothing. :class:`CompileProgress` (started by :mod:`.jit` when the first
package kernel starts compiling) counts every package kernel that becomes ready (compiled here,
or loaded from what the compile-ahead helper compiled: ``ahead.ready_hook``) and shows, while
the compiler is busy: on a terminal a tqdm bar refreshed twice a second, otherwise a line every
:data:`LINE_INTERVAL_S` seconds. With the method's compile plan (``plans/<method>.json``: the
kernels a first run compiles and each one's recorded time) it knows how many kernels the run
needs and estimates the time left from the recorded times of those still to come, scaled by how
fast the ones done went on this machine. It stops, with one closing line, once the compiler has
been idle for :data:`IDLE_S` seconds. It imports nothing else of feeder_sim.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import TextIO

LINE_INTERVAL_S = 5.0      # without a terminal: a line at least this often
IDLE_S = 1.5               # no compile for this long: the first compile is over
_TICK_S = 0.5


class CompileProgress:
    """Counts package kernels as they become ready and reports them from a daemon thread.

    ``plan``: ``(kernel, recorded compile time in s)`` of each kernel a first run needs, or
    None without a plan. ``busy``: whether numba's compiler lock is held."""

    def __init__(self, plan: list[tuple[str, float]] | None, busy,
                 stream: TextIO = sys.stderr, tty: bool | None = None) -> None:
        self.costs: dict[str, list[float]] = {}
        for name, cost in plan or ():
            self.costs.setdefault(name, []).append(cost)
        self.total_s = sum(cost for _, cost in plan or ())
        self.busy = busy
        self.stream = stream
        self.tty = stream.isatty() if tty is None else tty
        self.done = 0
        self.done_s = 0.0          # recorded compile time of the planned kernels ready
        self.start_s = time.perf_counter()
        self._last_busy_s = self.start_s
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name='compile-progress', daemon=True)

    def compiled(self, name: str | None = None) -> None:
        with self._lock:
            self.done += 1
            left = self.costs.get(name)
            if left:
                self.done_s += left.pop()
            self._last_busy_s = time.perf_counter()

    def fraction(self) -> float | None:
        """The share of the plan's recorded compile time done (None: no plan)."""
        return min(1.0, self.done_s / self.total_s) if self.total_s > 0.0 else None

    def left_s(self, elapsed_s: float) -> float | None:
        """Estimated seconds still to compile, at the pace of those done (None: no plan, or
        nothing done to scale by)."""
        share = self.fraction()
        return None if not share else elapsed_s * (1.0 - share) / share

    def text(self) -> str:
        elapsed = time.perf_counter() - self.start_s
        share, left = self.fraction(), self.left_s(elapsed)
        planned = f' ({100 * share:.0f} % of the plan)' if share is not None else ''
        rest = f', about {left:.0f} s left' if left is not None else ''
        return f'compiling kernels: {self.done} done{planned}, {elapsed:.0f} s{rest}'

    def start(self) -> None:
        self._thread.start()

    def running(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        bar = None
        if self.tty:
            from tqdm import tqdm

            bar = tqdm(total=100 if self.total_s else None, file=self.stream,
                       desc='compiling kernels', leave=False,
                       bar_format='{desc}: {bar} {elapsed}{postfix}')
        last_line = time.perf_counter()
        while True:
            time.sleep(_TICK_S)
            now = time.perf_counter()
            if self.busy():
                self._last_busy_s = now
            elif now - self._last_busy_s > IDLE_S:
                break
            if bar is not None:
                share, left = self.fraction(), self.left_s(now - self.start_s)
                bar.n = round(100 * share) if share is not None else self.done
                bar.set_postfix_str(f'{self.done} kernels' + (
                    '' if left is None else f', about {left:.0f} s left'), refresh=False)
                bar.refresh()
            elif now - last_line >= LINE_INTERVAL_S:
                print(self.text(), file=self.stream, flush=True)
                last_line = now
        if bar is not None:
            bar.close()
        elapsed = self._last_busy_s - self.start_s
        kernels = 'kernel' if self.done == 1 else 'kernels'
        print(f'compiled {self.done} {kernels} in {elapsed:.0f} s', file=self.stream, flush=True)


def plan_costs(plan: dict | None) -> list[tuple[str, float]] | None:
    """``(kernel, recorded compile time in s)`` of the plan's kernels (the helper's share
    included: the run loads those as it reaches them)."""
    return [(item['kernel'], item['cost_s']) for item in plan['items']] if plan else None


def wanted() -> bool:
    """Progress is shown unless FEEDER_SIM_COMPILE_PROGRESS=0."""
    return os.environ.get('FEEDER_SIM_COMPILE_PROGRESS', '1').strip() != '0'
